"""Headless warehouse renderer: PNG frames and animated GIFs, drawn with Pillow.

The renderer knows nothing about the warehouse class: a :class:`Frame` of plain numpy arrays describes everything to
draw, so the sim, the monitor (replaying a run record) and the lab can all produce frames.

Style follows TA-RWARE's pyglet renderer (white floor, dark grid lines, dark-slate-blue shelves, teal requested
shelves, dark goal cells, orange robots turning red while loaded, a black heading tick), with two additions: AGVs and
pickers get distinct glyphs and colours (hexagon vs diamond), and MORPH's coordination links can be drawn between
agents as in the paper's animations (stable = thick green, new = thin, pruned = red dashed).

Coordinates: cell (x, y) is column x, row y, with y = 0 at the top of the image, as the original shows it (goals sit
on the bottom row).  Every cell is ``cell_px`` pixels plus a 1-pixel grid line, so an image is
``1 + W·(cell_px+1)`` wide and ``1 + H·(cell_px+1) + header`` tall, where the header band exists only when the frame
has a step number or a caption.

Speed: frames are drawn in palette ("P") mode on a cached copy of the static background (grid, aisles, goals); GIFs
are written frame by frame, each frame cropped to the rectangle that changed since the previous one, so an 800-step
episode of a large warehouse neither holds all frames in memory nor re-encodes the unchanged floor.
"""

from __future__ import annotations

import io
import math
import struct
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

__all__ = [
    "UP",
    "DOWN",
    "LEFT",
    "RIGHT",
    "LINK_STATUSES",
    "COLORS",
    "Frame",
    "Renderer",
    "link_statuses",
    "render_frame",
    "save_png",
    "write_gif",
    "image_size",
    "legend_height",
    "LEGEND_TEXT",
    "WAREHOUSE_LEGEND",
    "RECORD_LEGEND",
]

# Headings as in TA-RWARE's Direction enum.
UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3
_HEADING = {UP: (0.0, -1.0), DOWN: (0.0, 1.0), LEFT: (-1.0, 0.0), RIGHT: (1.0, 0.0)}

LINK_STATUSES = ("stable", "new", "pruned")

# One palette for every frame (index order = palette order). Names are what they depict.
COLORS: dict[str, tuple[int, int, int]] = {
    "background": (255, 255, 255),  # highway floor
    "rack_floor": (236, 238, 244),  # empty rack slot: shows the aisle structure the original leaves implicit
    "grid": (120, 120, 120),
    "goal": (60, 60, 60),
    "goal_mark": (255, 255, 255),
    "shelf": (72, 61, 139),  # TA-RWARE dark slate blue
    "shelf_requested": (0, 150, 150),  # TA-RWARE teal, a little brighter to stand out at small cell sizes
    "agv": (255, 140, 0),  # TA-RWARE dark orange
    "agv_loaded": (230, 20, 20),  # TA-RWARE: a robot carrying a shelf turns red
    "picker": (30, 144, 255),  # TA-RWARE's (unused) loader blue
    "outline": (20, 20, 20),
    "heading": (0, 0, 0),
    "target": (150, 150, 150),
    "link_stable": (0, 150, 60),
    "link_new": (90, 205, 90),
    "link_pruned": (215, 25, 25),
    "header": (245, 245, 245),
    "text": (20, 20, 20),
    "dead_zone": (250, 212, 212),  # floor of a network dead zone (--network): a fade among metal racks
    "access_point": (255, 215, 0),  # a Wi-Fi access point (--network)
}
_IDX = {name: i for i, name in enumerate(COLORS)}

