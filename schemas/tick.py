"""The Tick, the one big message every process handles every tick: its model, its fast codec and the agents'
observation of it.

The model
---------
:class:`Tick` is the world snapshot the sim publishes on ``sim/tick`` at every tick (docs/services.md).

The fast codec
--------------
Validated-but-cheap decode and encode of the tick. Why: a distributed tick runs ~20 processes on 2 cores, so each process wakes up with cold caches, and the work it
touches per tick is what costs (docs/services.md, Performance). Validating a ``Tick`` through pydantic walks ~650
list elements one by one; here the per-robot lists become two numpy blocks (integers, flags) in one conversion each,
and their types, shapes and ranges are checked on the blocks.

The contract stays the one of :class:`Tick`: :func:`decode_tick` accepts a payload only if the model would (exact types, every constraint of the model and of its ``_shape`` check); whenever the cheap
check is not sure — an unusual type pydantic may coerce, a value out of range, a missing or foreign field, another
schema version — it hands the payload to the full :func:`~schemas.codec.decode`, which either raises the
typed :class:`~schemas.base.DecodeError` naming the field or returns the validated model. Both paths give
the same :class:`TickArrays`.

Per-robot rows of the decoded blocks are reached by field name (:data:`INT_ROWS`, :data:`FLAG_ROWS`, the maps
:data:`INT_ROW` and :data:`FLAG_ROW`), never by position.

The observation
---------------
:class:`TickObservation` is what an agent sees at one tick: the plain-array content of the Tick; the sim
builds the Tick from it (:func:`tick_fields`), an agent rebuilds it from the decoded arrays
(:func:`observation_from_arrays`). An agent's brain learns only from a sequence of :class:`TickObservation` objects and decides dispatch
requests from the latest one; it never reads the warehouse or another agent's memory. The sim's
controller (``services.world.cta``) produces one observation per tick, and the distributed
services carry exactly these fields.

Timing (docs/services.md): the observation for tick ``t`` is taken *after* the controller has assigned items
and advanced the AGV missions for step ``t`` and *before* pickers are dispatched. It carries two blocks:

* the ``prev_*`` block and ``delivered``/``reward``/``loader`` describe step ``t-1`` as it was executed
  (missions after dispatch and release, deliveries and rewards of that environment step). An agent
  applies its plasticity update for step ``t-1`` from this block. At ``t == 0`` there is no previous
  step and ``has_previous`` is false.
* ``mission``/``target``/``task``/``needs_picker``/``free_picker``/``request_order`` describe step ``t``
  before dispatch: the AGVs' missions and what a dispatch decision needs.

``cells`` are the robots' cells at the start of tick ``t``, i.e. after step ``t-1`` moved them: the
positions the reference's update for step ``t-1`` reads, and the positions Proximity uses at step ``t``.

Agent index convention: ``0 .. n_agvs-1`` are AGVs, ``n_agvs .. n-1`` are pickers (TA-RWARE's order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Annotated, Any, ClassVar

import msgpack
import numpy as np
from pydantic import Field, model_validator
from pydantic_core import PydanticCustomError

from schemas.base import DecodeError, Message
from schemas.codec import KIND_FIELD, VERSION_FIELD, decode, unpack_envelope
from schemas.fields import (
    DISPATCH_OUTCOMES,
    MAX_ROBOTS,
    Coord,
    Finite,
    MissionType,
    OptCoord,
    OptRobotId,
    OutcomeCounts,
    RobotId,
    SimTime,
    TickNo,
    length_mismatch,
    robot_id_out_of_range,
)


# ------------------------------------------------------------------------------------------------------------------
# The model
# ------------------------------------------------------------------------------------------------------------------
class Tick(Message):
    """Phase 1 of tick ``t``: the world snapshot after step t−1, published by the sim on ``sim/tick``.

    Everything an agent needs for its plasticity update of step t−1 and for dispatch at t comes from here.
    """

    KIND = "tick"

    t: TickNo
    sim_time: SimTime = Field(description="t·Δ, seconds of robot time")
    grid_rows: Annotated[int, Field(ge=1, lt=65536)]
    grid_cols: Annotated[int, Field(ge=1, lt=65536)]
    # -- per robot (index = robot id; AGVs first, then pickers, as in TA-RWARE), state at the start of tick t ----
    x: list[Coord]
    y: list[Coord]
    heading: list[Annotated[int, Field(ge=0, le=3)]] = Field(description="Heading: UP=0 DOWN=1 LEFT=2 RIGHT=3")
    is_agv: list[bool]
    busy: list[bool]
    carrying: list[bool] = Field(description="AGV carries a shelf")
    carrying_requested: list[bool] = Field(description="the carried shelf is in the request queue")
    # missions of step t before dispatch
    mission: list[Annotated[int, Field(ge=0, le=3)]] = Field(description="MissionType of the current mission")
    target_x: list[OptCoord] = Field(description="target cell of the current mission, -1 = none")
    target_y: list[OptCoord]
    task: list[Annotated[int, Field(ge=0)]] = Field(
        description="requested-shelf id the robot works on (1-based), 0 = none; a picker's is its AGV's")
    needs_picker: list[bool] = Field(description="AGV whose mission needs a picker at its target and has none")
    partner: list[OptRobotId] = Field(
        description="AGV: picker committed to its target cell; picker: AGV it serves; -1 = none")
    # -- fleet-level ---------------------------------------------------------------------------------------------
    mission_order: list[RobotId] = Field(description="AGVs holding a mission, in the controller's mission order "
                                                     "(requests are resolved in this order)")
    free_pickers: list[RobotId] = Field(description="pickers with no assignment, ascending id")
    request_queue: list[Annotated[int, Field(ge=0)]] = Field(description="requested shelf ids, queue order")
    # -- what happened in step t−1 (the plasticity update of step t−1 reads only this block) ----------------------
    has_previous: bool = Field(description="false at t = 0: the prev_* block describes no step")
    prev_mission: list[Annotated[int, Field(ge=0, le=3)]]
    prev_target_x: list[OptCoord] = Field(description="mission targets during step t−1 (co-assignment J^{t−1})")
    prev_target_y: list[OptCoord]
    prev_task: list[Annotated[int, Field(ge=0)]]
    reward: list[Finite] = Field(description="each robot's individual reward in step t−1")
    delivered_by: list[RobotId] = Field(description="AGVs that delivered in step t−1 (len = deliveries)")
    loader: list[OptRobotId] = Field(description="for an AGV that delivered in step t−1: the picker that loaded "
                                                 "the delivered shelf, else -1")
    loads: list[tuple[RobotId, RobotId]] = Field(description="(AGV, picker) co-located at a load in step t−1")
    unloads: list[tuple[RobotId, RobotId]] = Field(description="(AGV, picker) co-located at an unload in step t−1")
    deliveries_total: Annotated[int, Field(ge=0, lt=2**63)] | None = Field(
        default=None, description="cumulative deliveries up to step t−1 (a monitor that joins late continues the "
                                  "cumulative count from it); None = not given")
    handled: list[bool] = Field(description="robots that took part in a load or unload in step t−1")
    final: bool = Field(default=False, description="the report after the last step: agents learn, nobody asks")
    # synchronisation, not world state: an AGV takes its decision of step t once this many replies to it have arrived
    # (delivered, held or lost by the network), so whether it heard an answer does not depend on wall-clock races
    # between the pickers' path and the sim's (cumulative, so a Tick an AGV missed hides nothing)
    replied: list[Annotated[int, Field(ge=0)]] = Field(
        default_factory=list, description="per AGV: HelpReplies sent to it so far (cumulative; empty: none)")
    # telemetry for the record (the monitor's ticks are never faulted): the sim's side of the dispatch protocol
    outcomes: OutcomeCounts | None = Field(
        default=None, description="the sim's cumulative dispatch outcome counters (commitments applied on time or "
                                  "late, refused as stale, duplicates) after the step boundary t·Δ; None = not given")

    PER_ROBOT: ClassVar[tuple[str, ...]] = (
        "y", "heading", "is_agv", "busy", "carrying", "carrying_requested", "mission", "target_x", "target_y",
        "task", "needs_picker", "partner", "prev_mission", "prev_target_x", "prev_target_y", "prev_task", "reward",
        "loader", "handled",
    )
    ROBOT_IDS: ClassVar[tuple[str, ...]] = ("mission_order", "free_pickers", "delivered_by", "partner", "loader")

    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def n_agvs(self) -> int:
        return sum(self.is_agv)

    @property
    def deliveries(self) -> int:
        return len(self.delivered_by)

    @model_validator(mode="after")
    def _shape(self) -> Tick:
        d = self.__dict__  # plain attribute reads: this runs for every tick in every agent
        n = len(d["x"])
        if any(len(d[name]) != n for name in self.PER_ROBOT):
            name = next(name for name in self.PER_ROBOT if len(d[name]) != n)
            raise length_mismatch(name, len(d[name]), n)
        for name in self.ROBOT_IDS:
            top = max(d[name], default=-1)
            if top >= n:
                raise robot_id_out_of_range(name, top, n)
        for name in ("loads", "unloads"):
            top = max((max(pair) for pair in d[name]), default=-1)
            if top >= n:
                raise robot_id_out_of_range(name, top, n)
        cols, rows = d["grid_cols"], d["grid_rows"]
        for name, limit in (("x", cols), ("target_x", cols), ("prev_target_x", cols),
                            ("y", rows), ("target_y", rows), ("prev_target_y", rows)):
            top = max(d[name], default=-1)
            if top >= limit:
                raise PydanticCustomError(
                    "off_grid", "{field} holds {value}, outside the {limit}-cell grid dimension",
                    {"field": name, "value": top, "limit": limit})
        return self


# ------------------------------------------------------------------------------------------------------------------
# The fast codec
# ------------------------------------------------------------------------------------------------------------------
#: integer per-robot fields, in the row order of :attr:`TickArrays.ints`
INT_ROWS = ("x", "y", "target_x", "target_y", "prev_target_x", "prev_target_y", "mission", "prev_mission", "task",
            "prev_task", "loader", "heading", "partner")
#: boolean per-robot fields, in the row order of :attr:`TickArrays.flags`
FLAG_ROWS = ("is_agv", "needs_picker", "busy", "carrying", "carrying_requested", "handled")
#: robot-id lists of any length (ascending checks: each entry a robot id of this tick)
ID_LISTS = ("mission_order", "free_pickers", "delivered_by")
#: field name -> its row in :attr:`TickArrays.ints` / :attr:`TickArrays.flags`
INT_ROW = {name: i for i, name in enumerate(INT_ROWS)}
FLAG_ROW = {name: i for i, name in enumerate(FLAG_ROWS)}
#: coordinate rows read as (n, 2) cell blocks: each y row follows its x row, so a cell block is a view, not a copy
_PAIRS = (("x", "y"), ("target_x", "target_y"), ("prev_target_x", "prev_target_y"))
if any(INT_ROW[y] != INT_ROW[x] + 1 for x, y in _PAIRS):
    raise ImportError("INT_ROWS must keep each y row right after its x row")
_CELL_ROW = {pair: INT_ROW[pair[0]] for pair in _PAIRS}
_COORD, _TASK = 65536, 2**63
_FIELDS = frozenset(Tick.model_fields)
_REQUIRED = frozenset(name for name, f in Tick.model_fields.items() if f.is_required())
_OUTCOMES = frozenset(DISPATCH_OUTCOMES)


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
    outcomes: dict[str, int] | None = None

    @property
    def n(self) -> int:
        return self.ints.shape[1]

    @property
    def deliveries(self) -> int:
        return len(self.delivered_by)

    def row(self, name: str) -> np.ndarray:
        """The per-robot row of field ``name`` (a view into the block)."""
        return self.ints[INT_ROW[name]] if name in INT_ROW else self.flags[FLAG_ROW[name]]

    def cells(self, x: str, y: str) -> np.ndarray:
        """(n, 2) view of the coordinate rows ``x`` and ``y`` (one of the pairs of :data:`_PAIRS`)."""
        i = _CELL_ROW[(x, y)]
        return self.ints[i:i + 2].T


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
        limits = {"x": (0, cols), "y": (0, rows), "target_x": (-1, cols), "target_y": (-1, rows),
                  "prev_target_x": (-1, cols), "prev_target_y": (-1, rows), "mission": (0, 4), "prev_mission": (0, 4),
                  "task": (0, _TASK - 1), "prev_task": (0, _TASK - 1), "loader": (-1, ids), "heading": (0, 4),
                  "partner": (-1, ids), **{name: (0, 2) for name in FLAG_ROWS}}
        low = np.array([limits[name][0] for name in _ROWS])[:, None]
        high = np.array([limits[name][1] for name in _ROWS])[:, None]
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
    outcomes = body.get("outcomes")
    if not (outcomes is None or (type(outcomes) is dict and outcomes.keys() <= _OUTCOMES
                                 and _exact_ints(list(outcomes.values()), 0, _TASK))):
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
                      body["request_queue"], *pairs, has_previous, final, replied, total, outcomes)


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
        tick.deliveries_total, None if tick.outcomes is None else dict(tick.outcomes))


def decode_tick(data: bytes | bytearray | memoryview) -> TickArrays:
    """Decode a ``tick`` payload into arrays; raises DecodeError naming the field exactly as ``decode(data, Tick)``."""
    kind, body = unpack_envelope(data)
    version = body.get(VERSION_FIELD)
    if kind == Tick.KIND and type(version) is int and version == Tick.VERSION:
        arrays = _cheap(body)
        if arrays is not None:
            return arrays
    return arrays_from_tick(decode(data, Tick))


def tick_number(data: bytes | bytearray | memoryview) -> int:
    """The tick number of a ``tick`` payload without validating the rest of it (for a reader that needs only the
    number); raises DecodeError naming the field."""
    kind, body = unpack_envelope(data)
    if kind != Tick.KIND:
        raise DecodeError(KIND_FIELD, f"expected a {Tick.KIND!r} message, got {kind[:64]!r}", kind=kind)
    t = body.get("t")
    if type(t) is not int or t < 0:
        raise DecodeError("t", f"expected an integer >= 0, got {type(t).__name__}", kind=Tick.KIND)
    return t


def encode_tick_body(body: dict[str, Any]) -> bytes:
    """The wire bytes of a tick whose field map the sim built itself from its own arrays (no model round trip).

    ``body`` must hold exactly the Tick's fields as plain Python values; tests check that
    ``decode(encode_tick_body(b), Tick) == Tick(**b)``.
    """
    return msgpack.packb({**body, VERSION_FIELD: Tick.VERSION, KIND_FIELD: Tick.KIND}, use_bin_type=True)


# ------------------------------------------------------------------------------------------------------------------
# The observation
# ------------------------------------------------------------------------------------------------------------------
#: Missions whose rack-cell target needs a picker standing on it (load or unload).
NEEDS_PICKER = (MissionType.PICKING, MissionType.RETURNING)

NO_CELL = -1  # coordinate used for "no target"


@dataclass(frozen=True, eq=False)
class TickObservation:
    """One tick's world snapshot as seen by every agent (arrays are indexed by agent)."""

    #: the tick index (the step about to be decided)
    t: int
    #: number of AGVs (agents ``0 .. n_agvs-1``)
    n_agvs: int
    #: number of pickers (agents ``n_agvs .. n-1``)
    n_pickers: int
    #: (rows, cols) of the grid: used by the reference's normalised positions x/cols, y/rows
    grid_shape: tuple[int, int]
    #: (n, 2) int, (x, y) cell of each robot at the start of the tick
    cells: np.ndarray
    #: (n,) int8 MissionType of each robot at tick t before dispatch (pickers: PICKING if assigned)
    mission: np.ndarray
    #: (n, 2) int, (x, y) of each robot's mission target at tick t before dispatch, NO_CELL if none
    target: np.ndarray
    #: (n,) int, task id (1-based requested-shelf id) each robot works on at tick t, 0 if none;
    #: a picker's task is that of the AGV it is serving
    task: np.ndarray
    #: (n,) bool, AGVs whose mission needs a picker at its target and none is assigned there
    needs_picker: np.ndarray
    #: (n,) bool, pickers with no assignment (candidates for dispatch)
    free_picker: np.ndarray
    #: (k,) int, the AGVs that hold a mission, in the sim's mission order (order of first assignment);
    #: requests are resolved in this order
    request_order: np.ndarray
    #: whether the ``prev_*`` block describes a real step (false at t == 0)
    has_previous: bool
    #: (n,) int8 MissionType of each robot during step t-1 (after dispatch and release)
    prev_mission: np.ndarray
    #: (n, 2) int, mission targets during step t-1: the co-assignment signal J^{t-1}
    prev_target: np.ndarray
    #: (n,) int, task ids during step t-1
    prev_task: np.ndarray
    #: (n,) bool, AGVs that received TA-RWARE's +1 delivery reward in step t-1
    delivered: np.ndarray
    #: (n,) float, each robot's individual TA-RWARE reward in step t-1
    reward: np.ndarray
    #: (n,) int, for an AGV that delivered in step t-1: the picker that loaded the delivered shelf
    #: (-1 if unknown or not delivered)
    loader: np.ndarray
    #: (n,) bool, robots that took part in a load or unload in step t-1 (the AGV and the picker on its cell)
    handled: np.ndarray
    #: true for the observation after the last step: agents learn from it, nothing is dispatched
    final: bool = False

    @property
    def n(self) -> int:
        return self.n_agvs + self.n_pickers

    @property
    def deliveries(self) -> int:
        """Deliveries in step t-1 (the reference's ``delivery`` argument)."""
        return int(np.count_nonzero(self.delivered))

    def requesters(self) -> np.ndarray:
        """AGVs that ask for a picker at this tick, in mission order."""
        order = self.request_order
        return order[self.needs_picker[order]]

    def coassignment(self, previous: bool = True) -> np.ndarray:
        """J: (n, n) 0/1, pairs whose mission targets are the same cell (zero diagonal).

        This is the reference's "Jaccard" of singleton target sets.
        """
        tgt = self.prev_target if previous else self.target
        # one integer per target cell (y < 65536 on the wire); a robot without a target gets a code of its own,
        # equal to nobody else's: then one comparison gives J
        code = tgt[:, 0] * 65536 + tgt[:, 1]
        none = tgt[:, 0] == NO_CELL
        if none.any():
            code = np.where(none, -(2**40) - np.arange(len(code)), code)  # below every cell code x·65536 + y ≥ −1
        j = code[:, None] == code[None, :]
        np.fill_diagonal(j, False)
        return j.astype(float)

    def task_overlap(self, previous: bool = True) -> np.ndarray:
        """(n, n) 0/1 Jaccard of the singleton task sets (same task id, both non-zero)."""
        task = self.prev_task if previous else self.task
        j = (task[:, None] == task[None, :]) & (task[:, None] > 0)
        np.fill_diagonal(j, False)
        return j.astype(float)

    def nearest_free_picker(self, agv: int, free: np.ndarray | None = None) -> int:
        """The free picker nearest (Manhattan, from its cell) to ``agv``'s target; -1 if none.

        Ties go to the lowest index, as in the reference. ``free`` overrides ``free_picker``
        (the sequential dispatch removes pickers taken earlier in the same tick).
        """
        free = self.free_picker if free is None else free
        # a scan in plain Python: a fleet's few pickers cost less than numpy's calls on arrays this small
        tx, ty = self.target_list[agv]
        cells = self.cell_list
        best, best_d = -1, 0
        for i in np.flatnonzero(free).tolist():
            x, y = cells[i]
            d = abs(x - tx) + abs(y - ty)
            if best < 0 or d < best_d:  # strictly nearer: ties keep the lowest index
                best, best_d = i, d
        return best

    # The arrays as lists, read by the per-AGV scans of a tick (the observation's arrays are never written after it
    # is made; dataclasses.replace and replace_fields make another observation, without these)
    @cached_property
    def cell_list(self) -> list[list[int]]:
        """``cells.tolist()``, made once: [x, y] of each robot (read it, do not change it)."""
        return self.cells.tolist()

    @cached_property
    def target_list(self) -> list[list[int]]:
        """``target.tolist()``, made once: [x, y] of each robot's mission target (read it, do not change it)."""
        return self.target.tolist()


