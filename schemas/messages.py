"""Every wire message of a run: the tick protocol, faults, records (docs/services.md).

The Tick, its fast codec and its observation live in :mod:`schemas.tick`; the shared field types in
:mod:`schemas.fields`. Both are re-exported here for importers of the whole contract.
"""

from __future__ import annotations

from enum import Enum, IntEnum
from typing import Annotated

from pydantic import Field, JsonValue, field_validator, model_validator
from pydantic_core import PydanticCustomError

from schemas.base import Message
from schemas.codec import register_kinds
from schemas.faults import FaultOp, FaultSpec
from schemas.fields import (
    MAX_POLICY_DATA,
    MAX_POLICY_MESSAGES,
    MAX_ROBOTS,
    Coord,
    Finite,
    Heading,
    MissionType,
    OptCoord,
    OutcomeCounts,
    RobotId,
    Seq,
    SimTime,
    TickNo,
    length_mismatch,
)
from schemas.keys import check_chunk
from schemas.tick import Tick


class Role(str, Enum):
    agv = "agv"
    picker = "picker"


class Phase(IntEnum):
    """Which phase of the two-phase tick an Ack closes (the tick and the resolve round, docs/services.md)."""

    TICK = 0
    RESOLVE = 1


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
    view_age: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] | None = Field(
        default=None, description="sim seconds since the fleet state this agent acted on was sent (None: no view "
                                  "yet)")
    # Phase TICK, telemetry for the record (acks are never faulted, so the counts are exact): what became of this
    # robot's dispatch messages up to the previous step boundary (requests, expiries, declines, duplicates)
    outcomes: OutcomeCounts | None = Field(
        default=None, description="this robot's cumulative dispatch outcome counters as they stood at the start of "
                                  "tick t (before its decision of step t); a counter left out is zero")
    # Phase RESOLVE only (synchronisation, never faulted): what the sim must wait for before the step boundary
    committed_to: RobotId | None = Field(
        default=None, description="RESOLVE: the AGV this picker sent a Commit for (the sim waits for it to arrive)")
    more: bool = Field(default=False, description="RESOLVE: requests still on their way to or waiting at this "
                                                  "picker; the sim gives it the next decision point too")
    replied_to: list[RobotId] = Field(default_factory=list, description="RESOLVE: AGVs this picker sent a "
                                      "HelpReply (the next Tick tells them to wait for it)")
    # Phase TICK (synchronisation): the robots its policy messages of this tick went to (-1: every other robot);
    # the sim tells each receiver, in its next on-board state, how many to wait for
    policy_to: list[Annotated[int, Field(ge=-1, lt=MAX_ROBOTS)]] = Field(
        default_factory=list, max_length=MAX_POLICY_MESSAGES,
        description="TICK: the robots this robot's policy sent a message to (-1: all)")


