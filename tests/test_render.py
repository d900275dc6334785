"""Headless renderer: geometry, colours, links, PNG and GIF output, on hand-made frames."""

import time

import numpy as np
import pytest
from PIL import Image, ImageSequence

from services.world.render import (
    COLORS,
    DOWN,
    LEFT,
    RIGHT,
    UP,
    Frame,
    Renderer,
    image_size,
    link_statuses,
    render_frame,
    save_png,
    write_gif,
)

CELL = 20


def make_frame(H=6, W=8, agents=(), shelves=(), requested=(), goals=((2, 5), (3, 5)), **kw):
    """agents: tuples (x, y, dir, is_agv, carrying[, carrying_requested])."""
    highway = np.ones((H, W), bool)
    sh = np.zeros((H, W), bool)
    rq = np.zeros((H, W), bool)
    for x, y in shelves:
        sh[y, x] = True
        highway[y, x] = False
    for x, y in requested:
        sh[y, x] = rq[y, x] = True
        highway[y, x] = False
    a = list(agents)
    col = lambda k, default=False: [t[k] if len(t) > k else default for t in a]  # noqa: E731
    return Frame(
        height=H,
        width=W,
        highway=highway,
        goals=np.array(goals).reshape(-1, 2),
        shelves=sh,
        requested=rq,
        agent_x=col(0),
        agent_y=col(1),
        agent_dir=col(2),
        is_agv=col(3),
        carrying=col(4),
        carrying_requested=col(5),
        **kw,
    )


def center(x, y, cell=CELL, header=0):
    return x * (cell + 1) + 1 + (cell - 1) // 2, y * (cell + 1) + 1 + header + (cell - 1) // 2


def px(img, xy):
    return img.convert("RGB").getpixel(xy)


def test_image_size_with_and_without_header():
    f = make_frame(H=5, W=4, goals=())
    assert render_frame(f, cell_px=10).size == (1 + 4 * 11, 1 + 5 * 11) == image_size(5, 4, 10)
    g = make_frame(H=5, W=4, goals=(), step=3)
    w, h = render_frame(g, cell_px=10).size
    assert w == 45 and h > 56 and (w, h) == image_size(5, 4, 10, header=True)


def test_agv_and_picker_colours_at_their_cells():
    f = make_frame(agents=[(1, 1, RIGHT, True, False), (5, 2, UP, False, False), (3, 3, DOWN, True, True)])
    img = render_frame(f, cell_px=CELL)
    cx, cy = center(1, 1)
    assert px(img, (cx - 4, cy)) == COLORS["agv"]  # left of centre: off the heading tick, which points right
    assert px(img, (cx + 4, cy)) == COLORS["heading"]  # the heading tick
    cx, cy = center(5, 2)
    assert px(img, (cx, cy + 4)) == COLORS["picker"]
    assert px(img, (cx, cy - 4)) == COLORS["heading"]
    cx, cy = center(3, 3)
    assert px(img, (cx, cy - 4)) == COLORS["agv_loaded"]
    # A carried shelf shows in the cell's corner, under the glyph.
    x0, y0 = 3 * (CELL + 1) + 1, 3 * (CELL + 1) + 1
    assert px(img, (x0 + 3, y0 + 3)) == COLORS["shelf"]
    assert COLORS["agv"] != COLORS["picker"] != COLORS["agv_loaded"]


def test_glyph_shapes_differ_between_agv_and_picker():
    # Hexagon (AGV) vs diamond (picker): at (0.6r, 0.5r) from the centre the hexagon is filled, the diamond is not.
    cell = 40
    f = make_frame(agents=[(1, 1, LEFT, True, False), (5, 1, LEFT, False, False)])
    img = render_frame(f, cell_px=cell)
    r = cell * 0.38
    for x, colour in ((1, COLORS["agv"]), (5, COLORS["background"])):
        cx = cy = (cell + 1) * 1 + 1 + (cell - 1) / 2
        cx += (x - 1) * (cell + 1)
        assert px(img, (round(cx + 0.6 * r), round(cy + 0.5 * r))) == colour


def test_requested_shelves_differ_from_plain_shelves():
    f = make_frame(shelves=[(2, 1)], requested=[(3, 1)])
    img = render_frame(f, cell_px=CELL)
    plain = px(img, center(2, 1))
    req = px(img, center(3, 1))
    assert plain == COLORS["shelf"]
    assert req == COLORS["shelf_requested"]
    assert plain != req
    assert px(img, center(0, 0)) == COLORS["background"]
    assert px(img, center(2, 5)) in (COLORS["goal"], COLORS["goal_mark"])
    assert px(img, (0, 0)) == COLORS["grid"]


