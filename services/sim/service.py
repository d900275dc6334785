"""The sim clock service: the warehouse's single authority, running the two-phase lockstep tick (docs/services.md).

Per tick ``t``:

1. the CTA controller runs steps 1–2 (:meth:`CTAController.begin_tick`); the observation becomes a ``Tick``, the
   fleet broadcast on ``sim/fleet`` (faults act on it) and the world record on ``sim/tick`` (monitor, tools); each
   robot's own state goes to it on ``sim/@onboard/<id>`` (on-board sensing; it is also the decision point's
   synchronisation);
2. every present agent answers with an ``Ack`` listing the pickers it asked (AGVs send their ``HelpRequest``\\ s
   directly to those pickers);
3. if anybody asked, the sim publishes ``Resolve`` (per picker, the requesters in mission order); each picker that
   expects requests answers with a ``Commit`` (or an ``Ack`` of phase RESOLVE if it takes none);
4. the commits (validated against the resolve) are applied in mission order and the world steps.

After the last step a final ``Tick`` (``t == steps``) reports that step; agents apply their last plasticity update
and ack; then the sim publishes a ``run.finished`` event and ``ctl/stop``.

Presence: an agent takes part once its liveliness token is visible *and* it has answered a readiness probe
(declarations propagate asynchronously in Zenoh). An agent whose token disappears, or that stays silent past
the lockstep phase timeout, is absent until it answers a probe again; the sim never waits for an absent agent, and
its robot gets no new help from it (its requests are simply missing).

The service never raises on bad input: undecodable or out-of-place messages are counted in ``rejected`` and logged.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from schemas import Ack, Commit, Event, OnBoard, Phase, Refusal, Resolve, Stop
from schemas.codec import encode_fields
from schemas.keys import RunKeys
from schemas.tick import TickObservation, encode_tick_body, onboard_fields, tick_fields
from services.bus.base import Bus, LivelinessEvent, Sample
from services.bus.registry import mount_registry
from services.protocol import dispatch as protocol
from services.protocol.tick import TickStep
from services.rejects import Rejects
from services.runconfig import RunConfig
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig

log = logging.getLogger("morph_sim.sim")

LEAVE_TIMEOUT = 2.0  # seconds the sim waits, after its stop, for the other participants to leave
# ... and for the monitor, which may still be working through a backlog (64 agents publishing their state every tick
# on a loaded machine: several seconds). The sim hosts the endpoint: closing it earlier loses what is still on the way
# to the monitor, and the record would end before the run did (seen: 51 of 60 rows).
MONITOR_LEAVE_TIMEOUT = 20.0
PROBE_INTERVAL = 0.25  # seconds between readiness probes
MONITOR = "monitor"
# Lockstep: the sim runs at most this many ticks ahead of the rows the monitor has written (it reports them every
# PROGRESS_EVERY rows). The monitor takes in every message of the run and is not part of the tick's barrier; without
# this bound a monitor slower than the run builds an unbounded backlog (memory, a record that ends long after the
# run, live streams that lag by minutes). Larger than PROGRESS_EVERY plus the rows a monitor may hold back.
MONITOR_WINDOW = 200


def world_fields(ctl: CTAController, obs: TickObservation) -> dict:
    """The Tick fields that describe the world beyond the observation (monitor, live views)."""
    wh = ctl.wh
    queue = set(wh.queue)
    partner = [-1] * ctl.n
    by_cell = {m.cell: p for p, m in ctl.picker_missions.items()}
    for agv, m in ctl.agv_missions.items():
        p = by_cell.get(m.cell)
        if p is not None:
            partner[agv] = int(p)  # plain ints: the sim packs this map without the model (encode_tick_body)
            partner[p] = int(agv)
    loads, unloads = handling_pairs(obs, wh.carrying)
    return dict(
        heading=[int(d) for d in wh.dir], busy=[bool(b) for b in wh.busy],
        carrying=[bool(c) for c in wh.carrying], carrying_requested=[bool(c) and c in queue for c in wh.carrying],
        partner=partner, request_queue=[int(q) for q in wh.queue], loads=loads, unloads=unloads,
        deliveries_total=int(ctl.deliveries),
    )


def handling_pairs(obs: TickObservation, carrying) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(AGV, picker) pairs that loaded / unloaded in step t−1, from the observation's ``handled`` robots.

    A load or unload always has the AGV and one picker on the same cell (cta.py), so the pairs carry ``handled``
    exactly; an unpaired handled robot would be a controller bug and is logged.
    """
    handled = getattr(obs, "handled", None)
    if handled is None:
        return [], []
    cells = obs.cells
    pickers = {(int(cells[p, 0]), int(cells[p, 1])): p for p in np.flatnonzero(handled[obs.n_agvs:]) + obs.n_agvs}
    loads, unloads, paired = [], [], set()
    for agv in np.flatnonzero(handled[: obs.n_agvs]):
        p = pickers.get((int(cells[agv, 0]), int(cells[agv, 1])))
        if p is None:
            continue
        (loads if carrying[agv] else unloads).append((int(agv), int(p)))
        paired.update((int(agv), int(p)))
    missing = set(np.flatnonzero(handled).tolist()) - paired
    if missing:
        log.error("sim: handled robots %s have no load/unload partner; agents will not see them", sorted(missing))
    return loads, unloads


