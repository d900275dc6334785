"""The monitor service: observes the whole run, computes per-tick metrics from messages alone, records the run.

One subscription on ``morph/<run>/**`` (one Zenoh callback thread, fan-out in Python) feeds:

* ``sim/tick``            deliveries of step t−1 (its ``delivered_by``), sim time;
* ``agent/<id>/ack``      requests sent, the agent's out-links after its update (→ links, λ₂), η;
* ``agent/<id>/commit``   commitments;
* ``agent/<id>/state``    rows of W and A (→ mean W by block, W/A snapshots), latest state per agent;
* ``events/*``            run events into ``events.jsonl``;
* ``ctl/stop``            end: last rows, snapshots and summary are written, then the service returns.

Row ``t`` of the record is final once tick t+2 (or the end of the run) has been seen: the lockstep sim cannot
publish tick t+2 before every message of tick t reached the router that also forwards them here.

Metric streams ``metrics/<name>`` are decimated to ``max_rate`` updates per second (live views need no more); the
record is complete regardless. ``get`` on ``state/**`` answers with the latest metric samples
(``state/metrics/<name>``) and agent states (``state/agent/<id>``) for late joiners.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from schemas import Ack, AgentState, Commit, Event, MetricSample, Phase, Stop
from schemas.keys import RunKeys, intersects
from schemas.tick import TickArrays, decode_tick
from services.bus.base import Bus, Query, Sample
from services.metrics import catalogue, measures as M
from services.monitor.recorder import Recorder, read_metrics
from services.monitor.streams import MessageStats
from services.protocol.dispatch import view_age_stats
from services.rejects import Rejects
from services.runconfig import RunConfig
from services.tickorder import TickOrder

log = logging.getLogger("morph_sim.monitor")

ROW_GRACE_TICKS = 8
STOP_GRACE = 3.0  # seconds the monitor waits for the sim's end of run after someone else's stop
QUIET_EVENTS = ("ready.probe", "ready.ack", "record.progress")
#: every this many rows the monitor says how far its record is (event ``record.progress``, t = rows written): the
#: lockstep sim keeps at most its window of ticks ahead of it (services/sim/service.py, MONITOR_WINDOW)
PROGRESS_EVERY = 50
HEARTBEAT = 0.5  # seconds: no stream goes longer than about this plus its decimation without a sample
PUBLISH_BURST, PUBLISH_PAUSE = 256, 0.005  # metric samples published back to back at most, then a pause (s)


def summary_of_rows(rows: list[dict[str, str]]) -> dict:
    """The summary's totals computed from the record's rows (strings, as read back from metrics.csv)."""
    links = [int(r["links"] or 0) for r in rows]
    return {"steps": len(rows), "deliveries_total": int(rows[-1]["deliveries_total"] or 0) if rows else 0,
            "mean_links": sum(links) / max(1, len(links)), "final_links": links[-1] if links else None,
            "rows_missing": (int(rows[-1]["t"]) + 1 - len(rows)) if rows else 0}


NET_STREAMS = tuple(m.name.split("/", 1)[1] for m in catalogue.CATALOGUE if m.source == "network")
# what the dispatch protocol sends, by the monitor's message kind (the sim's Ticks and Resolves are kind "sim")
PROTOCOL_KINDS = ("sim", "ack", "request", "reply", "commit")  # what the monitor's own network model can see


def _by_id(values: dict[int, float]) -> list[float]:
    """Per-agent values in agent-id order, whatever order their acks came in."""
    return [values[a] for a in sorted(values)]


@dataclass
class Row:
    t: int
    sim_time: float = 0.0
    deliveries: int | None = None
    requests: int = 0
    commits: int = 0
    ackers: set[int] = field(default_factory=set)
    links: dict[int, list[int]] = field(default_factory=dict)
    # per agent, summed in id order: a float sum in arrival order would differ between two runs of the same seed
    etas: dict[int, float] = field(default_factory=dict)
    # dispatch outcomes by the end of step t: each robot's counts (its ack of t+1), the sim's (its tick t+1)
    outcomes: dict[int, dict[str, int]] = field(default_factory=dict)
    sim_outcomes: dict[str, int] | None = None
    view_ages: dict[int, float] = field(default_factory=dict)


@dataclass
class MonitorResult:
    rows: list[dict] = field(default_factory=list)
    snapshots: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    deliveries_total: int = 0
    rejected: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)  # payload bytes per kind, as messages
    finished: dict | None = None
    failure: str | None = None  # why the record could not be written, if it could not

    def communication(self, steps: int, n_agents: int) -> dict:
        """What the dispatch protocol sent (Ticks and Resolves of the sim, acks, requests, replies, commits — not the
        skips that synchronise virtual time, nor telemetry): totals, per delivery, per agent per tick."""
        msgs = sum(self.messages.get(k, 0) for k in PROTOCOL_KINDS)
        size = sum(self.bytes.get(k, 0) for k in PROTOCOL_KINDS)
        per = max(1, self.deliveries_total)
        agent_ticks = max(1, steps * n_agents)
        return {"kinds": list(PROTOCOL_KINDS), "messages": msgs, "bytes": size,
                "messages_per_delivery": msgs / per if self.deliveries_total else None,
                "bytes_per_delivery": size / per if self.deliveries_total else None,
                "messages_per_agent_tick": msgs / agent_ticks, "bytes_per_agent_tick": size / agent_ticks}


class MonitorService:
    """Monitor of the run of ``config`` over ``bus``; ``await run()`` until the run stops."""

    def __init__(self, config: RunConfig, bus: Bus, *, record: bool = True, max_rate: float = 10.0,
                 keep_rows: bool = True, tap: Callable[[Sample], None] | None = None):
        """``tap``: sees every sample the monitor receives, in arrival order, before it is handled (a bus
        recording of the whole run: the sim starts no tick before the monitor is there)."""
        self.config = config
        self.tap = tap
        self._rejects = Rejects(log, "monitor")
        self.bus = bus
        bus.reject_hook = self._reject  # oversized messages refused on arrival count here
        self.keys = RunKeys(config.run_id)
        self._robot_copies = (self.keys.fleet, self.keys.onboard(0).rsplit("/", 1)[0] + "/")
        self.n = config.n_agents
        self.is_agv = np.arange(self.n) < config.n_agvs
        self.recorder = Recorder(config) if record else None
        self.max_rate = max_rate
        self.keep_rows = keep_rows
        self.result = MonitorResult()
        self._rows: dict[int, Row] = {}
        self._next_row = 0
        self._last_tick = -1
        self._ticks = TickOrder(config.steps)  # which ticks the record takes (services/tickorder.py)
        self._total = 0
        self._states: dict[int, dict[int, AgentState]] = {}  # tick -> agent -> state
        self.latest_state: dict[int, AgentState] = {}
        self.latest_metric: dict[str, MetricSample] = {}
        self._block: dict[int, M.BlockMeans] = {}
        self._last_publish = 0.0
        self._stop = asyncio.Event()
        self._pending_publish: list[MetricSample] = []
        self._publishing = False  # a publication of metric samples is under way
        self._last_values: dict = {}
        self._links_sum = 0
        self._graph: tuple[dict[int, list[int]] | None, int, float] = (None, 0, 0.0)  # (links, count, λ₂) of a row
        self._fresh: dict[str, tuple[int, float, float]] = {}  # stream -> newest (t, sim time, value) unpublished
        self._unbuilt = False  # rows queued since the metric samples were last built
        self._done = False
        self._stop_timer: asyncio.TimerHandle | None = None
        self._link_shift = 1 if config.policy == "morph" else 0
        self.stats = MessageStats(self.n, config.dt)  # message streams (counts, drops, latency, dispatch)
        # per key class sent / delivered / dropped / duplicated / late and latency, from the samples'
        # own headers, published as link/* metrics every k (state_every) ticks
        from services.faults.linkstats import LinkMeter

        self.link_meter = LinkMeter(f"morph/{config.run_id}", bus.identity)
        from services.monitor.faultwindows import FaultWindows

        self.fault_windows = FaultWindows()  # faults in force, from the events (Prometheus morph_faults_active)
        self.latest_links: list[MetricSample] = []
        # the run's Wi-Fi as the robots drive through it (hand-overs, robots in an outage): the same model, seed and
        # trajectories as every fault layer of the run, observed here, never applied (the monitor is the instrument)
        self.network = None
        if config.network is not None:
            from services.faults.network import NetworkModel, load_profile
            from services.world.layout import LayoutConfig, layout_for

            self.network = NetworkModel(load_profile(config.network), layout_for(LayoutConfig.named(config.scale)),
                                        seed=config.seed)
        self._links_due = False
        from services.protocol.dispatch import OutcomeTally

        self.outcomes = OutcomeTally()  # the robots' dispatch outcome counts, taken in row order
        self._sim_outcomes: dict[str, int] = {}

    def _reject(self, what: str, why: object) -> None:
        self._rejects.count(what, why)
        self.result.rejected = self._rejects.total
        self.stats.rejected = self._rejects.total

    # -- lifecycle -----------------------------------------------------------------------------------------------------
    async def run(self) -> MonitorResult:
        k = self.keys
        # Not inline: the monitor takes in the whole run's traffic, and it must never hold up the transport's receive
        # thread. Handled inline, a slow moment (a W snapshot at tick 50 of a 64-agent run) let the sim's router block
        # writing to us while our own publish from that thread blocked writing to the router: the run deadlocked
        # (seen 3 times in 10 loaded 64-agent runs). On the loop, samples arrive in batches (one wake-up per burst).
        await self.bus.subscribe(k.everything, self._on_sample)
        await self.bus.declare_queryable(k.latest_all, self._on_query)
        token = await self.bus.declare_token(k.alive("monitor"))
        heartbeat = asyncio.get_running_loop().create_task(self._heartbeat())
        try:
            await self._stop.wait()
        finally:
            heartbeat.cancel()
        if self.result.failure is None:
            try:
                self._finish()
            except OSError as exc:
                self._record_failed(exc)
        await self._publish_pending(force=True)
        await token.close()
        return self.result

    def stop(self, grace: float = 0.0) -> None:
        """Finish the record now, or after ``grace`` seconds unless the sim's end of run comes first."""
        if grace <= 0:
            self._stop.set()
        elif self._stop_timer is None:
            self._stop_timer = asyncio.get_running_loop().call_later(grace, self._stop.set)

    # -- dispatch --------------------------------------------------------------------------------------------------------
    def _record_failed(self, exc: OSError) -> None:
        """The record cannot be written (disk full, file too large, permissions): nothing this monitor records from
        now on would be true, so it stops and says why (the supervisor stops the run)."""
        if self.result.failure is None:
            where = getattr(exc, "filename", None) or (self.recorder.dir if self.recorder is not None else "?")
            self.result.failure = f"cannot write the run record {where}: {exc.strerror or exc}"
            log.error("%s", self.result.failure)
        self._done = True
        self._stop.set()

    def _on_sample(self, sample: Sample) -> None:
        """On the loop (the subscription is not inline; replay feeds samples here too)."""
        if self._done:
            return
        try:
            if self.tap is not None:
                self.tap(sample)
            self._handle(sample)
        except OSError as exc:
            self._record_failed(exc)

    def _handle(self, sample: Sample) -> None:
        if sample.key.startswith(self._robot_copies):
            # the fleet broadcast and the on-board states repeat the world record (sim/tick) for the robots: the
            # one subscription to the whole run (which keeps its arrival order) brings them, nothing records them
            return
        try:
            rel = self.keys.relative(sample.key)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        head = rel[0]
        kind = head if head != "agent" or len(rel) < 3 else rel[2]
        self.result.messages[kind] = self.result.messages.get(kind, 0) + 1
        self.result.bytes[kind] = self.result.bytes.get(kind, 0) + len(sample.payload)
        # Latency in the clock of the stamp: a wall stamp (wall fault time) against our wall clock; a sim-time stamp
        # (virtual time) against our sim clock, the start of the last tick we saw: sim seconds that passed while
        # the message travelled (never time.time() minus sim seconds). The stream says which (label "clock").
        wall = sample.sent_at > 1e8
        if not self.stats.observe(kind, sample.key, sample.sender, sample.seq, sample.sent_at,
                                  None if wall else max(self._last_tick, 0) * self.config.dt,
                                  clock="wall" if wall else "sim"):
            self._reject(sample.key, f"sequence number {sample.seq} of {sample.sender!r} jumps too far ahead")
            return
        if sample.sender:
            # the link meter's latency in the same clock as the stamp (see above)
            sent = sample.sent_at
            self.link_meter.record(sample.key, sample.sender, sample.seq, sent,
                                   time.time() if wall else max(self._last_tick, 0) * self.config.dt)
        try:
            if head == "sim" and rel[1:] == ["tick"]:
                if sample.sender != "sim":
                    raise ValueError(f"tick published by {sample.sender!r}, not the sim")
                self._on_tick(decode_tick(sample.payload))  # validated, as arrays (schemas/tick.py)
            elif head == "agent" and len(rel) == 3:
                if rel[2] == "ack":
                    self._on_ack(sample.decode(Ack), rel[1])
                elif rel[2] == "commit":
                    self._on_commit(sample.decode(Commit), rel[1])
                elif rel[2] == "state":
                    self._on_state(sample.decode(AgentState), rel[1])
            elif head == "events" and len(rel) == 2:
                self._on_event(sample.decode(Event), rel[1])
            elif head == "ctl" and rel[1:] == ["stop"]:
                sample.decode(Stop)
                if sample.sender == "sim":
                    self._stop.set()
                elif self._stop_timer is None:
                    # an operator's stop: the sim ends the run and says so; stop anyway if it cannot
                    self._stop_timer = asyncio.get_running_loop().call_later(STOP_GRACE, self._stop.set)
        except ValueError as exc:  # DecodeError and bad ids
            self._reject(sample.key, exc)

    def _row(self, t: int) -> Row | None:
        if t < self._next_row:
            return None  # already final (a late duplicate)
        row = self._rows.get(t)
        if row is None:
            row = self._rows[t] = Row(t)
        return row

    def _on_tick(self, tick: TickArrays) -> None:
        if tick.n != self.n:
            raise ValueError(f"tick has {tick.n} robots, this fleet {self.n}")
        if not self._ticks.admit(tick.t):
            return
        if self._last_tick < 0 and self.recorder is not None and self.recorder.resume_from is not None:
            self._resume(tick)
            if self._done:
                return
        self._last_tick = tick.t
        if tick.t > 0:
            prev = self._row(tick.t - 1)
            if prev is not None:
                prev.deliveries = tick.deliveries
                prev.sim_outcomes = tick.outcomes
        if tick.t < self.config.steps:
            row = self._row(tick.t)
            if row is not None:
                row.sim_time = tick.sim_time
        if self.recorder is not None:
            self.recorder.positions(tick.t, *(tick.row(name).tolist() for name in ("x", "y", "heading", "carrying")))
        if self.network is not None:
            self.network.observe_tick(tick.t, self.config.dt, list(zip(tick.row("x").tolist(), tick.row("y").tolist())))
        # Row t-2 is due once tick t arrives, but its acks (and the link reports of t-1) travel on other paths than
        # the sim's ticks and may reach the monitor after tick t: a row that still misses an agent's report waits
        # up to ROW_GRACE_TICKS more ticks (an absent agent's row is then written without it).
        self._finalize(upto=tick.t - 2, grace=ROW_GRACE_TICKS)

    def _resume(self, tick: TickArrays) -> None:
        # A restarted monitor appends to its predecessor's record: rows from the first tick it sees (the first it can
        # see whole), the cumulative count continued from the sim's own (the gap's deliveries included), and the
        # rows in between declared lost (a gap event).
        first_tick = tick.t
        last_row, total = self.recorder.resume_from
        if first_tick <= last_row:
            # the run's ticks are behind the record's rows: not this run's record but another run's with the same id
            self.result.failure = (f"run_id: {self.recorder.dir} holds rows up to tick {last_row} and this run is at "
                                   f"tick {first_tick}: another run was recorded under this id; choose another")
            log.error("%s", self.result.failure)
            self._done = True
            self._stop.set()
            return
        self._next_row = max(first_tick, last_row + 1)
        self._total = tick.deliveries_total if tick.deliveries_total is not None and \
            self._next_row == first_tick else total
        kind = "monitor.gap" if self._next_row > last_row + 1 else "monitor.resumed"
        self.recorder.event(Event(kind=kind, source="monitor", t=first_tick, details={
            "first": last_row + 1, "last": self._next_row - 1, "reason": "monitor restarted"}).model_dump(mode="json"))
        self.recorder.flush()

    def _check_sender(self, chunk: str, agent: int) -> None:
        if chunk != str(agent):
            raise ValueError(f"message of agent {agent} on the key of {chunk}")
        if not 0 <= agent < self.n:
            raise ValueError(f"agent id {agent} outside 0..{self.n - 1}")

    def _on_ack(self, ack: Ack, chunk: str) -> None:
        self._check_sender(chunk, ack.agent)
        if ack.phase != Phase.TICK:
            return
        if ack.t < self.config.steps:
            row = self._row(ack.t)
            if row is not None and ack.agent not in row.ackers:
                row.ackers.add(ack.agent)
                row.requests += len(ack.requests_sent)
                if ack.view_age is not None:
                    row.view_ages[ack.agent] = ack.view_age
                if ack.requests_sent:
                    self.stats.requested(ack.t, ack.agent)
        if ack.outcomes is not None and 0 < ack.t <= self.config.steps:
            # counts as they stood at the start of tick t: the end of step t−1
            row = self._row(ack.t - 1)
            if row is not None:
                row.outcomes.setdefault(ack.agent, ack.outcomes)
        self._links_from(ack.t, ack.agent, ack.links or [], ack.eta)

    def _links_from(self, t: int, agent: int, links: list[int], eta: float | None) -> None:
        # Links and η belong to the step whose update produced them: a plastic policy's report at tick t carries the
        # state after the update for step t−1 (the reference logs it as step t−1); a memoryless one's is of tick t.
        step = t - self._link_shift
        if not 0 <= step < self.config.steps:
            return
        row = self._row(step)
        if row is None or agent in row.links:
            return
        row.links[agent] = [j for j in links if 0 <= j < self.n]
        if eta is not None and self._link_shift:
            row.etas[agent] = float(eta)

    def _on_commit(self, commit: Commit, chunk: str) -> None:
        self._check_sender(chunk, commit.picker)
        if commit.picker < self.config.n_agvs or not 0 <= commit.agv < self.config.n_agvs:
            raise ValueError(f"commit of robot {commit.picker} to robot {commit.agv}: a picker commits to an AGV")
        if not 0 <= commit.t <= self._last_tick + 1:
            raise ValueError(f"commit of tick {commit.t}, the run is at tick {self._last_tick}")
        row = self._row(commit.t)
        if row is not None:
            row.commits += 1
        self.stats.committed(commit.t, commit.agv)

    def _on_state(self, state: AgentState, chunk: str) -> None:
        self._check_sender(chunk, state.agent)
        if len(state.w_row) != self.n:
            raise ValueError(f"state row of {len(state.w_row)} entries, fleet of {self.n}")
        prev = self.latest_state.get(state.agent)
        if prev is None or state.t >= prev.t:
            self.latest_state[state.agent] = state
        if state.t % self.config.state_every != 0 and state.t < self.config.steps:
            return  # a per-tick state (links only): not a W sample
        if state.t < self._next_row - ROW_GRACE_TICKS:
            return  # its sample was written already (complete, or as it was when its row became final)
        at = self._states.setdefault(state.t, {})
        at[state.agent] = state
        if len(at) == self.n:
            self._complete_states(state.t)

    def _matrices(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        W = np.full((self.n, self.n), np.nan)
        A = np.zeros((self.n, self.n), dtype=bool)
        for agent, st in self._states.get(t, {}).items():
            W[agent] = st.w_row
            A[agent] = st.a_row
        return W, A

    def _complete_states(self, t: int) -> None:
        W, A = self._matrices(t)
        if not np.isnan(W).any():
            self._block[t] = M.mean_w_by_block(W, self.is_agv)
        if t % self.config.snapshot_every == 0 or t >= self.config.steps:
            if self.keep_rows:  # in memory only for in-process callers; the record has them on disk
                self.result.snapshots[t] = (W, A)
            if self.recorder is not None:
                self.recorder.snapshot(t, W, A)
        del self._states[t]

    def _on_event(self, event: Event, chunk: str | None = None) -> None:
        """``chunk``: the ``events/<chunk>`` key it came on (None: handed over in-process, e.g. by a test)."""
        if chunk is not None and str(event.source) != chunk:
            raise ValueError(f"event of {event.source!r} on the key of {chunk}")
        if event.kind == "run.finished" and chunk not in (None, "sim"):
            raise ValueError(f"run.finished from {chunk}: only the sim ends a run")
        if event.kind in QUIET_EVENTS:
            if event.kind == "ready.probe":
                # answered at once, as every participant does (the sim waits for the answers)
                self.bus.put(self.keys.event("monitor"), Event(
                    kind="ready.ack", source="monitor", details={"round": event.details.get("round", 0)}))
            return
        self.fault_windows.add({"kind": event.kind, "t": event.t, "details": event.details})
        if event.kind == "run.finished":
            self.result.finished = {**(self.result.finished or {}), **event.details}
            self._stop.set()
        if self.recorder is not None:
            self.recorder.event(event.model_dump(mode="json"))

    # -- rows ------------------------------------------------------------------------------------------------------------
    def _row_complete(self, row: Row) -> bool:
        return len(row.ackers) >= self.n and len(row.links) >= self.n and len(row.outcomes) >= self.n

    def _finalize(self, upto: int, grace: int = 0) -> None:
        while self._next_row <= upto:
            t = self._next_row
            pending = self._rows.get(t)
            if t > upto - grace and (pending is None or not self._row_complete(pending)):
                break
            row = self._rows.pop(t, None) or Row(t)
            self._emit(row)
            self._next_row += 1
        # A state sample that never completes (an agent was absent at that tick) is written as it is once its row is
        # final, so that the monitor's memory does not grow with the length of a run that lost an agent.
        while self._states and min(self._states) < self._next_row - ROW_GRACE_TICKS:
            self._complete_states(min(self._states))

    def _emit(self, row: Row) -> None:
        A = np.zeros((self.n, self.n), dtype=bool)
        for agent, links in row.links.items():
            A[agent, links] = True
        if row.links != self._graph[0]:
            # the link graph changes only at structural steps: its count and λ₂ (an eigen-solve) are kept until then
            self._graph = (row.links, M.undirected_link_count(A), M.algebraic_connectivity(A))
        _, link_count, lambda2 = self._graph
        delivered = row.deliveries or 0
        self._total += delivered
        block = self._block.pop(row.t, None)
        values = {
            "t": row.t, "sim_time": row.sim_time, "deliveries": row.deliveries, "deliveries_total": self._total,
            "requests": row.requests, "commits": row.commits, "links": link_count,
            "lambda2": lambda2, "eta": float(np.mean(_by_id(row.etas))) if row.etas else None,
            "acks": len(row.ackers), **catalogue.w_block_values(block),
            **self._outcome_values(row),
        }
        values["view_age_mean"], values["view_age_max"] = view_age_stats(_by_id(row.view_ages))
        self.result.deliveries_total = self._total
        self._last_values = values
        self._links_sum += values["links"]
        if self.keep_rows:
            self.result.rows.append(values)
        if self.recorder is not None:
            self.recorder.row(values, links=A)
        self._queue_metrics(values)
        if (row.t + 1) % PROGRESS_EVERY == 0:
            self._progress(row.t + 1)

    def _outcome_values(self, row: Row) -> dict[str, int]:
        """The dispatch outcome columns of ``row``: a robot or sim whose report of this row is missing (absent, or
        joined late) counts with its latest report."""
        for agent, counts in row.outcomes.items():
            self.outcomes.report(agent, row.t, counts)
        if row.sim_outcomes is not None:
            self._sim_outcomes = row.sim_outcomes
        return catalogue.outcome_values(self.outcomes.total(self._sim_outcomes))

    def _progress(self, rows: int) -> None:
        """Tell the sim that rows ``< rows`` are written (never dropped: the sim may be waiting for it)."""
        self.bus.put(self.keys.event("monitor"), Event(kind="record.progress", source="monitor", t=rows))

    def _queue_metrics(self, values: dict) -> None:
        """Note the row's stream values; build and publish MetricSamples only when a publication is due.

        Streams are decimated to ``max_rate`` updates per second, so building ~15 samples (and the latency quantiles)
        for every row would be work nobody reads: per stream the newest value since the last publication is kept
        (a sparse stream, e.g. the W block means every k ticks, is not lost) and turned into a sample when due.
        ``latest_metric`` (late joiners, Prometheus) is refreshed then, and at the end of the run.
        """
        t = values["t"]
        sim_time = values["sim_time"] or t * self.config.dt
        for name in catalogue.ROW:
            v = values.get(name)
            if v is not None and not (isinstance(v, float) and not math.isfinite(v)):
                self._fresh[name] = (t, sim_time, float(v))
        if self.network is not None:
            net = self.network.counters(sim_time)
            for name in NET_STREAMS:
                self._fresh[f"net/{name}"] = (t, sim_time, net[name])
        self.stats.row(values)
        self._unbuilt = True
        if t % self.config.state_every == 0:
            # one sample per (counter, key class): kept apart from latest_metric (one value per name), and carried
            # to the next decimated publish so a k-tick snapshot is never skipped
            self.latest_links = self.link_meter.metrics(t, sim_time, self.bus.identity)
            self._links_due = True
        now = time.monotonic()
        due = self.max_rate <= 0 or now - self._last_publish >= 1.0 / self.max_rate  # 0: every row
        if due:
            self._build_samples(values)
            self._last_publish = now
            self.bus.spawn(self._publish_pending(), "metrics")

    def _build_samples(self, values: dict) -> None:
        """The pending MetricSamples of the rows noted since the last build; ``values`` is the newest row."""
        self._unbuilt = False
        samples = [catalogue.sample(name, t, sim_time, value=v) for name, (t, sim_time, v) in self._fresh.items()]
        self._fresh = {}
        samples += self.stats.samples(values)
        for s in samples:
            self.latest_metric[s.name] = s
        if self._links_due:
            samples += self.latest_links
            self._links_due = False
        if self.max_rate <= 0:  # every row's samples, in order
            self._pending_publish += samples
            return
        # per stream the newest sample since the last publication: a sparse stream (dispatch_delay) is not lost
        pending = {s.name: s for s in self._pending_publish}
        pending.update((s.name, s) for s in samples)
        self._pending_publish = list(pending.values())

    async def _heartbeat(self) -> None:
        """Every stream gets a sample at least once a second, even while the run makes no new row (a loaded machine,
        a phase waiting for a late agent): the newest values, or the latest ones again. A live view never goes
        silent while the run is alive."""
        while True:
            await asyncio.sleep(HEARTBEAT)
            now = time.monotonic()
            if self._done or now - self._last_publish < HEARTBEAT:
                continue
            if self._unbuilt:
                self._build_samples(self._last_values)  # rows noted since the last publication
            elif not self._pending_publish:  # (else a publication is on its way)
                self._pending_publish = list(self.latest_metric.values()) + list(self.latest_links)
            self._last_publish = now
            await self._publish_pending()

    async def _publish_pending(self, force: bool = False) -> None:
        """Publish the pending samples. One publication at a time, which takes whatever is queued meanwhile too, so
        each stream's samples go out in tick order; ``force`` (the end of the run) waits for the one under way."""
        while self._publishing:
            if not force:
                return  # the publication under way takes these too
            await asyncio.sleep(0.01)
        self._publishing = True
        try:
            while self._pending_publish:
                samples, self._pending_publish = self._pending_publish, []
                for i, s in enumerate(samples, 1):
                    await self.bus.publish(self.keys.metric(s.name), s, droppable=True)
                    if i % PUBLISH_BURST == 0 and i < len(samples):
                        # a backlog (every row of a monitor that fell behind, --max-rate 0) goes out in bursts the
                        # transport can queue: droppable samples beyond its queue would be lost for every subscriber
                        await asyncio.sleep(PUBLISH_PAUSE)
        finally:
            self._publishing = False

    def _finish(self) -> None:
        self._done = True
        if self._stop_timer is not None:
            self._stop_timer.cancel()
        # every row up to the last completed step; the final tick (t == steps) only reported that step
        last = min(self._last_tick - 1, self.config.steps - 1)
        self._finalize(upto=last)
        for t in sorted(self._states):
            self._complete_states(t)
        if self._unbuilt:  # the last rows' samples: latest_metric ends on the run's final values
            self._build_samples(self._last_values)
        summary = {
            "run_id": self.config.run_id, "steps": self._next_row, "deliveries_total": self._total,
            "rejected": self.result.rejected, "mean_links": self._links_sum / max(1, self._next_row),
            "sequence_gaps": self.stats.gaps,  # messages lost on the way to the monitor (per sender and key)
            "messages": dict(sorted(self.result.messages.items())),
            "bytes": dict(sorted(self.result.bytes.items())),
            "communication": self.result.communication(self._next_row, self.n),
            "finished": self.result.finished,
            "final_links": self._last_values.get("links"),
        }
        if self.recorder is not None:
            self.recorder.flush()
            if self.recorder.resume_from is not None:
                # a restarted monitor saw only part of the run: the totals are those of the record's rows
                summary.update(summary_of_rows(read_metrics(self.recorder.dir)))
            self.recorder.summary(summary)
            self.recorder.close()

    # -- late joiners ----------------------------------------------------------------------------------------------------
    def _on_query(self, query: Query) -> None:
        key = self.keys.latest("config")
        if intersects(key, query.key_expr):  # the run's configuration, for a recorder that joins (replay needs it)
            query.reply(key, Event(kind="run.config", source="monitor", t=max(self._last_tick, 0),
                                   details={"config": self.config.model_dump(mode="json")}))
        metrics, states = list(self.latest_metric.items()), sorted(self.latest_state.items())
        for name, sample in metrics:
            key = self.keys.latest("metrics", name)
            if intersects(key, query.key_expr):
                query.reply(key, sample)
        for agent, state in states:
            key = self.keys.latest("agent", str(agent))
            if intersects(key, query.key_expr):
                query.reply(key, state)