# What a legend band can explain (key -> words), drawn with the same glyphs and colours as the frame. A caller names
# the entries its frames show: WAREHOUSE_LEGEND for the simulation's own frames, RECORD_LEGEND for a run record's
# (which knows positions and links but not which shelves are requested).
LEGEND_TEXT = {
    "agv": "AGV (tick: heading)",
    "agv_loaded": "AGV carrying a shelf",
    "picker": "picker",
    "shelf": "shelf",
    "shelf_requested": "requested shelf",
    "rack_floor": "empty shelf slot",
    "goal": "goal (drop-off)",
    "link_stable": "stable link",
    "link_new": "new link",
    "link_pruned": "pruned link",
    "access_point": "Wi-Fi access point",
    "dead_zone": "network dead zone",
}
WAREHOUSE_LEGEND = ("agv", "agv_loaded", "picker", "shelf", "shelf_requested", "rack_floor", "goal")
RECORD_LEGEND = ("agv", "agv_loaded", "picker", "shelf", "goal", "link_stable", "link_new", "link_pruned")
_PALETTE = [c for rgb in COLORS.values() for c in rgb]
_PALETTE += _PALETTE[-3:] * (256 - len(COLORS))


# ---------------------------------------------------------------------------------------------------------------------
# Frame


def _arr(name: str, value, dtype, shape: tuple) -> np.ndarray:
    a = np.asarray(value, dtype=dtype)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return a


@dataclass(frozen=True, eq=False)
class Frame:
    """Everything needed to draw one warehouse tick.

    Grid masks are (H, W) indexed [y, x].  ``goals`` is (G, 2) of (x, y).  Per-agent arrays have length N:
    position ``agent_x``/``agent_y``, heading ``agent_dir`` (0 UP, 1 DOWN, 2 LEFT, 3 RIGHT), ``is_agv`` (False =
    picker), ``carrying`` a shelf, ``carrying_requested`` (the carried shelf is a requested one), and ``target``
    (N, 2) of (x, y) or (−1, −1) for none.  ``shelves`` marks shelves standing on the floor, ``requested`` the
    requested ones among them (carried shelves are drawn under their carrier).  ``links`` are (i, j, status) with
    status in :data:`LINK_STATUSES`.
    """

    height: int
    width: int
    highway: np.ndarray
    goals: np.ndarray
    shelves: np.ndarray
    requested: np.ndarray
    agent_x: np.ndarray
    agent_y: np.ndarray
    agent_dir: np.ndarray
    is_agv: np.ndarray
    carrying: np.ndarray
    carrying_requested: np.ndarray | None = None
    target: np.ndarray | None = None
    step: int | None = None
    caption: str | None = None
    links: Sequence[tuple[int, int, str]] = field(default_factory=tuple)
    #: a network profile's access points, (K, 2) of (x, y) cells (may lie between cells), and its dead zones (H, W)
    access_points: np.ndarray | None = None
    dead_zone: np.ndarray | None = None

    def __post_init__(self):
        H, W = int(self.height), int(self.width)
        if H < 1 or W < 1:
            raise ValueError(f"height/width: must be ≥ 1, got {H}×{W}")
        s = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 — frozen dataclass normalisation
        s("height", H)
        s("width", W)
        s("highway", _arr("highway", self.highway, bool, (H, W)))
        s("shelves", _arr("shelves", self.shelves, bool, (H, W)))
        s("requested", _arr("requested", self.requested, bool, (H, W)))
        goals = np.asarray(self.goals, dtype=np.int64).reshape(-1, 2)
        if goals.size and (goals[:, 0].min() < 0 or goals[:, 0].max() >= W or goals[:, 1].min() < 0
                           or goals[:, 1].max() >= H):
            raise ValueError(f"goals: cells must lie inside the {W}×{H} grid")
        s("goals", goals)
        ax = np.asarray(self.agent_x, dtype=np.int64).reshape(-1)
        n = ax.size
        s("agent_x", ax)
        s("agent_y", _arr("agent_y", self.agent_y, np.int64, (n,)))
        s("agent_dir", _arr("agent_dir", self.agent_dir, np.int64, (n,)))
        s("is_agv", _arr("is_agv", self.is_agv, bool, (n,)))
        s("carrying", _arr("carrying", self.carrying, bool, (n,)))
        cr = np.zeros(n, bool) if self.carrying_requested is None else self.carrying_requested
        s("carrying_requested", _arr("carrying_requested", cr, bool, (n,)))
        tg = np.full((n, 2), -1, np.int64) if self.target is None else self.target
        s("target", _arr("target", tg, np.int64, (n, 2)))
        if n and (ax.min() < 0 or ax.max() >= W or self.agent_y.min() < 0 or self.agent_y.max() >= H):
            raise ValueError(f"agent_x/agent_y: agents must lie inside the {W}×{H} grid")
        if n and (self.agent_dir.min() < 0 or self.agent_dir.max() > 3):
            raise ValueError("agent_dir: headings must be 0 (UP), 1 (DOWN), 2 (LEFT) or 3 (RIGHT)")
        links = tuple((int(i), int(j), str(st)) for i, j, st in self.links)
        for i, j, st in links:
            if not (0 <= i < n and 0 <= j < n) or i == j:
                raise ValueError(f"links: bad agent pair ({i}, {j}) for {n} agents")
            if st not in LINK_STATUSES:
                raise ValueError(f"links: status must be one of {LINK_STATUSES}, got {st!r}")
        s("links", links)
        if self.step is not None:
            s("step", int(self.step))
        if self.access_points is not None:
            aps = np.asarray(self.access_points, dtype=float).reshape(-1, 2)
            if aps.size and (aps[:, 0].min() < 0 or aps[:, 0].max() > W - 1 or aps[:, 1].min() < 0
                             or aps[:, 1].max() > H - 1):
                raise ValueError(f"access_points: must lie inside the {W}×{H} grid")
            s("access_points", aps)
        if self.dead_zone is not None:
            s("dead_zone", _arr("dead_zone", self.dead_zone, bool, (H, W)))

    @property
    def n_agents(self) -> int:
        return int(self.agent_x.size)

    @property
    def has_header(self) -> bool:
        return self.step is not None or bool(self.caption)


