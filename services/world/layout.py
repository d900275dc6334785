"""Warehouse grid layouts with TA-RWARE's formulas and index orders.

Pure data: a :class:`LayoutConfig` (validated by pydantic) and the :class:`Layout` derived from it. Cells are
``(x, y)`` with ``y`` the row; arrays are indexed ``[y, x]``; flat cell indices are ``y * W + x``.
"""

from __future__ import annotations

import tomllib
from functools import lru_cache
from importlib import resources

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# Fixed constants of the original layout builder: 2 highway lanes, 2-wide racks, 2 bottom rows + goal row.
HIGHWAY_LANES = 2
RACK_WIDTH = 2
BOTTOM_ROWS = 2


class LayoutConfig(BaseModel):
    """Size of a warehouse: ``shelf_rows`` × ``shelf_columns`` rack blocks of 2 × ``column_height`` cells."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    shelf_columns: int = Field(ge=1, description="rack columns C (odd, as the original requires)")
    column_height: int = Field(ge=1, description="rack cells per column block h")
    shelf_rows: int = Field(ge=1, description="rack block rows R")
    request_queue_size: int = Field(ge=1, description="number of simultaneously requested shelves Q")

    @field_validator("shelf_columns")
    @classmethod
    def _odd_columns(cls, value: int) -> int:
        if value % 2 != 1:
            raise ValueError(f"shelf_columns must be odd (the original supports only odd counts), got {value}")
        return value

    @model_validator(mode="after")
    def _queue_fits(self) -> LayoutConfig:
        shelves = RACK_WIDTH * self.column_height * self.shelf_rows * self.shelf_columns
        if self.request_queue_size > shelves:
            raise ValueError(
                f"request_queue_size {self.request_queue_size} exceeds the number of shelves {shelves}"
            )
        return self

    @classmethod
    def named(cls, name: str) -> LayoutConfig:
        """One of the original's registered sizes: tiny, small, medium, large, extralarge."""
        sizes = named_sizes()
        if name not in sizes:
            raise ValueError(f"scale: unknown size {name!r}; choose one of {', '.join(sizes)}")
        return sizes[name][0]


@lru_cache(maxsize=1)
def _presets() -> dict:
    text = resources.files("services.world").joinpath("layouts.toml").read_text(encoding="utf-8")
    return tomllib.loads(text)


def named_sizes() -> dict[str, tuple[LayoutConfig, int, int]]:
    """Size name -> (layout config, default AGV count, default picker count), in file order."""
    out = {}
    for name, table in _presets().items():
        fields = {k: v for k, v in table.items() if not k.startswith("default_")}
        out[name] = (LayoutConfig(**fields), int(table["default_agvs"]), int(table["default_pickers"]))
    return out


class Layout:
    """Grid geometry and the original's index maps for one :class:`LayoutConfig`.

    Attributes (all read-only by convention):
      H, W            grid height and width
      highway         (H, W) bool, True on highway cells (goal row included)
      goals           goal cells (x, y), x ascending
      action_cells    action id -> cell; index 0 is None ("no target"), 1..G goals, then rack cells column-major
      shelf_cells     shelf id - 1 -> its initial rack cell, row-major (shelf ids and action ids differ in order)
      rack_groups     list of rack blocks, each a list of cells (the original's greedy `find_sections` result)
      highway_cells   highway cells row-major (the spawn list)
    """

    def __init__(self, config: LayoutConfig):
        self.config = config
        c, h, r = config.shelf_columns, config.column_height, config.shelf_rows
        self.H = HIGHWAY_LANES + (h + HIGHWAY_LANES) * r + BOTTOM_ROWS + 1
        self.W = HIGHWAY_LANES + (RACK_WIDTH + HIGHWAY_LANES) * c
        H, W = self.H, self.W
        ys = np.arange(H)[:, None]
        xs = np.arange(W)[None, :]
        hw_rows = (ys % (h + HIGHWAY_LANES) < HIGHWAY_LANES) | (ys >= H - 1 - BOTTOM_ROWS)
        hw_cols = xs % (RACK_WIDTH + HIGHWAY_LANES) < HIGHWAY_LANES
        self.highway = np.asarray(hw_rows | hw_cols)
        self.highway.setflags(write=False)
        self.goals: list[tuple[int, int]] = [(x, H - 1) for x in range(W) if not hw_cols[0, x]]
        self.num_goals = len(self.goals)
        rack_colmajor = [(x, y) for x in range(W) for y in range(H) if not self.highway[y, x]]
        self.action_cells: list[tuple[int, int] | None] = [None, *self.goals, *rack_colmajor]
        self.cell_to_action = {cell: i for i, cell in enumerate(self.action_cells) if cell is not None}
        self.shelf_cells: list[tuple[int, int]] = [
            (x, y) for y in range(H) for x in range(W) if not self.highway[y, x]
        ]
        self.num_shelves = len(self.shelf_cells)
        self.highway_cells: list[tuple[int, int]] = [
            (x, y) for y in range(H) for x in range(W) if self.highway[y, x]
        ]
        self.rack_action_ids = list(range(self.num_goals + 1, len(self.action_cells)))
        self.rack_groups = _find_sections(rack_colmajor)
        self.action_size = len(self.action_cells)

    def action_to_cell(self, action: int) -> tuple[int, int]:
        if not 1 <= action < self.action_size:
            raise ValueError(f"action: {action} is not a target id (1..{self.action_size - 1})")
        return self.action_cells[action]  # type: ignore[return-value]

    def cell_to_action_id(self, cell: tuple[int, int]) -> int:
        try:
            return self.cell_to_action[cell]
        except KeyError:
            raise ValueError(f"cell: {cell} is neither a goal nor a rack cell") from None


def _find_sections(cells: list[tuple[int, int]]) -> list[list[tuple[int, int]]]:
    """Greedy grouping of the original: each cell joins the first group holding a 4-neighbour, else starts one."""
    groups: list[list[tuple[int, int]]] = []
    for x, y in cells:
        for group in groups:
            if any(abs(x - gx) + abs(y - gy) == 1 for gx, gy in group):
                group.append((x, y))
                break
        else:
            groups.append([(x, y)])
    return groups


@lru_cache(maxsize=32)
def layout_for(config: LayoutConfig) -> Layout:
    """Layouts are immutable; share one per config."""
    return Layout(config)