_OBSERVATION_FIELDS = tuple(f.name for f in fields(TickObservation))


def replace_fields(obs: TickObservation, **changes) -> TickObservation:
    """``dataclasses.replace(obs, **changes)`` without its pass through ``__init__``: an observation derives nothing
    from its fields when made, so they are all it holds (its cached lists stay behind, as with ``replace``). An agent
    makes one for its own view whenever it has moved since the fleet's broadcast: several a tick."""
    unknown = changes.keys() - set(_OBSERVATION_FIELDS)
    if unknown:
        raise TypeError(f"replace_fields: {sorted(unknown)[0]!r} is not a field of TickObservation")
    out = object.__new__(TickObservation)
    state, src = out.__dict__, obs.__dict__
    for name in _OBSERVATION_FIELDS:
        state[name] = src[name]
    state.update(changes)
    return out


# ------------------------------------------------------------------------------------------------------------------
# Observation <-> Tick
# ------------------------------------------------------------------------------------------------------------------
def tick_fields(obs: TickObservation, sim_time: float, extra: dict | None = None) -> dict:
    """The Tick's field map as plain Python values. The sim encodes it directly (:func:`encode_tick_body`): the
    model's validation of the sim's own arrays is the tests' job, not every tick's."""
    cells = obs.cells
    return dict(
        t=int(obs.t), sim_time=float(sim_time),
        grid_rows=int(obs.grid_shape[0]), grid_cols=int(obs.grid_shape[1]),
        x=cells[:, 0].tolist(), y=cells[:, 1].tolist(),
        is_agv=[True] * obs.n_agvs + [False] * obs.n_pickers,
        mission=obs.mission.tolist(), target_x=obs.target[:, 0].tolist(), target_y=obs.target[:, 1].tolist(),
        task=obs.task.tolist(), needs_picker=obs.needs_picker.tolist(),
        mission_order=obs.request_order.tolist(),
        free_pickers=np.flatnonzero(obs.free_picker).tolist(),
        has_previous=bool(obs.has_previous),
        prev_mission=obs.prev_mission.tolist(), prev_target_x=obs.prev_target[:, 0].tolist(),
        prev_target_y=obs.prev_target[:, 1].tolist(), prev_task=obs.prev_task.tolist(),
        delivered_by=np.flatnonzero(obs.delivered).tolist(),
        reward=np.asarray(obs.reward, dtype=float).tolist(), loader=obs.loader.tolist(),
        handled=np.asarray(obs.handled, dtype=bool).tolist(), final=bool(obs.final),
        **(extra or {}),
    )


