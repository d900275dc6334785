"""Layouts: the original's size table, grid formulas and index orders."""

import numpy as np
import pytest
from pydantic import ValidationError

from services.world.layout import Layout, LayoutConfig, layout_for, named_sizes

# the original's size table: name -> (H, W, shelves S, goals G, action size 1+G+S, rack groups, highway cells, queue)
SIZES = {
    "tiny": (15, 14, 48, 6, 55, 3, 162, 20),
    "small": (25, 14, 96, 6, 103, 6, 254, 20),
    "medium": (25, 22, 160, 10, 171, 10, 390, 20),
    "large": (35, 22, 240, 10, 251, 15, 530, 40),
    "extralarge": (45, 30, 448, 14, 463, 28, 902, 60),
}


@pytest.mark.parametrize("name", list(SIZES))
def test_named_size_table(name):
    H, W, S, G, A, groups, highway, queue = SIZES[name]
    lay = Layout(LayoutConfig.named(name))
    assert (lay.H, lay.W) == (H, W)
    assert lay.num_shelves == len(lay.shelf_cells) == S
    assert lay.num_goals == G and lay.action_size == A
    assert len(lay.rack_groups) == groups
    assert len(lay.highway_cells) == int(lay.highway.sum()) == highway
    assert lay.config.request_queue_size == queue
    assert sum(len(g) for g in lay.rack_groups) == S


def test_named_sizes_have_default_fleets():
    fleets = {k: (a, p) for k, (_, a, p) in named_sizes().items()}
    assert fleets == {"tiny": (5, 3), "small": (8, 4), "medium": (12, 6), "large": (16, 8), "extralarge": (14, 7)}


def test_small_grid_picture():
    """The 'small' map as the original draws it."""
    lay = Layout(LayoutConfig.named("small"))
    rows = ["".join("." if lay.highway[y, x] else "#" for x in range(lay.W)) for y in range(lay.H)]
    assert rows[0] == rows[1] == ".............."
    assert all(rows[y] == "..##..##..##.." for y in list(range(2, 10)) + list(range(12, 20)))
    assert all(rows[y] == ".............." for y in (10, 11, 20, 21, 22, 23, 24))
    assert lay.goals == [(2, 24), (3, 24), (6, 24), (7, 24), (10, 24), (11, 24)]


def test_action_ids_goals_then_racks_column_major():
    lay = Layout(LayoutConfig.named("tiny"))
    assert lay.action_cells[0] is None
    assert lay.action_cells[1:7] == lay.goals
    # rack cells column-major: x = 2 column top to bottom, then x = 3, ...
    assert lay.action_cells[7:10] == [(2, 2), (2, 3), (2, 4)]
    assert lay.action_cells[7 + 8] == (3, 2)
    assert lay.action_cells[-1] == (11, 9)
    assert lay.cell_to_action_id((3, 2)) == 15
    with pytest.raises(ValueError, match="cell"):
        lay.cell_to_action_id((0, 0))
    with pytest.raises(ValueError, match="action"):
        lay.action_to_cell(0)


def test_shelf_ids_row_major():
    lay = Layout(LayoutConfig.named("tiny"))
    # in the original: shelf ids 47, 15, 37 sit at (10, 9), (6, 4), (2, 8)
    assert lay.shelf_cells[47 - 1] == (10, 9)
    assert lay.shelf_cells[15 - 1] == (6, 4)
    assert lay.shelf_cells[37 - 1] == (2, 8)
    assert lay.shelf_cells[:6] == [(2, 2), (3, 2), (6, 2), (7, 2), (10, 2), (11, 2)]


def test_rack_groups_by_column_block_then_row_block():
    lay = Layout(LayoutConfig.named("small"))
    firsts = [g[0] for g in lay.rack_groups]
    assert firsts == [(2, 2), (2, 12), (6, 2), (6, 12), (10, 2), (10, 12)]
    # within a group cells are column-major
    assert lay.rack_groups[0][:9] == [(2, y) for y in range(2, 10)] + [(3, 2)]
    assert all(len(g) == 16 for g in lay.rack_groups)


def test_highway_spawn_list_row_major():
    lay = Layout(LayoutConfig.named("tiny"))
    assert lay.highway_cells[:3] == [(0, 0), (1, 0), (2, 0)]
    assert lay.highway_cells[14:17] == [(0, 1), (1, 1), (2, 1)]
    assert lay.highway_cells[28:32] == [(0, 2), (1, 2), (4, 2), (5, 2)]


def test_custom_size_follows_formulas():
    cfg = LayoutConfig(shelf_columns=1, column_height=3, shelf_rows=2, request_queue_size=4)
    lay = layout_for(cfg)
    assert (lay.H, lay.W) == (2 + 5 * 2 + 3, 6)
    assert lay.num_shelves == 2 * 3 * 2
    assert layout_for(cfg) is lay
    assert np.array_equal(lay.highway[:, 2], [y % 5 < 2 or y >= lay.H - 3 for y in range(lay.H)])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(shelf_columns=4, column_height=8, shelf_rows=1, request_queue_size=5), "shelf_columns"),
        (dict(shelf_columns=0, column_height=8, shelf_rows=1, request_queue_size=5), "shelf_columns"),
        (dict(shelf_columns=3, column_height=0, shelf_rows=1, request_queue_size=5), "column_height"),
        (dict(shelf_columns=3, column_height=8, shelf_rows=-1, request_queue_size=5), "shelf_rows"),
        (dict(shelf_columns=3, column_height=8, shelf_rows=1, request_queue_size=0), "request_queue_size"),
        (dict(shelf_columns=1, column_height=1, shelf_rows=1, request_queue_size=3), "request_queue_size"),
    ],
)
def test_bad_layout_names_the_field(kwargs, field):
    with pytest.raises(ValidationError, match=field):
        LayoutConfig(**kwargs)


def test_unknown_size_is_a_clear_error():
    with pytest.raises(ValueError, match="scale: unknown size 'huge'"):
        LayoutConfig.named("huge")