def make_controller(config: RunConfig) -> CTAController:
    """The world of a run: a warehouse of the configured size and fleet, reset with the run's seed."""
    wh_cfg = WarehouseConfig.named(config.scale, config.n_agvs, config.n_pickers,
                                   max_steps=max(config.steps + 1, 500))
    ctl = CTAController(Warehouse(wh_cfg))
    ctl.reset(config.seed)
    return ctl


@dataclass
class Pace:
    """When the ticks of a paced run started (wall clock): what the fleet saw of its real-time period."""

    period: float = 0.0
    ticks: int = 0
    interval_max: float = 0.0  # wall seconds between two tick starts, at most
    interval_min: float = float("inf")  # ... and at least
    interval_sum: float = 0.0
    late: int = 0  # intervals longer than 1.5 periods
    early: int = 0  # intervals shorter than half a period (a tick after one that overran its period)
    rescheduled: int = 0  # times the sim was more than a period behind and started again from the present
    worst: list[tuple[int, float]] = field(default_factory=list)  # the 5 longest intervals: (tick, seconds)
    _last: float | None = None

    def started(self, t: int, now: float) -> None:
        if self._last is not None:
            gap = now - self._last
            self.interval_sum += gap
            self.interval_max = max(self.interval_max, gap)
            self.interval_min = min(self.interval_min, gap)
            self.late += gap > 1.5 * self.period
            self.early += gap < 0.5 * self.period
            self.worst = sorted([*self.worst, (t, gap)], key=lambda w: -w[1])[:5]
        self._last = now
        self.ticks += 1

    def summary(self) -> dict:
        n = max(1, self.ticks - 1)
        return {"period": self.period, "ticks": self.ticks, "interval_mean": round(self.interval_sum / n, 4),
                "interval_min": round(self.interval_min, 4) if self.ticks > 1 else None,
                "interval_max": round(self.interval_max, 4), "late": self.late, "early": self.early, "rescheduled": self.rescheduled,
                "worst": [[t, round(g, 4)] for t, g in self.worst]}


@dataclass
class SimResult:
    steps: int = 0
    deliveries: int = 0
    per_tick_deliveries: list[int] = field(default_factory=list)
    commits_applied: int = 0
    rejected: int = 0
    absences: int = 0
    wall_seconds: float = 0.0
    stopped_early: str | None = None
    protocol: dict[str, int] = field(default_factory=dict)  # the dispatch protocol's outcome counters (sim + robots)
    network_stops: int = 0  # robot-steps a network profile's silence stop held a robot in place
    pace: Pace = field(default_factory=Pace)  # paced mode: the tick starts' intervals
    # wall seconds spent per part of the tick (where a distributed tick's time goes)
    phase_seconds: dict[str, float] = field(default_factory=lambda: {
        "controller": 0.0, "tick_phase": 0.0, "resolve_phase": 0.0, "step": 0.0})

    @property
    def ticks_per_s(self) -> float:
        return self.steps / self.wall_seconds if self.wall_seconds > 0 else 0.0


