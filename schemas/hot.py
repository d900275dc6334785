"""Validated-but-cheap decode and encode of the tick, the one big message every process handles every tick.

Why: a distributed tick runs ~20 processes on 2 cores, so each process wakes up with cold caches, and the work it
touches per tick is what costs (docs/services.md, Performance). Validating a ``Tick`` through pydantic walks ~650
list elements one by one; here the per-robot lists become two numpy blocks (integers, flags) in one conversion each,
and their types, shapes and ranges are checked on the blocks.

The contract stays the one of :class:`~schemas.messages.Tick`: :func:`decode_tick` accepts a payload
only if the model would (exact types, every constraint of the model and of its ``_shape`` check); whenever the cheap
check is not sure — an unusual type pydantic may coerce, a value out of range, a missing or foreign field, another
schema version — it hands the payload to the full :func:`~schemas.codec.decode`, which either raises the
typed :class:`~schemas.base.DecodeError` naming the field or returns the validated model. Both paths give
the same :class:`TickArrays`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from schemas.base import DecodeError
from schemas.codec import KIND_FIELD, VERSION_FIELD, decode, unpack_envelope
from schemas.messages import MAX_ROBOTS, Tick

#: integer per-robot fields, in the row order of :attr:`TickArrays.ints`
INT_ROWS = ("x", "y", "target_x", "target_y", "prev_target_x", "prev_target_y", "mission", "prev_mission", "task",
            "prev_task", "loader", "heading", "partner")
#: boolean per-robot fields, in the row order of :attr:`TickArrays.flags`
FLAG_ROWS = ("is_agv", "needs_picker", "busy", "carrying", "carrying_requested", "handled")
#: robot-id lists of any length (ascending checks: each entry a robot id of this tick)
ID_LISTS = ("mission_order", "free_pickers", "delivered_by")
_COORD, _TASK = 65536, 2**63
_FIELDS = frozenset(Tick.model_fields)
_REQUIRED = frozenset(name for name, f in Tick.model_fields.items() if f.is_required())


@dataclass(slots=True, eq=False)
class TickArrays:
    """A decoded, validated ``Tick`` as arrays: ``ints[i]`` is field ``INT_ROWS[i]``, ``flags[i]`` ``FLAG_ROWS[i]``."""

    t: int
    sim_time: float
    grid_rows: int
    grid_cols: int
    ints: np.ndarray  # (len(INT_ROWS), n) int64
    flags: np.ndarray  # (len(FLAG_ROWS), n) bool
    reward: np.ndarray  # (n,) float64
    mission_order: list[int]
    free_pickers: list[int]
    delivered_by: list[int]
    request_queue: list[int]
    loads: list[tuple[int, int]]
    unloads: list[tuple[int, int]]
    has_previous: bool
    final: bool
    replied: list[int] = field(default_factory=list)
    deliveries_total: int | None = None

    @property
    def n(self) -> int:
        return self.ints.shape[1]

    @property
    def deliveries(self) -> int:
        return len(self.delivered_by)

    def row(self, name: str) -> np.ndarray:
        return self.ints[INT_ROWS.index(name)] if name in INT_ROWS else self.flags[FLAG_ROWS.index(name)]


def _exact_ints(values: Any, lo: int, hi: int) -> bool:
    """A list of plain ints (no bools: the model would turn them into ints, the slow path does that) in [lo, hi)."""
    return type(values) is list and (not values or (set(map(type, values)) == _INT and lo <= min(values)
                                                    and max(values) < hi))


_ROWS = INT_ROWS + FLAG_ROWS
_INT = {int}
_BOUNDS: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}


def _bounds(rows: int, cols: int, ids: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-row [low, high) of :data:`INT_ROWS` then :data:`FLAG_ROWS` (the model's field constraints, its grid and
    robot-id checks; flags must be 0 or 1). Cached: a run has one grid and one fleet."""
    got = _BOUNDS.get((rows, cols, ids))
    if got is None:
        flags = len(FLAG_ROWS)
        low = np.array([0, 0, -1, -1, -1, -1, 0, 0, 0, 0, -1, 0, -1] + [0] * flags)[:, None]
        high = np.array([cols, rows, cols, rows, cols, rows, 4, 4, _TASK - 1, _TASK - 1, ids, 4, ids]
                        + [2] * flags)[:, None]
        if len(_BOUNDS) > 64:
            _BOUNDS.clear()
        got = _BOUNDS[(rows, cols, ids)] = (low, high)
    return got