def onboard_fields(tick: dict, robot: int, free: bool, replied: int = 0, refused: int = 0, messaged: int = 0) -> dict:
    """One robot's :class:`~schemas.messages.OnBoard` field map, read off the Tick field map the sim built
    (:func:`tick_fields` plus the world fields): what that robot senses of itself. ``free``: a picker without an
    assignment; ``replied``, ``refused``, ``messaged``: the synchronisation counts of its decision point (the last
    only when a policy has sent any: the field's default)."""
    return dict(
        t=tick["t"], robot=robot, x=tick["x"][robot], y=tick["y"][robot], heading=tick["heading"][robot],
        mission=tick["mission"][robot], target_x=tick["target_x"][robot], target_y=tick["target_y"][robot],
        task=tick["task"][robot], needs_picker=tick["needs_picker"][robot], free=free,
        carrying=tick["carrying"][robot], reward=tick["reward"][robot], handled=tick["handled"][robot],
        final=tick["final"], replied=replied, refused=refused, **({"messaged": messaged} if messaged else {}))


def tick_from_observation(obs: TickObservation, sim_time: float, extra: dict | None = None) -> Tick:
    """The wire form of an observation (every field an agent's policy reads)."""
    return Tick(**tick_fields(obs, sim_time, extra))


def observation_from_tick(tick: Tick, steps: int | None = None) -> TickObservation:
    """The policy's observation rebuilt from a Tick message alone (inverse of :func:`tick_from_observation`)."""
    return observation_from_arrays(arrays_from_tick(tick), steps)