class _Phase:
    """Who must still answer in the current phase, and a future that resolves when nobody is left.

    Answers arrive on the transport's receive thread (inline handlers) or on the loop; ``lock`` guards ``waiting``
    and the answers recorded with it, and ``close`` (on the loop, when the phase ends) makes later answers stale.
    """

    def __init__(self, t: int, phase: int, waiting: set[int]):
        self.t = t
        self.phase = phase
        self.waiting = set(waiting)
        self.held: set[int] = set()  # answers held by the fault layer (virtual time): accepted if released in time
        # RESOLVE: a picker's ack names the AGV it committed to; it has answered once that Commit has arrived too
        # (delivered, or held / lost by the network: either way nothing more is coming from it this phase)
        self.commit_wanted: dict[int, int] = {}
        self.commit_arrived: set[int] = set()
        self.lock = threading.Lock()
        self.closed = False
        self._loop = asyncio.get_running_loop()
        self.done = self._loop.create_future()
        if not self.waiting:
            self.done.set_result(None)

    def answered(self, agent: int) -> None:
        """Call with ``lock`` held, from any thread."""
        if agent in self.waiting:
            self.waiting.discard(agent)
            if not self.waiting:
                self._loop.call_soon_threadsafe(self._finish)

    def _finish(self) -> None:
        if not self.done.done():
            self.done.set_result(None)

    def close(self) -> None:
        with self.lock:
            self.closed = True