def _cheap(body: dict[str, Any]) -> TickArrays | None:
    """The arrays of a tick body if it is certainly valid, else None (the caller takes the full decode)."""
    keys = body.keys()
    if not (_REQUIRED <= keys and keys <= _FIELDS):
        return None
    t, sim_time, rows, cols = body["t"], body["sim_time"], body["grid_rows"], body["grid_cols"]
    has_previous, final = body["has_previous"], body.get("final", False)
    total = body.get("deliveries_total")
    if not (total is None or (type(total) is int and 0 <= total < _TASK)):
        return None
    if not (type(t) is int and t >= 0 and type(sim_time) is float and math.isfinite(sim_time) and sim_time >= 0.0
            and type(rows) is int and 1 <= rows < _COORD and type(cols) is int and 1 <= cols < _COORD
            and type(has_previous) is bool and type(final) is bool):
        return None
    try:
        # one conversion for every per-robot list: int64 only if each entry is an int or a bool (the model takes a
        # bool as an int, and 0/1 as a bool, with the same values); a float, string, None or nested list gives
        # another dtype, ragged rows raise
        block = np.array([body[name] for name in _ROWS])
        reward = np.array(body["reward"])
    except (ValueError, TypeError, OverflowError):
        return None
    if block.dtype != np.int64 or block.ndim != 2 or reward.dtype != np.float64:
        return None
    n = block.shape[1]
    if n == 0 or reward.shape != (n,) or not np.isfinite(reward).all():
        return None
    ids = min(n, MAX_ROBOTS)
    low, high = _bounds(rows, cols, ids)
    if not ((block >= low).all() and (block < high).all()):
        return None
    lists = [body[name] for name in ID_LISTS]
    loads, unloads = body["loads"], body["unloads"]
    replied = body.get("replied", [])
    if not (type(loads) is list and type(unloads) is list and all(type(v) is list for v in (*lists, replied))
            and all(type(p) is list and len(p) == 2 for p in loads + unloads)):
        return None
    robot_ids = [v for row in lists for v in row] + [v for p in loads + unloads for v in p]
    if not (_exact_ints(robot_ids, 0, ids) and _exact_ints(body["request_queue"], 0, _TASK)
            and _exact_ints(replied, 0, _TASK)):
        return None
    pairs = [[(a, b) for a, b in loads], [(a, b) for a, b in unloads]]
    split = len(INT_ROWS)
    return TickArrays(t, sim_time, rows, cols, block[:split], block[split:] != 0, reward, *lists,
                      body["request_queue"], *pairs, has_previous, final, replied, total)


def arrays_from_tick(tick: Tick) -> TickArrays:
    """The arrays of a validated Tick (the full decode's path, and tests).

    Raises DecodeError for a task id beyond 64 bits (valid for the model, which sets no upper bound, but no array
    or agent can hold it)."""
    d = tick.__dict__
    try:
        ints = np.array([d[name] for name in INT_ROWS], dtype=np.int64).reshape(len(INT_ROWS), tick.n)
    except OverflowError:
        field = next((name for name in INT_ROWS if any(v >= _TASK for v in d[name])), "<root>")
        raise DecodeError(field, "an entry does not fit in 64 bits", kind=Tick.KIND) from None
    return TickArrays(
        tick.t, float(tick.sim_time), tick.grid_rows, tick.grid_cols, ints,
        np.array([d[name] for name in FLAG_ROWS], dtype=bool).reshape(len(FLAG_ROWS), tick.n),
        np.array(tick.reward, dtype=float), list(tick.mission_order), list(tick.free_pickers),
        list(tick.delivered_by), list(tick.request_queue), [tuple(p) for p in tick.loads],
        [tuple(p) for p in tick.unloads], bool(tick.has_previous), bool(tick.final), list(tick.replied),
        tick.deliveries_total)


def decode_tick(data: bytes | bytearray | memoryview) -> TickArrays:
    """Decode a ``tick`` payload into arrays; raises DecodeError naming the field exactly as ``decode(data, Tick)``."""
    kind, body = unpack_envelope(data)
    version = body.get(VERSION_FIELD)
    if kind == Tick.KIND and type(version) is int and version == Tick.VERSION:
        arrays = _cheap(body)
        if arrays is not None:
            return arrays
    return arrays_from_tick(decode(data, Tick))


def encode_tick_body(body: dict[str, Any]) -> bytes:
    """The wire bytes of a tick whose field map the sim built itself from its own arrays (no model round trip).

    ``body`` must hold exactly the Tick's fields as plain Python values; tests check that
    ``decode(encode_tick_body(b), Tick) == Tick(**b)``.
    """
    return msgpack.packb({**body, VERSION_FIELD: Tick.VERSION, KIND_FIELD: Tick.KIND}, use_bin_type=True)
