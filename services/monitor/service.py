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

This module is the service's shell: its life cycle, and what it does with each checked message. The samples are
counted and checked in :mod:`.ingest`, the rows are reduced by the pure :mod:`services.metrics.rows`, the metric
streams go out through :mod:`.streams`, the late joiners' answers come from :mod:`.latest`, and the record is
written by :mod:`.recorder`.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from schemas import Ack, AgentState, AirStats, Commit, Event, Stop
from schemas.keys import RunKeys
from schemas.tick import TickArrays
from services.bus.base import Bus, Query, Sample
from services.intake import Intake
from services.metrics.rows import ROW_GRACE_TICKS, ClosedRow, RowReducer, Snapshot, summary_of_rows
from services.monitor.ingest import QUIET_EVENTS, Ingest
from services.monitor.latest import LatestState
from services.monitor.recorder import Recorder, read_metrics
from services.monitor.streams import MessageStats, StreamPublisher
from services.policies.interface import Fleet
from services.protocol.claims import FloodWatch
from services.protocol.tickorder import TickOrder
from services.runconfig import RunConfig

__all__ = ["MonitorResult", "MonitorService", "ROW_GRACE_TICKS", "summary_of_rows"]

log = logging.getLogger("morph_sim.monitor")

STOP_GRACE = 3.0  # seconds the monitor waits for the sim's end of run after someone else's stop
# seconds the monitor waits, after the sim's end of run, for final acks still on their way (an agent that died at the
# very end sends none)
FINAL_ACKS_GRACE = 2.0
#: every this many rows the monitor says how far its record is (event ``record.progress``, t = rows written): the
#: lockstep sim keeps at most its window of ticks ahead of it (services/sim/service.py, MONITOR_WINDOW)
PROGRESS_EVERY = 50
END_FLUSH_TIMEOUT = 5.0  # seconds the monitor waits for its last samples to be past the endpoint
# what the dispatch protocol sends, by the monitor's message kind (the sim's Ticks and Resolves are kind "sim")
PROTOCOL_KINDS = ("sim", "ack", "request", "reply", "commit", "policy")  # what the monitor's own network model can see


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
        self.bus = bus
        self.keys = RunKeys(config.run_id)
        # counts each robot's refused messages for the refused_by_robot stream (the sim reports and cuts off floods)
        self.intake = Intake(bus, self.keys, log, "monitor", on_refused=self._count_refused,
                             flood=FloodWatch(config.n_agents))
        self.n = config.n_agents
        self.recorder = Recorder(config) if record else None
        self.keep_rows = keep_rows
        self.result = MonitorResult()
        self.rows = RowReducer(self.n, config.n_agvs, config.steps, state_every=config.state_every,
                               snapshot_every=config.snapshot_every, plastic=not config.make_policy().memoryless(
                                   Fleet(config.n_agvs, config.n_pickers, config.scale)))
        self._ticks = TickOrder(config.steps)  # which ticks the record takes (services/protocol/tickorder.py)
        self._stop = asyncio.Event()
        self._done = False
        self._stop_timer: asyncio.TimerHandle | None = None
        self._final_acks: set[int] | None = None  # after the sim's end of run: the final acks still awaited
        self.stats = MessageStats(self.n, config.dt)  # message streams (counts, drops, latency, dispatch)
        self.stats.refused_by_robot = self.intake.flood.refused
        # per key class sent / delivered / dropped / duplicated / late and latency, from the samples'
        # own headers, published as link/* metrics every k (state_every) ticks
        from services.faults.linkstats import LinkMeter

        self.link_meter = LinkMeter(f"morph/{config.run_id}", bus.identity)
        from services.monitor.faultwindows import FaultWindows

        self.fault_windows = FaultWindows()  # faults in force, from the events (Prometheus morph_faults_active)
        # the run's Wi-Fi as the robots drive through it (hand-overs, robots in an outage): the same model, seed and
        # trajectories as every fault layer of the run, observed here, never applied (the monitor is the instrument)
        self.network = None
        if config.network is not None:
            from services.faults.network import NetworkModel, load_profile
            from services.world.layout import LayoutConfig, layout_for

            self.network = NetworkModel(load_profile(config.network), layout_for(LayoutConfig.named(config.scale)),
                                        seed=config.seed)
        self.ingest = Ingest(config, self.keys, self.rows, self.stats, self.link_meter, self.result.messages,
                             self.result.bytes, self.intake.cut_off)
        self.streams = StreamPublisher(bus, self.keys, self.stats, self.link_meter, self.network, dt=config.dt,
                                       state_every=config.state_every, max_rate=max_rate)
        self.latest = LatestState(config, self.keys, self.streams.latest_metric)

    @property
    def latest_metric(self) -> dict:
        """The latest sample of every metric stream (late joiners, Prometheus)."""
        return self.streams.latest_metric

    @property
    def latest_air(self) -> list:
        """The shared air's newest per access point samples (label ``ap``), under a rate-limited profile."""
        return self.streams.latest_air

    @property
    def latest_links(self) -> list:
        """The latest link statistics, one sample per (counter, key class)."""
        return self.streams.latest_links

    @property
    def latest_state(self) -> dict[int, AgentState]:
        """Each agent's newest state."""
        return self.latest.agents

    @property
    def last_tick(self) -> int:
        """The newest tick the monitor took (-1 before the first): its sim clock."""
        return self.rows.last_tick

    def _count_refused(self, total: int) -> None:
        self.result.rejected = total
        self.stats.rejected = total

    # -- lifecycle -----------------------------------------------------------------------------------------------------
    async def run(self) -> MonitorResult:
        k = self.keys
        # Not inline: the monitor takes in the whole run's traffic, and it must never hold up the transport's receive
        # thread. Handled inline, a slow moment (a W snapshot at tick 50 of a 64-agent run) let the sim's router block
        # writing to us while our own publish from that thread blocked writing to the router: the run deadlocked
        # (seen 3 times in 10 loaded 64-agent runs). On the loop, samples arrive in batches (one wake-up per burst).
        await self.bus.subscribe(k.everything, self.on_sample)
        await self.bus.declare_queryable(k.latest_all, self._on_query)
        token = await self.bus.declare_token(k.alive("monitor"))
        heartbeat = asyncio.get_running_loop().create_task(self.streams.heartbeat(lambda: self._done))
        try:
            await self._stop.wait()
        finally:
            heartbeat.cancel()
        if self.result.failure is None:
            try:
                self.finish()
            except OSError as exc:
                self._record_failed(exc)
        await self.streams.publish_pending(force=True, lossless=True)  # the run is over: see there
        if self.streams.published_lossless and self.bus.flushes_late:
            # Closing a Zenoh session discards what it has not sent yet, and leaving (the token) can overtake the
            # samples still queued. A query the sim answers comes back only once the endpoint has taken everything
            # this session sent before it (one link, in order), the samples among them: then leaving loses nothing.
            await self.bus.get(k.registry_policy, timeout=END_FLUSH_TIMEOUT)
        await token.close()
        return self.result

    def _end_of_run(self) -> None:
        """The sim ended the run (its ``run.finished``, then its stop): finish the record now, or once the final acks
        still on their way have come. The sim ends the run when it has every final ack, but its messages can reach us
        before acks it routed on (seen: a last row short of one robot's links and η, in one suite run of five); a
        robot that died at the very end sends none, hence the bound."""
        if self._final_acks is None:
            self._final_acks = self.rows.final_acks_missing()
        if self._final_acks:
            self.stop(FINAL_ACKS_GRACE)
        else:
            self._stop.set()

    def stop(self, grace: float = 0.0) -> None:
        """Finish the record now, or after ``grace`` seconds unless the sim's end of run comes first."""
        if grace <= 0:
            self._stop.set()
        elif self._stop_timer is None:
            self._stop_timer = asyncio.get_running_loop().call_later(grace, self._stop.set)

    @property
    def done(self) -> bool:
        """The record is finished (or cannot be written): samples are no longer taken."""
        return self._done

    def _record_failed(self, exc: OSError) -> None:
        """The record cannot be written (disk full, file too large, permissions): nothing this monitor records from
        now on would be true, so it stops and says why (the supervisor stops the run)."""
        if self.result.failure is None:
            where = getattr(exc, "filename", None) or (self.recorder.dir if self.recorder is not None else "?")
            self.result.failure = f"cannot write the run record {where}: {exc.strerror or exc}"
            log.error("%s", self.result.failure)
        self._done = True
        self._stop.set()

    # -- messages ------------------------------------------------------------------------------------------------------
    def on_sample(self, sample: Sample) -> None:
        """One sample of the run, on the loop (the subscription is not inline; replay feeds samples here too)."""
        if self._done:
            return
        try:
            if self.tap is not None:
                self.tap(sample)
            self._handle(sample)
        except OSError as exc:
            self._record_failed(exc)

    def _handle(self, sample: Sample) -> None:
        try:
            message = self.ingest.take(sample)
            if message is None:
                return
            kind = type(message)
            if kind is TickArrays:
                self._on_tick(message)
            elif kind is Ack:
                if self.rows.ack(message) and message.requests_sent:
                    self.stats.requested(message.t, message.agent)
                if self._final_acks and message.agent in self._final_acks:
                    self._final_acks.discard(message.agent)
                    if not self._final_acks:
                        self._stop.set()
            elif kind is Commit:
                self.rows.commit(message.t)
                self.stats.committed(message.t, message.agv)
            elif kind is AgentState:
                self.latest.agent(message)
                snapshot = self.rows.state(message)
                if snapshot is not None:
                    self._snapshot(snapshot)
            elif kind is Event:
                self._on_event(message)
            elif kind is AirStats:
                self.streams.air(message)
            elif kind is Stop:
                if sample.sender == "sim":
                    self._end_of_run()
                elif self._stop_timer is None:
                    # an operator's stop: the sim ends the run and says so; stop anyway if it cannot
                    self._stop_timer = asyncio.get_running_loop().call_later(STOP_GRACE, self._stop.set)
        except ValueError as exc:  # DecodeError and bad ids
            self.intake.refuse(sample.key, exc)

    def _on_tick(self, tick: TickArrays) -> None:
        if not self._ticks.admit(tick.t):
            return
        if self.rows.last_tick < 0 and self.recorder is not None and self.recorder.resume_from is not None:
            self._resume(tick)
            if self._done:
                return
        rows, snapshots = self.rows.tick(tick.t, tick.sim_time, tick.deliveries, tick.outcomes)
        if self.recorder is not None:
            self.recorder.positions(tick.t, *(tick.row(name).tolist() for name in ("x", "y", "heading", "carrying")))
        if self.network is not None:
            self.network.observe_tick(tick.t, self.config.dt, list(zip(tick.row("x").tolist(), tick.row("y").tolist())))
        self._closed(rows, snapshots)

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
        next_row = max(first_tick, last_row + 1)
        self.rows.resume(next_row, tick.deliveries_total if tick.deliveries_total is not None and
                         next_row == first_tick else total)
        kind = "monitor.gap" if next_row > last_row + 1 else "monitor.resumed"
        self.recorder.event(Event(kind=kind, source="monitor", t=first_tick, details={
            "first": last_row + 1, "last": next_row - 1, "reason": "monitor restarted"}).model_dump(mode="json"))
        self.recorder.flush()

    def _on_event(self, event: Event) -> None:
        if event.kind in QUIET_EVENTS:
            if event.kind == "ready.probe":
                # answered at once, as every participant does (the sim waits for the answers)
                self.bus.put(self.keys.event("monitor"), Event(
                    kind="ready.ack", source="monitor", details={"round": event.details.get("round", 0)}))
            return
        if event.kind == "agent.cut_off" and event.source == "sim" and isinstance(event.details.get("agent"), int):
            self.intake.cut_off.add(event.details["agent"])  # (events of "sim" come on the sim's key alone)
        self.fault_windows.add({"kind": event.kind, "t": event.t, "details": event.details})
        if event.kind == "run.finished":
            self.result.finished = {**(self.result.finished or {}), **event.details}
            self._end_of_run()
        if self.recorder is not None:
            self.recorder.event(event.model_dump(mode="json"))

    # -- rows out ------------------------------------------------------------------------------------------------------
    def _closed(self, rows: list[ClosedRow], snapshots: list[Snapshot]) -> None:
        """Record and publish the rows that became final, then the snapshots, in order."""
        for values, links in rows:
            self.result.deliveries_total = values["deliveries_total"]
            if self.keep_rows:
                self.result.rows.append(values)
            if self.recorder is not None:
                self.recorder.row(values, links=links)
            self.streams.row(values)
            if (values["t"] + 1) % PROGRESS_EVERY == 0:
                self._progress(values["t"] + 1)
        for snapshot in snapshots:
            self._snapshot(snapshot)

    def _snapshot(self, snapshot: Snapshot) -> None:
        if self.keep_rows:  # in memory only for in-process callers; the record has them on disk
            self.result.snapshots[snapshot.t] = (snapshot.W, snapshot.A)
        if self.recorder is not None:
            self.recorder.snapshot(snapshot.t, snapshot.W, snapshot.A)

    def _progress(self, rows: int) -> None:
        """Tell the sim that rows ``< rows`` are written (never dropped: the sim may be waiting for it)."""
        self.bus.put(self.keys.event("monitor"), Event(kind="record.progress", source="monitor", t=rows))

    def finish(self) -> None:
        """Write the last rows, the snapshots and the summary, and close the record (the end of the run)."""
        self._done = True
        if self._stop_timer is not None:
            self._stop_timer.cancel()
        self._closed(*self.rows.finish())
        self.streams.finish()
        steps = self.rows.next_row
        summary = {
            "run_id": self.config.run_id, "steps": steps, "deliveries_total": self.rows.deliveries_total,
            "rejected": self.result.rejected, "mean_links": self.rows.links_sum / max(1, steps),
            "sequence_gaps": self.stats.gaps,  # messages lost on the way to the monitor (per sender and key)
            "messages": dict(sorted(self.result.messages.items())),
            "bytes": dict(sorted(self.result.bytes.items())),
            "communication": self.result.communication(steps, self.n),
            "finished": self.result.finished,
            "final_links": self.rows.last.get("links"),
        }
        if self.recorder is not None:
            self.recorder.flush()
            if self.recorder.resume_from is not None:
                # a restarted monitor saw only part of the run: the totals are those of the record's rows
                summary.update(summary_of_rows(read_metrics(self.recorder.dir)))
            self.recorder.summary(summary)
            self.recorder.close()

    def _on_query(self, query: Query) -> None:
        self.latest.answer(query, self.rows.last_tick)