def test_carried_requested_shelf_uses_requested_colour():
    f = make_frame(agents=[(3, 3, UP, True, True, True)])
    img = render_frame(f, cell_px=CELL)
    x0, y0 = 3 * (CELL + 1) + 1, 3 * (CELL + 1) + 1
    assert px(img, (x0 + 3, y0 + 3)) == COLORS["shelf_requested"]


@pytest.mark.parametrize("status", ["stable", "new", "pruned"])
def test_links_are_drawn_between_linked_agents(status):
    agents = [(0, 2, UP, True, False), (7, 2, UP, False, False)]
    bare = np.asarray(render_frame(make_frame(agents=agents), cell_px=CELL))
    linked = np.asarray(render_frame(make_frame(agents=agents, links=[(0, 1, status)]), cell_px=CELL))
    (x0, y), (x1, _) = center(0, 2), center(7, 2)
    strip = slice(y - 3, y + 4), slice(x0 + CELL, x1 - CELL)  # between the two glyphs
    changed = np.any(bare[strip] != linked[strip], axis=2)
    assert changed.sum() > 0
    colour = {"stable": "link_stable", "new": "link_new", "pruned": "link_pruned"}[status]
    assert (linked[strip] == COLORS[colour]).all(axis=2).any()
    # Nothing changes far from the segment.
    far = slice(0, CELL), slice(None)
    assert np.array_equal(bare[far], linked[far])
    if status == "pruned":  # dashed: gaps along the line
        row = linked[y, x0 + CELL : x1 - CELL]
        on = (row == COLORS["link_pruned"]).all(axis=1)
        assert on.any() and not on.all()


def test_stable_link_is_thicker_than_new():
    agents = [(0, 2, UP, True, False), (7, 2, UP, False, False)]
    counts = {}
    for st in ("stable", "new"):
        a = np.asarray(render_frame(make_frame(agents=agents, links=[(0, 1, st)]), cell_px=CELL))
        counts[st] = (a == COLORS["link_" + st]).all(axis=2).sum()
    assert counts["stable"] > counts["new"] > 0


def test_target_lines_optional():
    f = make_frame(agents=[(0, 0, UP, True, False)], target=[[7, 4]])
    plain = np.asarray(render_frame(f, cell_px=CELL))
    with_t = np.asarray(render_frame(f, cell_px=CELL, draw_targets=True))
    assert not np.array_equal(plain, with_t)
    assert (with_t == COLORS["target"]).all(axis=2).any()
    assert not (plain == COLORS["target"]).all(axis=2).any()


def test_header_shifts_grid_and_shows_text():
    f = make_frame(agents=[(1, 1, RIGHT, True, False)], step=42, caption="seed 0")
    img = render_frame(f, cell_px=CELL)
    hp = img.size[1] - image_size(6, 8, CELL)[1]
    cx, cy = center(1, 1, header=hp)
    assert px(img, (cx - 4, cy)) == COLORS["agv"]
    band = np.asarray(img)[:hp]
    assert (band == COLORS["text"]).all(axis=2).any()


def test_frame_validation_names_the_field():
    with pytest.raises(ValueError, match="shelves"):
        Frame(3, 3, np.ones((3, 3), bool), [], np.zeros((2, 3), bool), np.zeros((3, 3), bool), [], [], [], [], [])
    with pytest.raises(ValueError, match="links"):
        make_frame(agents=[(0, 0, UP, True, False), (1, 0, UP, False, False)], links=[(0, 1, "strong")])
    with pytest.raises(ValueError, match="links"):
        make_frame(agents=[(0, 0, UP, True, False)], links=[(0, 3, "new")])
    with pytest.raises(ValueError, match="agent_dir"):
        make_frame(agents=[(0, 0, 7, True, False)])
    with pytest.raises(ValueError, match="agent_x"):
        make_frame(agents=[(9, 0, UP, True, False)])
    with pytest.raises(ValueError, match="goals"):
        make_frame(goals=[(0, 6)])
    with pytest.raises(ValueError, match="cell_px"):
        Renderer(cell_px=2)


def test_save_png_round_trip(tmp_path):
    f = make_frame(agents=[(2, 2, LEFT, False, False)], requested=[(4, 1)])
    p = save_png(f, tmp_path / "f.png", cell_px=CELL)
    with Image.open(p) as im:
        assert im.size == image_size(6, 8, CELL)
        assert np.array_equal(np.asarray(im.convert("RGB")), np.asarray(render_frame(f, cell_px=CELL)))