def link_statuses(A, A_prev=None, age=None, stable_age: int = 0) -> list[tuple[int, int, str]]:
    """Links to draw for one tick, as (i, j, status) over unordered pairs i<j linked in either direction.

    "pruned": linked at the previous tick but not now; "new": linked now but not before, or (when ``age`` is given)
    linked for fewer than ``stable_age`` ticks (age[i, j] or age[j, i], the larger); "stable": the rest.
    Without ``A_prev`` nothing is pruned and, unless ages say otherwise, every current link is stable.
    """
    cur = np.asarray(A) != 0
    if cur.ndim != 2 or cur.shape[0] != cur.shape[1]:
        raise ValueError(f"A: expected a square (N, N) matrix, got shape {cur.shape}")
    cur = np.triu(cur | cur.T, k=1)
    if A_prev is None:
        prev = cur
    else:
        p = np.asarray(A_prev) != 0
        if p.shape != cur.shape:
            raise ValueError(f"A_prev: expected shape {cur.shape}, got {p.shape}")
        prev = np.triu(p | p.T, k=1)
    young = np.zeros_like(cur)
    if age is not None:
        g = np.asarray(age)
        if g.shape != cur.shape:
            raise ValueError(f"age: expected shape {cur.shape}, got {g.shape}")
        young = np.maximum(g, g.T) < stable_age
    out = []
    for i, j in np.argwhere(cur | prev):
        i, j = int(i), int(j)
        if not cur[i, j]:
            out.append((i, j, "pruned"))
        elif not prev[i, j] or young[i, j]:
            out.append((i, j, "new"))
        else:
            out.append((i, j, "stable"))
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Geometry


def _header_px(cell_px: int) -> int:
    return max(14, int(round(cell_px * 0.8)))


def image_size(height: int, width: int, cell_px: int = 24, header: bool = False,
               legend: Sequence[str] = ()) -> tuple[int, int]:
    """(image width, image height) in pixels for an H×W grid (with a legend band of ``legend`` entries below)."""
    w = 1 + width * (cell_px + 1)
    return w, 1 + height * (cell_px + 1) + (_header_px(cell_px) if header else 0) + legend_height(legend, w, cell_px)