class OnBoard(Message):
    """Sim → one robot, on that robot's own key: what the robot senses of itself at the start of tick ``t`` (its
    on-board state: odometry, its mission controller, its load), and the synchronisation of its decision point.

    On-board sensing is not a network message: no fault acts on it unless a scope names its key class
    (``sim/@onboard/*``). What a robot knows of the *others* reaches it only through the fleet broadcast
    (``sim/fleet``, a :class:`Tick`), which faults act on like any protocol message (docs/faults.md).
    """

    KIND = "onboard"

    t: TickNo
    robot: RobotId
    x: Coord
    y: Coord
    heading: Annotated[int, Field(ge=0, le=3)] = 0
    mission: Annotated[int, Field(ge=0, le=3)] = MissionType.NONE
    target_x: OptCoord = -1
    target_y: OptCoord = -1
    task: Annotated[int, Field(ge=0, lt=2**63)] = 0
    needs_picker: bool = Field(default=False, description="AGV: its mission needs a picker at its target, none yet")
    free: bool = Field(default=False, description="picker: it has no assignment")
    carrying: bool = False
    reward: Finite = Field(default=0.0, description="this robot's own reward in step t−1")
    handled: bool = Field(default=False, description="it took part in a load or unload in step t−1")
    final: bool = Field(default=False, description="the report after the last step: learn, do not ask")
    # synchronisation, never protocol content: an AGV takes its decision of step t once this many replies to it
    # have arrived (delivered, held or lost by the network); cumulative, so a missed one hides nothing
    replied: Annotated[int, Field(ge=0, lt=2**63)] = Field(default=0, description="AGV: HelpReplies sent to it so far")
    # likewise every robot takes it once this many refusals to it have arrived: a refusal frees an AGV to ask again
    # and ends a picker's commitment, so one still on its way would change what the robot decides
    refused: Annotated[int, Field(ge=0, lt=2**63)] = Field(default=0, description="Refusals sent to it so far")
    # and every policy message sent to it in the ticks before this one: its policy takes them at this decision point
    messaged: Annotated[int, Field(ge=0, lt=2**63)] = Field(
        default=0, description="policy messages sent to it in the ticks before this one, so far")


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
    # integers stay integers on the wire (a row of labels or counts costs a byte or two a value, not nine)
    rows: dict[str, list[int | Finite]] = Field(default_factory=dict,
                                               description="further per-agent rows of a policy")

    @model_validator(mode="after")
    def _shape(self) -> AgentState:
        n = len(self.w_row)
        for name in ("a_row", "theta_row", "age_row"):
            got = len(getattr(self, name))
            if got != n:
                raise length_mismatch(name, got, n)
        for key, row in self.rows.items():
            if len(row) != n:
                raise length_mismatch(f"rows.{key}", len(row), n)
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


class PolicyMessage(Message):
    """A robot's policy to another robot's (``to``) or to every other robot's (``to`` None): a bid, a claim, a round of
    a consensus. Sent at the robot's decision point of tick ``t`` under its own key, judged by the fault layer and the
    network profile like any protocol message; the receiver's policy takes it at its first decision point of a
    later tick by which it was delivered."""

    KIND = "policy_message"

    t: TickNo
    sender: RobotId
    to: RobotId | None = Field(default=None, description="the receiving robot; None: every other robot")
    pseq: Seq = Field(description="the sender's policy-message number (the order of messages delivered together)")
    data: bytes = Field(max_length=MAX_POLICY_DATA, description="the policy's content (msgpack of a mapping)")


class PolicyAnnouncement(Message):
    """The run's coordination policy as its sim built it (``morph/<run>/registry/policy``): every agent builds the
    same before it joins, and refuses to join with another."""

    KIND = "policy_announcement"

    policy: str = Field(min_length=1, max_length=256, description="the policy's name or package.module:Class")
    options: dict[Annotated[str, Field(max_length=64)], str | int | float | bool | None] = Field(
        default_factory=dict, max_length=64, description="the values of its parameters")


# ------------------------------------------------------------------------------------------------------------------
# The shared air (a network profile with rate-limited queues: services/faults/air.py)
# ------------------------------------------------------------------------------------------------------------------
#: a publisher in the air's messages: a robot id, or -1 for the sim
AirPublisher = Annotated[int, Field(ge=-1, lt=MAX_ROBOTS)]


def _as_long_as(msg, anchor: str, each: str, names: tuple[str, ...]):
    """``msg`` if each list of ``names`` has an entry per entry of ``anchor``, else the first that has not, named."""
    want = len(getattr(msg, anchor))
    for name in names:
        got = len(getattr(msg, name))
        if got != want:
            raise PydanticCustomError("length_mismatch", "{field} has {got} entries, expected {want} (one per {each})",
                                      {"field": name, "got": got, "want": want, "each": each})
    return msg
AirKey = Annotated[str, Field(min_length=1, max_length=128)]
MAX_AIR_ENTRIES = 4096
#: entries per air message as the services send them: well inside the transport's 32 KiB message (~40 B an entry)
AIR_CHUNK = 256


