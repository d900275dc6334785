"""What reaches the monitor, counted and checked: one sample of ``morph/<run>/**`` in, one message out.

:class:`Ingest` counts every sample by kind (messages and payload bytes), feeds the message statistics (sequence
gaps, latency) and the link meter from its header, decodes its payload and checks it against the run (sender, ids,
ticks, sizes). What it gives back is true of the run as far as the monitor can tell; what it refuses raises
``ValueError`` (the monitor counts it as rejected).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Union

from schemas import Ack, AgentState, AirStats, Commit, Event, Phase, Stop
from schemas.keys import RunKeys, check_robot_key
from schemas.tick import TickArrays, decode_tick
from services.bus.base import Sample
from services.metrics.rows import RowReducer
from services.monitor.streams import MessageStats
from services.protocol.claims import (
    EventBudget,
    OncePerTick,
    OutcomeBound,
    SenderBinding,
    check_tick,
    outcome_step_bound,
)
from services.runconfig import RunConfig

if TYPE_CHECKING:
    from services.faults.linkstats import LinkMeter

#: events that steer the run's start and the sim's window, never recorded
QUIET_EVENTS = ("ready.probe", "ready.ack", "record.progress")

#: what the monitor acts on: the sim's tick, an agent's ack (phase TICK), commit or state, an event, a stop
Checked = Union[TickArrays, Ack, Commit, AgentState, Event, Stop]


class Ingest:
    """The checked messages of the run of ``config``; ``rows`` holds the newest tick seen (the monitor's sim clock),
    ``counts`` the messages and ``sizes`` the payload bytes per kind."""

    def __init__(self, config: RunConfig, keys: RunKeys, rows: RowReducer, stats: MessageStats,
                 link_meter: LinkMeter, counts: dict[str, int], sizes: dict[str, int], cut_off: set[int]):
        self.config = config
        self.keys = keys
        self.n = config.n_agents
        self.rows = rows
        self.stats = stats
        self.link_meter = link_meter
        self.counts = counts
        self.sizes = sizes
        self._robot_copies = (keys.fleet, keys.onboard(0).rsplit("/", 1)[0] + "/")
        # what one robot may claim of itself (services/protocol/claims.py): its own header name, one ack of a tick's
        # phase, one commit and one state per tick, all of ticks the record can still use
        self._senders = SenderBinding()
        self._once = OncePerTick()
        self._outcomes = OutcomeBound(outcome_step_bound(self.n))  # before the row reducer takes a robot's counts
        self._events = EventBudget(self.n)  # what a robot may put into events.jsonl
        #: robots the sim cut off for flooding (the monitor's intake's set, filled from the sim's agent.cut_off
        #: events): the record takes nothing more of theirs
        self.cut_off = cut_off

    def take(self, sample: Sample) -> Checked | None:
        """The message ``sample`` carries, checked; None for one the monitor does not act on."""
        if sample.key.startswith(self._robot_copies):
            # the fleet broadcast and the on-board states repeat the world record (sim/tick) for the robots: the
            # one subscription to the whole run (which keeps its arrival order) brings them, nothing records them
            return None
        rel = self.keys.relative(sample.key)
        head = rel[0]
        if head == "agent":  # before anything is counted or kept per key: only the keys the protocol has
            check_robot_key(rel, self.n)
        kind = head if head != "agent" else rel[2]
        self.counts[kind] = self.counts.get(kind, 0) + 1
        self.sizes[kind] = self.sizes.get(kind, 0) + len(sample.payload)
        if head == "air":
            # the shared air's bookkeeping (the sim's announcements, the verdicts): traffic of the run, counted, but
            # nothing the record or the link streams take (and the busiest key class of a congested run); its per
            # access point counters become streams
            if rel[1:] == ["stats"]:
                if sample.sender != "air":
                    raise ValueError(f"air counters published by {sample.sender!r}, not the air")
                return sample.decode(AirStats)
            return None
        author = self.keys.sender_of(sample.key)
        if author in self.cut_off:
            raise ValueError(f"robot {author} is cut off for flooding")
        if isinstance(author, int):
            # before its sequence number is counted: a robot opens no stream under a name that is not its own
            self._senders.check(author, sample.sender)
        # Latency in the clock of the stamp: a wall stamp (wall fault time) against our wall clock; a sim-time stamp
        # (virtual time) against our sim clock, the start of the last tick we saw: sim seconds that passed while
        # the message travelled (never time.time() minus sim seconds). The stream says which (label "clock").
        wall = sample.sent_at > 1e8
        if not self.stats.observe(kind, sample.key, sample.sender, sample.seq, sample.sent_at,
                                  None if wall else max(self.rows.last_tick, 0) * self.config.dt,
                                  clock="wall" if wall else "sim"):
            raise ValueError(f"sequence number {sample.seq} of {sample.sender!r} jumps too far ahead")
        if sample.sender:
            # the link meter's latency in the same clock as the stamp (see above)
            sent = sample.sent_at
            self.link_meter.record(sample.key, sample.sender, sample.seq, sent,
                                   time.time() if wall else max(self.rows.last_tick, 0) * self.config.dt)
        if head == "sim" and rel[1:] == ["tick"]:
            if sample.sender != "sim":
                raise ValueError(f"tick published by {sample.sender!r}, not the sim")
            tick = decode_tick(sample.payload)  # validated, as arrays (schemas/tick.py)
            if tick.n != self.n:
                raise ValueError(f"tick has {tick.n} robots, this fleet {self.n}")
            return tick
        if head == "agent" and len(rel) == 3:
            if rel[2] == "ack":
                ack = sample.decode(Ack)
                self._check_sender(rel[1], ack.agent)
                self._check_tick(ack.t, "ack")
                if ack.phase != Phase.TICK or not self._once.admit(ack.agent, ack.t, ack.phase, sample.seq):
                    return None
                if ack.outcomes is not None:
                    try:
                        self._outcomes.check(ack.agent, ack.t, ack.outcomes)
                    except ValueError:
                        self._once.forget(ack.agent, ack.t, ack.phase)  # a refused lie keeps no genuine ack out
                        raise
                return ack
            if rel[2] == "commit":
                commit = self._commit(sample.decode(Commit), rel[1])
                # a picker commits once a tick; the network's copies of it count as they always did
                self._once.admit(commit.picker, commit.t, -1, sample.seq)
                return commit
            if rel[2] == "state":
                state = sample.decode(AgentState)
                self._check_sender(rel[1], state.agent)
                if len(state.w_row) != self.n:
                    raise ValueError(f"state row of {len(state.w_row)} entries, fleet of {self.n}")
                self._check_tick(state.t, "state")  # before any snapshot of that tick is begun
                if not self._once.admit(state.agent, state.t, -2, sample.seq):
                    return None
                return state
            return None
        if head == "events" and len(rel) == 2:
            if isinstance(author, int):  # before decoding: a flood of large events costs a length check each
                self._events.check_size(author, len(sample.payload))
            event = self._event(sample.decode(Event), rel[1])
            if isinstance(author, int) and event.kind not in QUIET_EVENTS:  # what goes into events.jsonl
                self._events.take(author, max(self.rows.last_tick, 0))
            return event
        if head == "ctl" and rel[1:] == ["stop"]:
            return sample.decode(Stop)
        return None

    def _check_sender(self, chunk: str, agent: int) -> None:
        if chunk != str(agent):
            raise ValueError(f"message of agent {agent} on the key of {chunk}")
        if not 0 <= agent < self.n:
            raise ValueError(f"agent id {agent} outside 0..{self.n - 1}")

    def _commit(self, commit: Commit, chunk: str) -> Commit:
        self._check_sender(chunk, commit.picker)
        if commit.picker < self.config.n_agvs or not 0 <= commit.agv < self.config.n_agvs:
            raise ValueError(f"commit of robot {commit.picker} to robot {commit.agv}: a picker commits to an AGV")
        self._check_tick(commit.t, "commit")
        return commit

    def _check_tick(self, t: int, what: str) -> None:
        """ValueError for a robot's message of a tick the record cannot use: beyond the run, ahead of the sim's
        newest tick (by more than the one tick an answer may overtake its tick), or older than a late message."""
        check_tick(t, self.rows.last_tick, self.config.steps, what)

    @staticmethod
    def _event(event: Event, chunk: str) -> Event:
        if str(event.source) != chunk:
            raise ValueError(f"event of {event.source!r} on the key of {chunk}")
        if event.kind == "run.finished" and chunk != "sim":
            raise ValueError(f"run.finished from {chunk}: only the sim ends a run")
        return event