class SimService:
    """Runs ``config.steps`` ticks over ``bus``. ``await run()`` returns a :class:`SimResult`."""

    def __init__(self, config: RunConfig, bus: Bus, *, wait_for_monitor: bool = True,
                 on_tick: Callable[[int, TickObservation], None] | None = None, faults=None):
        self.config = config
        # a FaultRuntime (services.faults.runtime) whose layer sits on this bus; phases then end
        # when every answer has *arrived* (delivered, held or dropped by the layer) and at each phase boundary the
        # runtime releases what is due, so a lost or late answer costs that agent its tick, never a hang.
        self.faults = faults
        self._rejects = Rejects(log, "sim")
        self.bus = bus
        bus.reject_hook = self._reject  # oversized messages refused on arrival count here
        self.keys = RunKeys(config.run_id)
        self.n = config.n_agents
        self._onboard_keys = [self.keys.onboard(robot) for robot in range(self.n)]  # named every tick
        self.wait_for_monitor = wait_for_monitor
        self.on_tick = on_tick
        self.ctl = make_controller(config)
        self.step = TickStep(self.ctl, dt=config.dt)
        self.result = SimResult()
        self.result.pace.period = config.period
        self.alive: set[int | str] = set()  # liveliness tokens visible
        self.ready: set[int | str] = set()  # answered a probe since their token appeared
        self._ready_changed = asyncio.Event()
        self._stop: str | None = None
        self._stop_event = asyncio.Event()
        self._phase: _Phase | None = None
        self._requests: dict[int, list[int]] = {}  # AGV -> pickers asked, this tick
        self._commits: dict[int, int] = {}  # picker -> AGV committed, this tick
        self._expected: dict[int, list[int]] = {}  # picker -> requesters (the resolve)
        # the dispatch protocol's sim side (services/protocol): commitments delivered and not yet applied
        self.outcomes = protocol.Outcomes()
        self.desk = protocol.CommitmentDesk(config.dt)
        self.robot_outcomes = protocol.OutcomeTally()  # the robots' own counts, as their acks report them
        self._reported_outcomes: dict[str, int] = {}  # the sim's counts on its latest tick
        self._broadcast = config.make_policy().broadcast  # its AGVs ask several pickers in one tick
        self._desk_lock = threading.Lock()
        self._more: set[int] = set()  # pickers that asked for the next decision point (requests still to come)
        self._replied = [0] * config.n_agvs  # replies sent to each AGV so far (each Tick tells the AGVs)
        self._refused = [0] * self.n  # refusals sent to each robot so far (its on-board state tells it)
        self._probe_round = 0
        self._running = False  # between tick 0 and the end: only then does a leaving agent count as absent
        self._monitor_rows: int | None = None  # rows the monitor reported written (None: not heard since it joined)
        self._monitor_progress = asyncio.Event()
        self._monitor_gone_at: float | None = None  # when the monitor left mid-run (lockstep waits for its return)

    # -- presence ----------------------------------------------------------------------------------------------------
    def present(self) -> set[int]:
        return {a for a in self.ready if isinstance(a, int) and a in self.alive}

    def _reject(self, what: str, why: object) -> None:
        self._rejects.count(what, why)
        self.result.rejected = self._rejects.total

    def _on_alive(self, event: LivelinessEvent) -> None:
        try:
            who = self.keys.alive_id(event.key)
        except ValueError as exc:
            self._reject(event.key, exc)
            return
        if isinstance(who, int) and not 0 <= who < self.n:
            self._reject(event.key, f"agent id {who} outside 0..{self.n - 1}")
            return
        if event.alive:
            self.alive.add(who)
            if who == MONITOR:
                self._monitor_gone_at = None
                self._monitor_progress.set()
        else:
            self.alive.discard(who)
            if who == MONITOR:
                self._monitor_rows = None  # a restarted monitor starts at the live tick: no rows to wait for
                if self._running and self._stop is None:
                    self._monitor_gone_at = time.monotonic()
                self._monitor_progress.set()
            self.ready.discard(who)
            self._absent(who, "liveliness token gone")
        self._ready_changed.set()

    def _absent(self, who: int | str, why: str) -> None:
        if isinstance(who, int) and self._running and self._stop is None:
            self.result.absences += 1
            log.info("sim: agent %s absent (%s)", who, why)
            ph = self._phase
            if ph is not None:
                with ph.lock:
                    ph.answered(who)

    def _on_event(self, sample: Sample) -> None:
        try:
            msg = sample.decode(Event)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if msg.kind == "record.progress":
            if self.keys.sender_of(sample.key) != MONITOR or msg.t is None:
                self._reject(sample.key, "record progress from another participant than the monitor")
                return
            self._monitor_rows = max(self._monitor_rows or 0, msg.t)
            self._monitor_progress.set()
            return
        if msg.kind != "ready.ack":
            return
        who = msg.source
        if self.keys.sender_of(sample.key) != who:
            self._reject(sample.key, f"ready ack of {who!r} on the key of another participant")
            return
        if who in self.alive and who not in self.ready:
            self.ready.add(who)
            self._ready_changed.set()

    def _on_stop(self, sample: Sample) -> None:
        try:
            msg = sample.decode(Stop)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if sample.sender == self.bus.identity:
            return
        self.stop(msg.reason or "stop requested")

    def stop(self, reason: str) -> None:
        """End the run after the current phase (operator stop, SIGTERM)."""
        if self._stop is None:
            self._stop = reason
        self._stop_event.set()
        if self._phase is not None and not self._phase.done.done():
            self._phase.done.set_result(None)

    # -- tick traffic ------------------------------------------------------------------------------------------------
    def _on_arrival(self, sample: Sample, fate: list[float]) -> None:
        """Fault layer hook: a sample physically arrived. A skip (an ack that cannot come, runtime.py) answers the
        phase. A Commit held or lost by the network has arrived all the same: its picker owes nothing more."""
        if fate and min(fate) <= 0.0:
            return  # delivered now: the handler records it
        ph = self._phase
        rel = sample.key.rsplit("/", 1)[-1]
        if ph is None or rel not in ("ack", "commit"):
            return
        try:
            msg = sample.decode(Ack if rel == "ack" else Commit)
        except ValueError:
            return  # the handler rejects it if it is ever delivered
        who = msg.agent if rel == "ack" else msg.picker
        if msg.t != ph.t or (rel == "ack" and msg.phase != ph.phase) or (rel == "commit" and ph.phase != Phase.RESOLVE):
            return
        with ph.lock:
            if ph.closed or who not in ph.waiting:
                return
            if rel == "commit":
                self._commit_arrived(ph, who)
                return
            if fate:
                ph.held.add(who)
            ph.answered(who)

    @staticmethod
    def _commit_arrived(ph: _Phase, picker: int) -> None:
        """With ``ph.lock`` held."""
        ph.commit_arrived.add(picker)
        if ph.commit_wanted.pop(picker, None) is not None:
            ph.answered(picker)

    def _boundary(self, t: int, phase: int) -> None:
        """Virtual time: reach the boundary that closes ``phase`` of tick ``t`` (releases held answers)."""
        if self.faults is not None:
            from services.faults.vtime import boundaries

            self.faults.advance(boundaries(t, self.config.dt)[1 if phase == Phase.TICK else 2])

    def _decode_own(self, sample: Sample, model: type, author: str, what: str):
        """Decode an answer and check that its author sent it under its own key; a bad one is counted and None."""
        try:
            msg = sample.decode(model)
            self.keys.check_author(sample.key, getattr(msg, author), what)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return None
        return msg

    def _on_ack(self, sample: Sample) -> None:
        msg = self._decode_own(sample, Ack, "agent", "ack of agent")
        if msg is None:
            return
        if msg.outcomes is not None and msg.phase == Phase.TICK:
            with self._desk_lock:
                self.robot_outcomes.report(msg.agent, msg.t, msg.outcomes)
        ph = self._phase
        if ph is None or msg.t != ph.t or msg.phase != ph.phase:
            return  # an ack of another phase: synchronisation only, nothing to do
        with ph.lock:
            if ph.closed or (msg.agent not in ph.waiting and msg.agent not in ph.held):
                return  # duplicate
            ph.held.discard(msg.agent)
            if ph.phase == Phase.TICK:
                asked = [p for p in msg.requests_sent if self.config.n_agvs <= p < self.n]
                if msg.agent < self.config.n_agvs and asked:
                    # one request per AGV per tick; a broadcasting policy's AGV asks each picker once
                    self._requests[msg.agent] = list(dict.fromkeys(asked)) if self._broadcast else asked[:1]
            else:
                if msg.more:
                    self._more.add(msg.agent)
                for a in msg.replied_to:
                    if 0 <= a < self.config.n_agvs:
                        self._replied[a] += 1
                if msg.committed_to is not None and msg.agent not in ph.commit_arrived:
                    ph.commit_wanted[msg.agent] = msg.committed_to  # answered when its Commit arrives
                    return
            ph.answered(msg.agent)

    def _on_commit(self, sample: Sample) -> None:
        msg = self._decode_own(sample, Commit, "picker", "commit of picker")
        if msg is None:
            return
        if not (self.config.n_agvs <= msg.picker < self.n and 0 <= msg.agv < self.config.n_agvs):
            self._reject(sample.key, f"commit of robot {msg.picker} to robot {msg.agv}: not a picker and an AGV")
            return
        # never discarded for being late: it waits on the desk for the next step boundary, where it is applied if
        # still valid (else refused, and both sides told)
        sent = msg.t * self.config.dt + self.config.dt / 2
        cell = (msg.target_x, msg.target_y) if msg.target_x >= 0 and msg.target_y >= 0 else None
        with self._desk_lock:
            self.desk.receive(protocol.Commitment(msg.picker, msg.agv, cell, sent, msg.seq),
                              sample.due if sample.due >= 0.0 else sent, self.outcomes)
        ph = self._phase
        if ph is not None and ph.phase == Phase.RESOLVE and msg.t == ph.t:
            with ph.lock:
                if not ph.closed and msg.picker in ph.waiting:
                    self._commit_arrived(ph, msg.picker)

    async def _settle(self, obs: TickObservation) -> list[tuple[int, int]]:
        """The step boundary: apply the commitments delivered by now (services/protocol), tell both sides of each
        refused one."""
        with self._desk_lock:
            applied, refusals = self.step.settle(obs, self.desk, self.outcomes)
        for r in refusals:
            refusal = Refusal(t=obs.t + 1, picker=r.picker, agv=r.agv, commit_seq=r.commit_seq)
            await self.bus.publish(self.keys.refusal(r.agv), refusal)
            await self.bus.publish(self.keys.refusal(r.picker), refusal)
            self._refused[r.agv] += 1
            self._refused[r.picker] += 1
        return applied

    # -- main ----------------------------------------------------------------------------------------------------------
    async def run(self) -> SimResult:
        k = self.keys
        bus = self.bus
        token = await bus.declare_token(k.alive("sim"))
        if self.faults is not None:
            layer = next((x for x in self.faults.layers if x is bus._interposer), None) or self.faults.attach(bus)
            layer.on_fate = self._on_arrival
            await self.faults.start()
        # inline: acks and commits are counted on the receive thread; only a phase's end wakes the loop
        await bus.subscribe(k.acks, self._on_ack, inline=True)
        await bus.subscribe(k.commits, self._on_commit, inline=True)
        await bus.subscribe(k.events, self._on_event)
        await bus.subscribe(k.stop, self._on_stop)
        await bus.subscribe_liveliness(k.alive_all, self._on_alive, history=True)
        # agents started without an id claim one here (morph/<run>/registry) before they declare their token
        self.registry = await mount_registry(bus, k, self.config.n_agvs, self.config.n_pickers)
        prober = asyncio.get_running_loop().create_task(self._probe_loop())
        try:
            await self._wait_ready()
            if self._stop is None:
                await self._event("run.started", agents=sorted(self.present()))
                await self._loop()
        finally:
            prober.cancel()
            try:
                await prober
            except (asyncio.CancelledError, Exception):
                pass
        r = self.result
        with self._desk_lock:  # the run's outcomes by the end of its last step: the sim's own, as its final tick
            # reported them, and the robots' (their acks of the final tick): the record's last row
            r.protocol = self.robot_outcomes.total(self._reported_outcomes)
        await self._event("run.finished", steps=r.steps, deliveries=r.deliveries,
                          stopped_early=r.stopped_early, rejected=r.rejected, absences=r.absences,
                          protocol=r.protocol,
                          **({"network_stops": r.network_stops} if self.config.network is not None else {}),
                          **({"pace": r.pace.summary()} if self.config.mode == "paced" else {}),
                          wall_seconds=round(r.wall_seconds, 3),
                          phase_seconds={k: round(v, 3) for k, v in r.phase_seconds.items()})
        await bus.publish(k.stop, Stop(reason="finished" if r.stopped_early is None else r.stopped_early))
        # The sim hosts the endpoint: let the others leave first (their tokens go), so nobody loses the stop and
        # closing the router session does not have to tear down live connections.
        started = time.monotonic()
        while True:
            waited = time.monotonic() - started
            if waited >= MONITOR_LEAVE_TIMEOUT or not (self.alive - {"sim"}):
                break
            if waited >= LEAVE_TIMEOUT and MONITOR not in self.alive:
                break  # agents that linger do not hold up the end; only the monitor's record does
            self._ready_changed.clear()
            try:
                await asyncio.wait_for(self._ready_changed.wait(), 0.1)
            except asyncio.TimeoutError:
                pass
        await self.registry.close()
        await token.close()
        return r

    def _publish_tick(self, obs: TickObservation) -> None:
        """Tick start: the fleet broadcast (a network message: faults act on it), the world record (the monitor's,
        never a robot's), and each robot's on-board state on its own key, which carries the synchronisation of its
        decision point (an AGV's count of replies sent to it). One encoding serves the broadcast and the record."""
        k, bus = self.keys, self.bus
        # the sim's dispatch outcome counts ride along for the record (the monitor's copy is never faulted)
        self._reported_outcomes = self.outcomes.counts()
        body = tick_fields(obs, obs.t * self.config.dt,
                           {**world_fields(self.ctl, obs), "outcomes": self._reported_outcomes})
        tick = encode_tick_body(body)
        bus.put(k.tick, tick)
        free = set(body["free_pickers"])
        replied, refused, n_agvs = self._replied, self._refused, self.config.n_agvs
        # each robot takes its on-board state and the broadcast together (over Zenoh in one message: bus.put_together)
        bus.put_together((k.fleet, tick), [
            (self._onboard_keys[robot], encode_fields(OnBoard, **onboard_fields(
                body, robot, robot in free, replied[robot] if robot < n_agvs else 0, refused[robot])))
            for robot in range(self.n)])

    async def _event(self, kind: str, **details) -> None:
        t = self.ctl.t
        await self.bus.publish(self.keys.event("sim"), Event(
            kind=kind, source="sim", t=t, sim_time=t * self.config.dt, wall_time=time.time(), details=details))

    async def _probe_loop(self) -> None:
        while True:
            if any(a not in self.ready and (isinstance(a, int) or a == MONITOR) for a in self.alive):
                self._probe_round += 1
                await self.bus.publish(self.keys.event("sim"), Event(
                    kind="ready.probe", source="sim", details={"round": self._probe_round}))
            await asyncio.sleep(PROBE_INTERVAL)

    def _everyone_ready(self) -> bool:
        need_monitor = self.wait_for_monitor and MONITOR not in self.ready
        return len(self.present()) >= self.n and not need_monitor

    async def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.config.ready_timeout
        while not self._everyone_ready():
            if self._stop is not None:
                return
            left = deadline - time.monotonic()
            if left <= 0:
                missing = sorted(set(range(self.n)) - self.present())
                raise TimeoutError(
                    f"ready_timeout: {len(missing)} of {self.n} agents not ready after "
                    f"{self.config.ready_timeout:.0f} s (missing: {missing[:20]})"
                    + ("" if MONITOR in self.ready or not self.wait_for_monitor else "; monitor not ready"))
            self._ready_changed.clear()
            try:
                await asyncio.wait_for(self._ready_changed.wait(), min(left, PROBE_INTERVAL))
            except asyncio.TimeoutError:
                pass

    def _deadline(self, started: float, phase: int) -> float:
        if self.config.mode == "paced":
            # a phase gets a share of the period; a late answer means no action this tick
            share = 0.45 if phase == Phase.TICK else 0.9
            return started + share * self.config.period
        return time.monotonic() + self.config.phase_timeout

    async def _collect(self, ph: _Phase, deadline: float) -> None:
        self._phase = ph
        if self._stop is not None:  # the run is ending: take what is already in, wait for nobody
            deadline = min(deadline, time.monotonic() + 0.2)
        left = deadline - time.monotonic()
        try:
            if left > 0:
                await asyncio.wait_for(asyncio.shield(ph.done), left)
        except asyncio.TimeoutError:
            pass
        finally:
            self._boundary(ph.t, ph.phase)
            ph.close()
            self._phase = None
        if ph.waiting and self.config.mode == "lockstep" and self._stop is None:
            for who in sorted(ph.waiting):
                self.ready.discard(who)  # silent past the timeout: absent until it answers a probe again
                self._absent(who, f"no answer in phase {ph.phase} of tick {ph.t} within {self.config.phase_timeout} s")

    async def _keep_monitor_window(self, t: int) -> None:
        """Before tick ``t``: wait while the monitor's record is more than MONITOR_WINDOW ticks behind, and while a
        monitor that left mid-run is away (a supervisor restarts it; a run that went on at full speed could end
        before it is back, and close the endpoint on it: the record would then not even say what it lost). A monitor
        that makes no progress, or stays away, for a phase timeout is not waited for any more (until it reports or
        returns): the record then says what it lost, and the run goes on."""
        started, waited = time.monotonic(), False
        while self._stop is None and self._monitor_gone_at is not None:
            if time.monotonic() - self._monitor_gone_at > self.config.phase_timeout:
                log.warning("sim: the monitor left %.0f s ago and is not back; the run goes on without it",
                            self.config.phase_timeout)
                self._monitor_gone_at = None
                break
            await self._monitor_news(0.25)
            waited = True
        rows = self._monitor_rows
        if rows is not None and t - rows > MONITOR_WINDOW:
            progressed = time.monotonic()
            while self._stop is None and self._monitor_rows is not None and t - self._monitor_rows > MONITOR_WINDOW:
                if self._monitor_rows > rows:
                    rows, progressed = self._monitor_rows, time.monotonic()
                elif time.monotonic() - progressed > self.config.phase_timeout:
                    log.warning("sim: the monitor's record is stuck at row %d (tick %d); not waiting for it", rows, t)
                    self._monitor_rows = None
                    break
                await self._monitor_news(0.5)
                waited = True
        if waited:
            self.result.phase_seconds["monitor_wait"] = (
                self.result.phase_seconds.get("monitor_wait", 0.0) + time.monotonic() - started)

    async def _monitor_news(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for the monitor to report rows, leave or come back."""
        self._monitor_progress.clear()
        try:
            await asyncio.wait_for(self._monitor_progress.wait(), timeout)
        except asyncio.TimeoutError:
            pass

    async def _loop(self) -> None:
        self._running = True
        try:
            await self._ticks()
        finally:
            self._running = False

    async def _ticks(self) -> None:
        cfg = self.config
        k = self.keys
        t0 = time.monotonic()
        next_start = t0
        for _ in range(cfg.steps):
            if self._stop is not None:
                self.result.stopped_early = self._stop
                break
            if cfg.mode == "paced":
                delay = next_start - time.monotonic()
                if delay > 0:
                    try:
                        await asyncio.wait_for(self._stop_event.wait(), delay)
                        continue
                    except asyncio.TimeoutError:
                        pass
                elif delay < -cfg.period:
                    # more than a period behind (the machine stalled): this tick starts now and the schedule starts
                    # again from here; a real-time fleet does not run the missed ticks back to back
                    next_start = time.monotonic()
                    self.result.pace.rescheduled += 1
                next_start += cfg.period
                self.result.pace.started(self.result.steps, time.monotonic())
            if cfg.mode == "lockstep" and self.wait_for_monitor:
                await self._keep_monitor_window(self.result.steps)
            started = time.monotonic()
            spent = self.result.phase_seconds
            obs = self.step.begin()
            t = obs.t
            if self.on_tick is not None:
                self.on_tick(t, obs)
            if self.faults is not None:
                self.faults.advance(t * cfg.dt)  # tick start: schedule, heals, what is due
            self._requests = {}
            self._commits = {}
            self._expected = {}
            ph = _Phase(t, Phase.TICK, self.present())
            t1 = time.monotonic()
            spent["controller"] += t1 - started
            self._phase = ph  # before the tick goes out: inline acks may arrive before _collect starts
            self._publish_tick(obs)
            await self._collect(ph, self._deadline(started, Phase.TICK))
            t2 = time.monotonic()
            spent["tick_phase"] += t2 - t1
            more, self._more = self._more, set()
            if cfg.mode == "paced":
                more = set(range(cfg.n_agvs, self.n))  # a real-time fleet: every picker decides every step
            if self._requests or more:
                self._expected = expected = self.step.decision_plan(obs, self._requests, more)
                pickers = sorted(expected)
                ph = _Phase(t, Phase.RESOLVE, {p for p in pickers if p in self.present()})
                self._phase = ph
                await self.bus.publish(k.resolve, Resolve(t=t, pickers=pickers,
                                                          requesters=[expected[p] for p in pickers]))
                await self._collect(ph, self._deadline(started, Phase.RESOLVE))
            if self.faults is not None:
                self.faults.advance((t + 1) * cfg.dt)  # the step boundary: what is due by now is delivered
            t3 = time.monotonic()
            spent["resolve_phase"] += t3 - t2
            await self._settle(obs)
            # an absent agent's robot gets no new target
            delivered = self.step.finish(idle=set(range(self.n)) - self.present(),
                                         radio=self.faults.network if self.faults is not None else None)
            self.result.network_stops = self.step.network_stops
            self.result.commits_applied = self.step.commits_applied
            self.result.steps += 1
            self.result.deliveries = self.ctl.deliveries
            self.result.per_tick_deliveries.append(delivered)
            spent["step"] += time.monotonic() - t3
            self.result.wall_seconds = time.monotonic() - t0
        # the final tick: agents apply the update of the last step, nobody dispatches
        obs = self.step.final()
        if self.faults is not None:
            self.faults.advance(obs.t * cfg.dt)  # its boundary, as every tick: stamps and releases like the others
        ph = _Phase(obs.t, Phase.TICK, self.present())
        self._phase = ph
        self._publish_tick(obs)
        wait = 0.5 if self._stop is not None else cfg.phase_timeout if cfg.mode == "lockstep" else cfg.period
        await self._collect(ph, time.monotonic() + wait)
        self.result.wall_seconds = time.monotonic() - t0