def _legend_glyph_px(cell_px: int) -> int:
    return max(12, min(cell_px, 22))


def _legend_layout(legend: Sequence[str], width: int, cell_px: int) -> list[tuple[str, int, int]]:
    """(entry, x, row) of each legend entry, flowed into rows of the image's width."""
    g = _legend_glyph_px(cell_px)
    font = _font(max(10, int(g * 0.75)))
    probe = ImageDraw.Draw(Image.new("P", (1, 1)))
    out, x, row = [], 4, 0
    for key in legend:
        if key not in LEGEND_TEXT:
            raise ValueError(f"legend: unknown entry {key!r} (known: {', '.join(LEGEND_TEXT)})")
        w = g + 4 + int(math.ceil(probe.textlength(LEGEND_TEXT[key], font=font))) + 12
        if x > 4 and x + w > width:
            x, row = 4, row + 1
        out.append((key, x, row))
        x += w
    return out


def legend_height(legend: Sequence[str], width: int, cell_px: int) -> int:
    """Pixels of the legend band under an image ``width`` pixels wide (0 without a legend)."""
    if not legend:
        return 0
    rows = 1 + max(row for _, _, row in _legend_layout(legend, width, cell_px))
    return rows * (_legend_glyph_px(cell_px) + 6) + 6


@lru_cache(maxsize=8)
def _font(px: int):
    try:
        return ImageFont.load_default(size=px)
    except (TypeError, OSError):  # Pillow without FreeType: fixed bitmap font
        return ImageFont.load_default()


