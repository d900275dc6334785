"""Every wire message of a run: the tick protocol, faults, records (docs/services.md).

Per-robot data travels as parallel arrays indexed by robot id (0..N−1), never as per-robot dicts: a Tick of 128
robots stays a few kilobytes of msgpack. ``-1`` means "none" in id and cell arrays.
"""

from __future__ import annotations

from enum import Enum, IntEnum
from typing import Annotated, ClassVar

from pydantic import Field, JsonValue, field_validator, model_validator
from pydantic_core import PydanticCustomError

from schemas.base import Message
from schemas.faults import FaultOp, FaultSpec
from schemas.keys import check_chunk

MAX_ROBOTS = 4096
RobotId = Annotated[int, Field(ge=0, lt=MAX_ROBOTS)]
OptRobotId = Annotated[int, Field(ge=-1, lt=MAX_ROBOTS)]  # -1 = none
Coord = Annotated[int, Field(ge=0, lt=65536)]
OptCoord = Annotated[int, Field(ge=-1, lt=65536)]  # -1 = no target
TickNo = Annotated[int, Field(ge=0)]
SimTime = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Seq = Annotated[int, Field(ge=0, lt=2**63)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class Heading(IntEnum):
    """TA-RWARE's direction enum order."""

    UP = 0
    DOWN = 1
    LEFT = 2
    RIGHT = 3


class MissionType(IntEnum):
    """A robot's current mission kind (TA-RWARE heuristic vocabulary, 0 = none)."""

    NONE = 0
    PICKING = 1  # AGV: fetch the requested shelf at a rack cell; picker: help at that rack cell
    DELIVERING = 2  # AGV: carry the shelf to a goal cell
    RETURNING = 3  # AGV: put the shelf back on an empty rack cell


class Role(str, Enum):
    agv = "agv"
    picker = "picker"


class Phase(IntEnum):
    """Which phase of the two-phase tick an Ack closes (the tick and the resolve round, docs/services.md)."""

    TICK = 0
    RESOLVE = 1


def _mismatch(field: str, got: int, want: int) -> PydanticCustomError:
    return PydanticCustomError(
        "length_mismatch", "{field} has {got} entries, expected {want} (one per robot)",
        {"field": field, "got": got, "want": want},
    )


def _out_of_range(field: str, value: int, n: int) -> PydanticCustomError:
    return PydanticCustomError(
        "robot_id_range", "{field} holds robot id {value}, but the tick has {n} robots",
        {"field": field, "value": value, "n": n},
    )


# ------------------------------------------------------------------------------------------------------------------
# Tick protocol (docs/services.md)
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
            raise _mismatch(name, len(d[name]), n)
        for name in self.ROBOT_IDS:
            top = max(d[name], default=-1)
            if top >= n:
                raise _out_of_range(name, top, n)
        for name in ("loads", "unloads"):
            top = max((max(pair) for pair in d[name]), default=-1)
            if top >= n:
                raise _out_of_range(name, top, n)
        cols, rows = d["grid_cols"], d["grid_rows"]
        for name, limit in (("x", cols), ("target_x", cols), ("prev_target_x", cols),
                            ("y", rows), ("target_y", rows), ("prev_target_y", rows)):
            top = max(d[name], default=-1)
            if top >= limit:
                raise PydanticCustomError(
                    "off_grid", "{field} holds {value}, outside the {limit}-cell grid dimension",
                    {"field": name, "value": top, "limit": limit})
        return self


class Ack(Message):
    """An agent closes a phase of tick ``t``; in phase TICK it lists the pickers it asked for help."""

    KIND = "ack"

    t: TickNo
    agent: RobotId
    phase: Phase = Phase.TICK
    requests_sent: list[RobotId] = Field(default_factory=list, description="picker ids asked this tick")
    seq: Seq = 0
    # Phase TICK only, optional (older agents omit them): the monitor's per-tick link and η streams come from the
    # acks, so an agent publishes its full AgentState only every k ticks.
    links: list[RobotId] | None = Field(
        default=None, description="out-links after the plasticity update of step t−1 (robot ids j with A[i,j]=1)")
    eta: Finite | None = Field(default=None, description="the agent's η after that update")
    # Phase RESOLVE only (synchronisation, never faulted): what the sim must wait for before the step boundary
    committed_to: RobotId | None = Field(
        default=None, description="RESOLVE: the AGV this picker sent a Commit for (the sim waits for it to arrive)")
    more: bool = Field(default=False, description="RESOLVE: requests still on their way to or waiting at this "
                                                  "picker; the sim gives it the next decision point too")
    replied_to: list[RobotId] = Field(default_factory=list, description="RESOLVE: AGVs this picker sent a "
                                      "HelpReply (the next Tick tells them to wait for it)")


class Resolve(Message):
    """Phase 2 of tick ``t``: for each picker, the AGVs whose requests it must expect, in mission order."""

    KIND = "resolve"

    t: TickNo
    pickers: list[RobotId]
    requesters: list[list[RobotId]] = Field(description="requesters[i] = AGVs that asked pickers[i]")

    @model_validator(mode="after")
    def _shape(self) -> Resolve:
        if len(self.requesters) != len(self.pickers):
            raise PydanticCustomError(
                "length_mismatch", "{field} has {got} entries, expected {want} (one per picker)",
                {"field": "requesters", "got": len(self.requesters), "want": len(self.pickers)})
        return self

    def expected(self, picker: int) -> list[int]:
        for p, agvs in zip(self.pickers, self.requesters):
            if p == picker:
                return list(agvs)
        return []


class HelpRequest(Message):
    """AGV → picker: come to my mission's target cell."""

    KIND = "help_request"

    t: TickNo
    agv: RobotId
    picker: RobotId
    target_x: Coord
    target_y: Coord
    mission: Annotated[int, Field(ge=1, le=3)] = MissionType.PICKING
    seq: Seq = 0


class HelpReply(Message):
    """Picker → AGV: accepted or declined."""

    KIND = "help_reply"

    t: TickNo
    picker: RobotId
    agv: RobotId
    accepted: bool
    seq: Seq = 0
    request_seq: Seq = Field(default=0, description="seq of the HelpRequest answered (0: unknown)")


class Commit(Message):
    """Picker → sim: I take the mission of ``agv`` (the sim dispatches me when it steps the world)."""

    KIND = "commit"

    t: TickNo
    picker: RobotId
    agv: RobotId
    seq: Seq = 0
    target_x: OptCoord = Field(default=-1, description="the requested cell (-1: not given)")
    target_y: OptCoord = -1


class Refusal(Message):
    """Sim → AGV and picker: a commitment that reached the sim no longer valid (the AGV needs no picker at that
    cell, or the picker is not free); it was not applied."""

    KIND = "refusal"

    t: TickNo = Field(description="the step boundary it was refused at")
    picker: RobotId
    agv: RobotId
    commit_seq: Seq = Field(description="seq of the refused Commit")
    seq: Seq = 0


# ------------------------------------------------------------------------------------------------------------------
# Agent state, metrics, events
# ------------------------------------------------------------------------------------------------------------------
class AgentState(Message):
    """An agent's plasticity state, published every k ticks (monitor, restore after a crash)."""

    KIND = "agent_state"

    agent: RobotId
    role: Role
    t: TickNo
    w_row: list[Finite] = Field(description="this agent's row of W")
    a_row: list[bool] = Field(description="this agent's row of the link matrix A")
    theta_row: list[Finite] = Field(description="BCM thresholds of this agent's row")
    age_row: list[Annotated[int, Field(ge=0)]] = Field(description="link ages in steps")
    h: Finite = Field(description="homeostatic variable")
    eta: Finite = Field(description="neuromodulation signal")
    d_hat: Finite = Field(default=0.0, description="delivery EMA behind eta")
    seq: Seq = 0
    scalars: dict[str, Finite] = Field(default_factory=dict, description="further per-agent scalars of a policy")
    rows: dict[str, list[Finite]] = Field(default_factory=dict, description="further per-agent rows of a policy")

    @model_validator(mode="after")
    def _shape(self) -> AgentState:
        n = len(self.w_row)
        for name in ("a_row", "theta_row", "age_row"):
            got = len(getattr(self, name))
            if got != n:
                raise _mismatch(name, got, n)
        for key, row in self.rows.items():
            if len(row) != n:
                raise _mismatch(f"rows.{key}", len(row), n)
        return self


class MetricSample(Message):
    """One value (or vector) of a metric stream ``metrics/<name>`` at tick ``t``."""

    KIND = "metric"

    name: str
    t: TickNo
    sim_time: SimTime
    value: float | None = None
    values: list[float] | None = None
    labels: dict[str, str] = Field(default_factory=dict)
    unit: str | None = None

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        for chunk in value.split("/"):
            check_chunk(chunk, "metric name chunk")
        return value

    @model_validator(mode="after")
    def _one_value(self) -> MetricSample:
        if (self.value is None) == (self.values is None):
            raise PydanticCustomError("metric_value", "{field}: exactly one of value and values must be set",
                                      {"field": "value"})
        return self


class Event(Message):
    """Something that happened (fault window opened/healed, crash, restart, reject …) with its sim time."""

    KIND = "event"

    kind: str = Field(pattern=r"^[a-z][a-z0-9_.]{0,63}$")
    source: str | int = Field(default="sim")
    t: TickNo | None = None
    sim_time: SimTime | None = None
    wall_time: float | None = Field(default=None, description="Unix seconds, for wall-time runs and logs")
    details: dict[str, JsonValue] = Field(default_factory=dict)


class Stop(Message):
    """Operator or supervisor asks every service of the run to stop."""

    KIND = "stop"

    reason: str = ""


# ------------------------------------------------------------------------------------------------------------------
# Faults and robot-id registration
# ------------------------------------------------------------------------------------------------------------------
class FaultCommand(Message):
    """``set`` a fault, ``list`` the active ones, ``reset`` one (``fault_id``) or all of them."""

    KIND = "fault_command"

    op: FaultOp
    spec: FaultSpec | None = None
    fault_id: str | None = None
    sender: str = "operator"
    # Apply at the start of this tick rather than on arrival: every process then changes its faults at the same sim
    # time, so a run with runtime commands is as reproducible as one with a schedule file (virtual time).
    at_tick: int | None = Field(default=None, ge=0)

    @model_validator(mode="after")
    def _op(self) -> FaultCommand:
        if self.op == "set" and self.spec is None:
            raise PydanticCustomError("missing_spec", "{field} is required for op 'set'", {"field": "spec"})
        if self.op != "set" and self.spec is not None:
            raise PydanticCustomError("extra_spec", "{field} is only allowed for op 'set'", {"field": "spec"})
        if self.op == "list" and self.at_tick is not None:
            raise PydanticCustomError("extra_at_tick", "{field} is only allowed for set and reset",
                                      {"field": "at_tick"})
        return self


class FaultReply(Message):
    """Answer to a FaultCommand: accepted or rejected (with the reason), and the faults now active."""

    KIND = "fault_reply"

    ok: bool
    error: str | None = None
    active: list[FaultSpec] = Field(default_factory=list)
    source: str | None = Field(default=None, description="the process that answered (every process holds a layer)")


class RegistrationRequest(Message):
    """An agent started without an id asks the sim's registry for one."""

    KIND = "registration_request"

    instance: str = Field(min_length=1, max_length=128, description="stable identity, e.g. container hostname")
    want_id: RobotId | None = Field(default=None, description="ask for this id back (restart)")
    want_role: Role | None = None


class RegistrationReply(Message):
    KIND = "registration_reply"

    ok: bool
    agent_id: RobotId | None = None
    role: Role | None = None
    reason: str | None = None
    n_agvs: int = Field(default=0, ge=0)
    n_pickers: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _ok(self) -> RegistrationReply:
        if self.ok:
            missing = [name for name in ("agent_id", "role") if getattr(self, name) is None]
            if missing:  # name the field that is actually missing (a corrupted role must not blame agent_id)
                raise PydanticCustomError("registration", "{field} is required when ok", {"field": missing[0]})
        return self


MESSAGE_TYPES: tuple[type[Message], ...] = (
    Tick, Ack, Resolve, HelpRequest, HelpReply, Commit, Refusal, AgentState, MetricSample, Event, Stop,
    FaultCommand, FaultReply, RegistrationRequest, RegistrationReply,
)
MESSAGES: dict[str, type[Message]] = {cls.KIND: cls for cls in MESSAGE_TYPES}

__all__ = [
    "Ack", "AgentState", "Commit", "Event", "FaultCommand", "FaultReply", "Heading", "HelpReply", "HelpRequest",
    "MESSAGES", "MESSAGE_TYPES", "MetricSample", "MissionType", "Phase", "Refusal", "RegistrationReply",
    "RegistrationRequest",
    "Resolve", "Role", "Stop", "Tick",
]