def observation_from_arrays(tick: TickArrays, steps: int | None = None) -> TickObservation:
    """The observation of a decoded tick (:func:`decode_tick`): views of its two blocks.

    Each agent does this every tick, so it is a handful of slices; the blocks are the agent's own (fresh per tick).
    """
    row = tick.row
    is_agv = row("is_agv")
    n = is_agv.shape[0]
    n_agvs = int(np.count_nonzero(is_agv))
    free = np.zeros(n, dtype=bool)
    free[tick.free_pickers] = True
    delivered = np.zeros(n, dtype=bool)
    delivered[tick.delivered_by] = True
    return TickObservation(
        t=tick.t, n_agvs=n_agvs, n_pickers=n - n_agvs, grid_shape=(tick.grid_rows, tick.grid_cols),
        cells=tick.cells("x", "y"), mission=row("mission").astype(np.int8), target=tick.cells("target_x", "target_y"),
        task=row("task"), needs_picker=row("needs_picker"), free_picker=free,
        request_order=np.array(tick.mission_order, dtype=np.int64), has_previous=tick.has_previous,
        prev_mission=row("prev_mission").astype(np.int8), prev_target=tick.cells("prev_target_x", "prev_target_y"),
        prev_task=row("prev_task"), delivered=delivered, reward=tick.reward, loader=row("loader"),
        handled=row("handled"), final=tick.final or (steps is not None and tick.t >= steps),
    )