class Renderer:
    """Draws frames of one cell size; caches the static background per layout.

    ``draw_targets`` adds a thin grey line from each agent to its target cell.  ``labels`` writes each agent's index
    beside its glyph (useful next to the W heatmaps, whose rows are agent indices).  ``legend`` adds a band under the
    grid that names each glyph and colour the frames use (e.g. :data:`WAREHOUSE_LEGEND`).
    """

    def __init__(self, cell_px: int = 24, draw_targets: bool = False, labels: bool = False,
                 legend: Sequence[str] = ()):
        if not isinstance(cell_px, (int, np.integer)) or cell_px < 4:
            raise ValueError(f"cell_px: must be an integer ≥ 4, got {cell_px!r}")
        self.cell_px = int(cell_px)
        self.draw_targets = bool(draw_targets)
        self.labels = bool(labels)
        self.legend = tuple(legend)  # entries of the legend band under the grid (LEGEND_TEXT keys); () = none
        for key in self.legend:
            if key not in LEGEND_TEXT:
                raise ValueError(f"legend: unknown entry {key!r} (known: {', '.join(LEGEND_TEXT)})")
        self._backgrounds: OrderedDict[tuple, Image.Image] = OrderedDict()

    # -- geometry -----------------------------------------------------------------------------------------------------
    def _origin(self, header: bool) -> int:
        return _header_px(self.cell_px) if header else 0

    def _cell_box(self, x: int, y: int, oy: int, pad: int = 0) -> tuple[int, int, int, int]:
        c = self.cell_px
        x0 = x * (c + 1) + 1
        y0 = y * (c + 1) + 1 + oy
        return x0 + pad, y0 + pad, x0 + c - 1 - pad, y0 + c - 1 - pad

    def _center(self, x, y, oy: int) -> tuple[float, float]:
        c = self.cell_px
        return x * (c + 1) + 1 + (c - 1) / 2, y * (c + 1) + 1 + oy + (c - 1) / 2

    # -- static layer -------------------------------------------------------------------------------------------------
    def _background(self, f: Frame) -> Image.Image:
        dead = f.dead_zone
        key = (f.height, f.width, f.has_header, f.highway.tobytes(), f.goals.tobytes(),
               None if dead is None else dead.tobytes())
        bg = self._backgrounds.get(key)
        if bg is not None:
            self._backgrounds.move_to_end(key)
            return bg
        c = self.cell_px
        w, h = image_size(f.height, f.width, c, f.has_header, self.legend)
        band = legend_height(self.legend, w, c)
        h -= band
        oy = self._origin(f.has_header)
        # Grid via numpy: cells filled by kind, grid lines left in between.
        cells = np.where(f.highway, _IDX["background"], _IDX["rack_floor"]).astype(np.uint8)
        goal_mask = np.zeros((f.height, f.width), bool)
        if f.goals.size:
            goal_mask[f.goals[:, 1], f.goals[:, 0]] = True
        cells[goal_mask] = _IDX["goal"]
        if dead is not None:
            cells[dead & ~goal_mask] = _IDX["dead_zone"]
        big = np.full((h - oy, w), _IDX["grid"], np.uint8)
        block = np.repeat(np.repeat(cells, c, axis=0), c, axis=1)
        inner = big[1:, 1:].reshape(f.height, c + 1, f.width, c + 1)
        inner[:, :c, :, :c] = block.reshape(f.height, c, f.width, c)
        arr = np.full((h + band, w), _IDX["header"], np.uint8)
        arr[oy:h] = big
        img = Image.fromarray(arr, mode="P")
        img.putpalette(_PALETTE)
        d = ImageDraw.Draw(img)
        # Goal mark: a white downward triangle (a drop-off point).
        for gx, gy in f.goals:
            x0, y0, x1, y1 = self._cell_box(int(gx), int(gy), oy, pad=max(2, c // 4))
            d.polygon([(x0, y0), (x1, y0), ((x0 + x1) / 2, y1)], fill=_IDX["goal_mark"])
        if band:
            self._draw_legend(d, w, h)
        self._backgrounds[key] = img
        if len(self._backgrounds) > 8:
            self._backgrounds.popitem(last=False)
        return img

    def _draw_legend(self, d: ImageDraw.ImageDraw, width: int, top: int) -> None:
        """The legend band from pixel row ``top``: each entry's glyph in the frame's colours, then its words."""
        g = _legend_glyph_px(self.cell_px)
        font = _font(max(10, int(g * 0.75)))
        d.fontmode = "1"
        for key, x, row in _legend_layout(self.legend, width, self.cell_px):
            y = top + 6 + row * (g + 6)
            x0, y0, x1, y1 = x, y, x + g - 1, y + g - 1
            cx, cy, r = (x0 + x1) / 2, (y0 + y1) / 2, g * 0.38
            if key in ("agv", "agv_loaded"):
                if key == "agv_loaded":
                    d.rectangle((x0, y0, x1, y1), fill=_IDX["shelf"])
                pts = [(cx + r * math.cos(math.pi / 3 * a), cy + r * math.sin(math.pi / 3 * a)) for a in range(6)]
                d.polygon(pts, fill=_IDX[key], outline=_IDX["outline"])
                d.line([(cx, cy), (cx, cy - r)], fill=_IDX["heading"], width=max(1, g // 10))
            elif key == "picker":
                pts = [(cx + r * math.cos(math.pi / 2 * a), cy + r * math.sin(math.pi / 2 * a)) for a in range(4)]
                d.polygon(pts, fill=_IDX["picker"], outline=_IDX["outline"])
                d.line([(cx, cy), (cx, cy - r)], fill=_IDX["heading"], width=max(1, g // 10))
            elif key in ("shelf", "shelf_requested", "rack_floor", "dead_zone"):
                d.rectangle((x0, y0, x1, y1), fill=_IDX[key], outline=_IDX["grid"])
            elif key == "goal":
                d.rectangle((x0, y0, x1, y1), fill=_IDX["goal"])
                p = max(2, g // 4)
                d.polygon([(x0 + p, y0 + p), (x1 - p, y0 + p), (cx, y1 - p)], fill=_IDX["goal_mark"])
            elif key == "link_stable":
                d.line([(x0, cy), (x1, cy)], fill=_IDX[key], width=max(2, g // 6))
            elif key == "link_new":
                d.line([(x0, cy), (x1, cy)], fill=_IDX[key], width=max(1, g // 12))
            elif key == "access_point":  # as on the map: a disc with its antenna
                ra = g * 0.3
                d.ellipse([cx - ra, cy - ra * 0.4, cx + ra, cy + ra * 1.6], fill=_IDX[key], outline=_IDX["outline"])
                d.line([(cx, cy - ra * 0.4), (cx, cy - ra * 1.2)], fill=_IDX["outline"], width=max(1, g // 12))
            else:  # link_pruned
                _dashed(d, (x0, cy), (x1, cy), _IDX[key], width=max(1, g // 10), dash=max(3, g // 4))
            d.text((x1 + 5, cy), LEGEND_TEXT[key], fill=_IDX["text"], font=font, anchor="lm")

    # -- dynamic layers -----------------------------------------------------------------------------------------------
    def render_indexed(self, f: Frame) -> Image.Image:
        """The frame as a palette image (fixed :data:`COLORS` palette); cheapest form for GIFs."""
        if not isinstance(f, Frame):
            raise ValueError(f"frame: expected a Frame, got {type(f).__name__}")
        img = self._background(f).copy()
        d = ImageDraw.Draw(img)
        d.fontmode = "1"  # no anti-aliasing: blending palette indices would produce arbitrary colours
        c = self.cell_px
        oy = self._origin(f.has_header)
        pad = max(1, c // 12)

        ys, xs = np.nonzero(f.shelves)
        req = f.requested[ys, xs]
        for x, y, r in zip(xs.tolist(), ys.tolist(), req.tolist()):
            d.rectangle(self._cell_box(x, y, oy, pad), fill=_IDX["shelf_requested" if r else "shelf"])

        centers = [self._center(x, y, oy) for x, y in zip(f.agent_x.tolist(), f.agent_y.tolist())]

        if self.draw_targets:
            for k, (tx, ty) in enumerate(f.target.tolist()):
                if tx >= 0 and ty >= 0:
                    d.line([centers[k], self._center(tx, ty, oy)], fill=_IDX["target"], width=1)

        # Links under the robots, pruned first so a re-formed pair shows its live status on top.
        order = {"pruned": 0, "new": 1, "stable": 2}
        for i, j, st in sorted(f.links, key=lambda e: order[e[2]]):
            p, q = centers[i], centers[j]
            if st == "stable":
                d.line([p, q], fill=_IDX["link_stable"], width=max(2, c // 6))
            elif st == "new":
                d.line([p, q], fill=_IDX["link_new"], width=max(1, c // 12))
            else:
                _dashed(d, p, q, _IDX["link_pruned"], width=max(1, c // 10), dash=max(3, c // 3))

        r = c * 0.38
        for k in range(f.n_agents):
            x, y = int(f.agent_x[k]), int(f.agent_y[k])
            cx, cy = centers[k]
            if f.carrying[k]:
                d.rectangle(self._cell_box(x, y, oy, pad), fill=_IDX["shelf_requested" if f.carrying_requested[k]
                                                                 else "shelf"])
            if f.is_agv[k]:
                fill = _IDX["agv_loaded"] if f.carrying[k] else _IDX["agv"]
                pts = [(cx + r * math.cos(math.pi / 3 * a), cy + r * math.sin(math.pi / 3 * a)) for a in range(6)]
            else:
                fill = _IDX["picker"]
                pts = [(cx + r * math.cos(math.pi / 2 * a), cy + r * math.sin(math.pi / 2 * a)) for a in range(4)]
            d.polygon(pts, fill=fill, outline=_IDX["outline"])
            hx, hy = _HEADING[int(f.agent_dir[k])]
            d.line([(cx, cy), (cx + hx * r, cy + hy * r)], fill=_IDX["heading"], width=max(1, c // 10))

        if f.access_points is not None:  # on top: an AP hangs above racks and robots
            ra = max(2.0, c * 0.3)
            for ax, ay in f.access_points.tolist():
                cx, cy = self._center(ax, ay, oy)
                d.ellipse([cx - ra, cy - ra, cx + ra, cy + ra], fill=_IDX["access_point"], outline=_IDX["outline"])
                d.line([(cx, cy - ra), (cx, cy - 1.8 * ra)], fill=_IDX["outline"], width=max(1, c // 12))

        if self.labels:
            font = _font(max(8, c // 2))
            for k, (cx, cy) in enumerate(centers):
                d.text((cx + r * 0.6, cy - r * 1.3), str(k), fill=_IDX["text"], font=font)

        if f.has_header:
            hp = _header_px(c)
            parts = []
            if f.step is not None:
                parts.append(f"t = {f.step}")
            if f.caption:
                parts.append(str(f.caption))
            d.text((4, hp / 2), "   ".join(parts), fill=_IDX["text"], font=_font(max(8, hp - 4)), anchor="lm")
        return img

    def render(self, f: Frame) -> Image.Image:
        """The frame as an RGB image."""
        return self.render_indexed(f).convert("RGB")


def _dashed(d: ImageDraw.ImageDraw, p, q, fill: int, width: int, dash: int) -> None:
    (x0, y0), (x1, y1) = p, q
    length = math.hypot(x1 - x0, y1 - y0)
    if length == 0:
        return
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    s = 0.0
    while s < length:
        e = min(s + dash, length)
        d.line([(x0 + ux * s, y0 + uy * s), (x0 + ux * e, y0 + uy * e)], fill=fill, width=width)
        s += 2 * dash


@lru_cache(maxsize=8)
def _renderer(cell_px: int, draw_targets: bool, labels: bool, legend: tuple[str, ...] = ()) -> Renderer:
    return Renderer(cell_px, draw_targets, labels, legend)


# ---------------------------------------------------------------------------------------------------------------------
# Public one-call API


def render_frame(frame: Frame, cell_px: int = 24, draw_targets: bool = False, labels: bool = False,
                 legend: Sequence[str] = ()) -> Image.Image:
    """Draw one frame; returns an RGB :class:`PIL.Image.Image`."""
    return _renderer(cell_px, draw_targets, labels, tuple(legend)).render(frame)


def save_png(frame: Frame, path, cell_px: int = 24, draw_targets: bool = False, labels: bool = False,
             legend: Sequence[str] = ()) -> Path:
    """Draw one frame to a PNG file; returns the path."""
    path = Path(path)
    _renderer(cell_px, draw_targets, labels, tuple(legend)).render_indexed(frame).save(path, format="PNG",
                                                                                       optimize=False)
    return path


def write_gif(
    frames: Iterable[Frame | Image.Image],
    path,
    fps: float = 10.0,
    cell_px: int = 24,
    draw_targets: bool = False,
    labels: bool = False,
    loop: int = 0,
    legend: Sequence[str] = (),
) -> int:
    """Write an animated GIF of ``frames`` (Frames, or ready images of one size) and return the frame count.

    Streams: each frame is encoded as soon as it is drawn, cropped to the region that changed since the previous one
    (a 1×1 patch if nothing changed, so the count still equals the input), with its own colour table.  ``fps`` sets
    the per-frame delay (GIF resolution is 1/100 s); ``loop`` = 0 repeats forever.
    """
    if not fps > 0:
        raise ValueError(f"fps: must be > 0, got {fps}")
    if not (isinstance(loop, int) and 0 <= loop <= 0xFFFF):
        raise ValueError(f"loop: must be an integer in 0..65535, got {loop!r}")
    delay = max(1, int(round(100.0 / fps)))
    ren = _renderer(cell_px, draw_targets, labels, tuple(legend))
    path = Path(path)
    count = 0
    size = None
    prev_key = None
    with open(path, "wb") as fp:
        for item in frames:
            if isinstance(item, Frame):
                im = ren.render_indexed(item)
                key = ("P", np.asarray(im))
            elif isinstance(item, Image.Image):
                im = item.convert("RGB")
                key = ("RGB", np.asarray(im))
            else:
                raise ValueError(f"frames: items must be Frame or PIL images, got {type(item).__name__}")
            if size is None:
                size = im.size
                fp.write(_gif_header(size, loop))
            elif im.size != size:
                raise ValueError(f"frames: frame {count} is {im.size[0]}×{im.size[1]}, the first was "
                                 f"{size[0]}×{size[1]}")
            box = _changed_box(prev_key, key)
            prev_key = key
            patch = im.crop(box)
            fp.write(_gif_frame(patch, box[:2], delay))
            count += 1
        if size is None:
            raise ValueError("frames: no frames to write")
        fp.write(b"\x3b")
    return count


# ---------------------------------------------------------------------------------------------------------------------
# GIF stream assembly.  Pillow encodes each (cropped) frame as a one-image GIF; we lift its colour table and LZW data
# into our own stream, which is plain GIF89a: header, looping extension, then per frame a graphic-control extension
# (delay, "leave in place" disposal), an image descriptor at the patch offset with a local colour table, and the data.


def _changed_box(prev, cur) -> tuple[int, int, int, int]:
    kind, a = cur
    h, w = a.shape[:2]
    if prev is None or prev[0] != kind or prev[1].shape != a.shape:
        return 0, 0, w, h
    diff = prev[1] != a
    if diff.ndim == 3:
        diff = diff.any(axis=2)
    rows = np.flatnonzero(diff.any(axis=1))
    if rows.size == 0:
        return 0, 0, 1, 1
    cols = np.flatnonzero(diff.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def _gif_header(size: tuple[int, int], loop: int) -> bytes:
    w, h = size
    lsd = struct.pack("<HHBBB", w, h, 0, 0, 0)  # no global colour table: every frame carries its own
    netscape = b"\x21\xff\x0bNETSCAPE2.0\x03\x01" + struct.pack("<H", loop) + b"\x00"
    return b"GIF89a" + lsd + netscape


def _gif_frame(patch: Image.Image, offset: tuple[int, int], delay: int) -> bytes:
    buf = io.BytesIO()
    patch.save(buf, format="GIF", interlace=False)
    table, lzw = _single_gif_parts(buf.getvalue())
    n_bits = max(1, (len(table) // 3 - 1).bit_length())
    table = table + b"\x00" * (3 * (1 << n_bits) - len(table))
    gce = b"\x21\xf9\x04" + struct.pack("<BHBB", 1 << 2, delay, 0, 0)  # disposal 1: leave in place
    desc = b"\x2c" + struct.pack("<HHHHB", offset[0], offset[1], patch.size[0], patch.size[1], 0x80 | (n_bits - 1))
    return gce + desc + table + lzw


def _single_gif_parts(data: bytes) -> tuple[bytes, bytes]:
    """(colour table, LZW min-code-size byte + data sub-blocks + terminator) of a one-image GIF."""
    pos = 13
    packed = data[10]
    table = b""
    if packed & 0x80:
        n = 3 * (1 << ((packed & 7) + 1))
        table = data[pos : pos + n]
        pos += n
    while pos < len(data):
        tag = data[pos]
        if tag == 0x21:  # extension: label, then sub-blocks
            pos += 2
            while data[pos]:
                pos += data[pos] + 1
            pos += 1
        elif tag == 0x2C:
            dpacked = data[pos + 9]
            pos += 10
            if dpacked & 0x80:
                n = 3 * (1 << ((dpacked & 7) + 1))
                table = data[pos : pos + n]
                pos += n
            start = pos
            pos += 1  # LZW minimum code size
            while data[pos]:
                pos += data[pos] + 1
            pos += 1
            if not table:
                raise ValueError("frames: Pillow wrote a GIF frame without a colour table")
            return table, data[start:pos]
        else:
            break
    raise ValueError("frames: could not find image data in Pillow's GIF output")