class AirPart(Message):
    """Sim → the air: what was published at ``sent_at`` by the sim (``part`` 0) or by the robots (``part`` 1), as
    the sim knows it (its own sends, the robots' acks): ``counts[i]`` publications by ``publishers[i]`` on
    ``keys[i]`` (relative to ``morph/<run>/``). The air judges the part once all of it has reached it."""

    KIND = "air_part"

    sent_at: SimTime
    part: Annotated[int, Field(ge=0, le=1)]
    more: bool = Field(default=False, description="more announcements of this part follow (a part too large for one "
                                                  "message)")
    publishers: list[AirPublisher] = Field(max_length=MAX_AIR_ENTRIES)
    keys: list[AirKey] = Field(max_length=MAX_AIR_ENTRIES)
    counts: list[Annotated[int, Field(ge=1, le=MAX_ROBOTS)]] = Field(max_length=MAX_AIR_ENTRIES)

    @model_validator(mode="after")
    def _shape(self) -> AirPart:
        return _as_long_as(self, "publishers", "publisher", ("keys", "counts"))


class AirVerdicts(Message):
    """The air → one receiver: the radio's verdict on each copy of a message sent to it, identified by (publisher,
    key, seq): delivered at ``at[i]`` (sim seconds) or, where ``at[i]`` is None, lost with ``causes[i]``."""

    KIND = "air_verdicts"

    publishers: list[AirPublisher] = Field(max_length=MAX_AIR_ENTRIES)
    keys: list[AirKey] = Field(max_length=MAX_AIR_ENTRIES)
    seqs: list[Seq] = Field(max_length=MAX_AIR_ENTRIES)
    at: list[SimTime | None] = Field(max_length=MAX_AIR_ENTRIES)
    causes: list[Annotated[str, Field(max_length=32)] | None] = Field(max_length=MAX_AIR_ENTRIES)

    @model_validator(mode="after")
    def _shape(self) -> AirVerdicts:
        return _as_long_as(self, "publishers", "publisher", ("keys", "seqs", "at", "causes"))


class AirStats(Message):
    """The air → the monitor: each access point's shared medium as judged up to sim time ``sim_time`` (the start of
    tick ``t``): bytes it took in so far, messages queued then, messages it dropped with a full queue so far."""

    KIND = "air_stats"

    t: TickNo
    sim_time: SimTime
    ap_bytes: list[Annotated[int, Field(ge=0, lt=2**63)]] = Field(max_length=MAX_AIR_ENTRIES)
    ap_queue: list[Annotated[int, Field(ge=0, lt=2**31)]] = Field(max_length=MAX_AIR_ENTRIES)
    ap_drops: list[Annotated[int, Field(ge=0, lt=2**63)]] = Field(max_length=MAX_AIR_ENTRIES)

    @model_validator(mode="after")
    def _shape(self) -> AirStats:
        return _as_long_as(self, "ap_bytes", "access point", ("ap_queue", "ap_drops"))


MESSAGE_TYPES: tuple[type[Message], ...] = (
    Tick, OnBoard, Ack, Resolve, HelpRequest, HelpReply, Commit, Refusal, AgentState, MetricSample, Event, Stop,
    FaultCommand, FaultReply, RegistrationRequest, RegistrationReply, PolicyAnnouncement, PolicyMessage, AirPart,
    AirVerdicts, AirStats,
)
MESSAGES: dict[str, type[Message]] = {cls.KIND: cls for cls in MESSAGE_TYPES}
register_kinds(*MESSAGE_TYPES)

__all__ = [
    "Ack", "AirPart", "AirStats", "AirVerdicts", "AgentState", "Commit", "Event", "FaultCommand", "FaultReply", "Heading", "HelpReply", "HelpRequest",
    "MESSAGES", "MESSAGE_TYPES", "MetricSample", "MissionType", "OnBoard", "Phase", "PolicyAnnouncement", "PolicyMessage", "Refusal",
    "RegistrationReply",
    "RegistrationRequest",
    "Resolve", "Role", "Stop", "Tick",
]