def _episode(n):
    frames = []
    for t in range(n):
        x = min(t, 7)
        frames.append(
            make_frame(
                agents=[(x, 2, RIGHT, True, t % 3 == 0), (7 - x, 4, LEFT, False, False)],
                requested=[(4, 1)] if t % 2 else [],
                shelves=[(5, 1)],
                links=[(0, 1, "stable" if t > 3 else "new")],
                step=t,
            )
        )
    return frames


def test_gif_round_trip_frame_count_and_content(tmp_path):
    frames = _episode(10)
    frames.append(frames[-1])  # an unchanged frame still counts as a frame
    path = tmp_path / "ep.gif"
    assert write_gif(frames, path, fps=10, cell_px=CELL) == 11
    with Image.open(path) as im:
        assert im.n_frames == 11
        assert im.size == image_size(6, 8, CELL, header=True)
        decoded = [np.asarray(fr.convert("RGB")) for fr in ImageSequence.Iterator(im)]
        assert im.info.get("duration") == 100
    # Every decoded frame equals the directly rendered one (the cropped patches composite correctly).
    for k in (0, 3, 9, 10):
        assert np.array_equal(decoded[k], np.asarray(render_frame(frames[k], cell_px=CELL)))


def test_gif_from_images_and_errors(tmp_path):
    imgs = [Image.new("RGB", (30, 20), (10 * k, 100, 200)) for k in range(4)]
    assert write_gif(imgs, tmp_path / "a.gif", fps=5) == 4
    with Image.open(tmp_path / "a.gif") as im:
        assert im.n_frames == 4
        im.seek(3)
        assert im.convert("RGB").getpixel((5, 5)) == (30, 100, 200)
    with pytest.raises(ValueError, match="frames"):
        write_gif([Image.new("RGB", (30, 20)), Image.new("RGB", (31, 20))], tmp_path / "b.gif")
    with pytest.raises(ValueError, match="frames"):
        write_gif([], tmp_path / "c.gif")
    with pytest.raises(ValueError, match="fps"):
        write_gif(imgs, tmp_path / "d.gif", fps=0)


def test_gif_speed_large_warehouse(tmp_path):
    # Large layout (R=3, C=5 → 35×22) with 24 robots and 40 links, every frame different: the 800-step GIF must be
    # practical, so 200 frames must take well under the budget (measured ≈ 1 s here).
    rng = np.random.default_rng(0)
    H, W, h = 35, 22, 8
    y, x = np.mgrid[0:H, 0:W]
    highway = (y % (h + 2) <= 1) | (y >= H - 3) | (x % 4 <= 1)
    goals = np.array([(gx, H - 1) for gx in range(W) if gx % 4 >= 2])
    cells = np.argwhere(highway)

    def frame(t):
        pick = rng.choice(len(cells), 24, replace=False)
        ys, xs = cells[pick].T
        shelves = ~highway & (rng.random((H, W)) < 0.9)
        links = [(int(i), int(j), "stable") for i, j in rng.choice(24, (40, 2)) if i != j]
        return Frame(H, W, highway, goals, shelves, shelves & (rng.random((H, W)) < 0.1), xs, ys,
                     rng.integers(0, 4, 24), np.arange(24) < 16, rng.random(24) < 0.3, step=t, links=links)

    frames = [frame(t) for t in range(200)]
    t0 = time.perf_counter()
    assert write_gif(frames, tmp_path / "large.gif", fps=20, cell_px=16) == 200
    assert time.perf_counter() - t0 < 20.0


def test_link_statuses_from_consecutive_link_matrices():
    prev = np.zeros((4, 4), int)
    prev[0, 1] = prev[1, 0] = 1
    prev[2, 3] = prev[3, 2] = 1
    cur = np.zeros((4, 4), int)
    cur[0, 1] = cur[1, 0] = 1  # kept
    cur[0, 2] = 1  # one-way link formed this tick
    assert link_statuses(cur, prev) == [(0, 1, "stable"), (0, 2, "new"), (2, 3, "pruned")]
    age = np.zeros((4, 4), int)
    age[0, 1] = age[1, 0] = 5
    assert link_statuses(cur, prev, age=age, stable_age=10)[0] == (0, 1, "new")
    assert link_statuses(cur) == [(0, 1, "stable"), (0, 2, "stable")]
    with pytest.raises(ValueError, match="A_prev"):
        link_statuses(cur, np.zeros((3, 3)))


def test_agent_labels_optional():
    f = make_frame(agents=[(3, 2, UP, True, False)])
    plain = np.asarray(render_frame(f, cell_px=CELL))
    labelled = np.asarray(render_frame(f, cell_px=CELL, labels=True))
    assert not np.array_equal(plain, labelled)
    assert (labelled == COLORS["text"]).all(axis=2).any()
