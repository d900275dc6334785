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

from schemas import Event, OnBoard, Phase, Refusal, Resolve, Stop
from schemas.codec import encode_fields
from schemas.keys import RunKeys
from schemas.tick import TickObservation, encode_tick_body, onboard_fields, tick_fields
from services.bus.base import Bus, Sample
from services.bus.registry import mount_registry
from services.intake import Intake
from services.protocol import dispatch as protocol
from services.protocol.claims import (
    FloodWatch,
    OncePerTick,
    OutcomeBound,
    SenderBinding,
    outcome_step_bound,
)
from services.protocol.tick import TickStep
from services.runconfig import RunConfig
from services.sim import air
from services.sim.answers import Answers
from services.sim.phases import PhaseBarrier, PhaseCollection
from services.sim.presence import MONITOR, Presence
from services.sim.result import SimResult, TickClock
from services.sim.wire import make_controller, world_fields

log = logging.getLogger("morph_sim.sim")

LEAVE_TIMEOUT = 2.0  # seconds the sim waits, after its stop, for the other participants to leave
# ... and for the monitor, which may still be working through a backlog (64 agents publishing their state every tick
# on a loaded machine: several seconds). The sim hosts the endpoint: closing it earlier loses what is still on the way
# to the monitor, and the record would end before the run did (seen: 51 of 60 rows).
MONITOR_LEAVE_TIMEOUT = 20.0
STREAM_DRAIN_SECONDS = 5.0  # the endpoint stays open, after the others left, while a client follows streams


class SimService(Presence, PhaseCollection, Answers, air.AirAnnouncements):
    """Runs ``config.steps`` ticks over ``bus``. ``await run()`` returns a :class:`SimResult`."""

    def __init__(self, config: RunConfig, bus: Bus, *, wait_for_monitor: bool = True,
                 on_tick: Callable[[int, TickObservation], None] | None = None, faults=None):
        self.config = config
        # a FaultRuntime (services.faults.runtime) whose layer sits on this bus; phases then end
        # when every answer has *arrived* (delivered, held or dropped by the layer) and at each phase boundary the
        # runtime releases what is due, so a lost or late answer costs that agent its tick, never a hang.
        self.faults = faults
        self.bus = bus
        self.keys = RunKeys(config.run_id)
        # robots seen flooding or cut off (robot, refusals, event kind), reported at the next tick's start
        self._floods: list[tuple[int, int, str]] = []
        self.intake = Intake(bus, self.keys, log, "sim", on_refused=self._count_refused,
                             flood=FloodWatch(config.n_agents), on_flood=self._flooding)
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
        self._newcomer = asyncio.Event()  # a participant's liveliness token appeared: probe it now
        self._stop: str | None = None
        self._stop_event = asyncio.Event()
        self._phase: PhaseBarrier | None = None
        self._requests: dict[int, list[int]] = {}  # AGV -> pickers asked, this tick
        self._commits: dict[int, int] = {}  # picker -> AGV committed, this tick
        self._expected: dict[int, list[int]] = {}  # picker -> requesters (the resolve)
        # the dispatch protocol's sim side (services/protocol): commitments delivered and not yet applied
        self.outcomes = protocol.Outcomes()
        self.desk = protocol.CommitmentDesk(config.dt)
        self.robot_outcomes = protocol.OutcomeTally()  # the robots' own counts, as their acks report them
        # what one robot may claim of itself (services/protocol/claims.py): acks and commits of ticks the sim can
        # use, one ack per tick and phase, under its own header name, its counts growing no faster than its ticks
        # can make them grow
        self._outcome_bound = OutcomeBound(outcome_step_bound(self.n))
        self._once = OncePerTick()
        self._senders = SenderBinding()
        self._reported_outcomes: dict[str, int] = {}  # the sim's counts on its latest tick
        self._broadcast = config.make_policy().broadcast  # its AGVs ask several pickers in one tick
        self._desk_lock = threading.Lock()
        self._more: set[int] = set()  # pickers that asked for the next decision point (requests still to come)
        self._replied = [0] * config.n_agvs  # replies sent to each AGV so far (each Tick tells the AGVs)
        self._refused = [0] * self.n  # refusals sent to each robot so far (its on-board state tells it)
        self._messaged = [0] * self.n  # policy messages sent to each robot so far, by the ticks before the current
        self._probe_round = 0
        self._running = False  # between tick 0 and the end: only then does a leaving agent count as absent
        self._monitor_rows: int | None = None  # rows the monitor reported written (None: not heard since it joined)
        self._monitor_progress = asyncio.Event()
        self._monitor_gone_at: float | None = None  # when the monitor left mid-run (lockstep waits for its return)
        # a profile with shared capacity: the air process judges the radio and waits for the sim's announcements of
        # what was published at each instant (services/sim/air.py); tick 0 waits for it as for the monitor
        self.shared_air = config.shared_air
        self._air_refusals: dict[tuple[int | str, str], int] = {}  # the sim's refusals since its last Tick

    # -- control ------------------------------------------------------------------------------------------------------
    def _count_refused(self, total: int) -> None:
        self.result.rejected = total

    def _flooding(self, robot: int, refused: int) -> None:
        # (on the bus's receive path: the report is published from the tick loop)
        if refused >= self.intake.flood.cut_off:
            # the rest of the run goes on without it: its messages refused unread, its robot held as a crashed one's
            log.warning("sim: robot %d cut off for flooding: %d of its messages refused", robot, refused)
            self.intake.cut_off.add(robot)
            self._absent(robot, "cut off for flooding")
            self._floods.append((robot, refused, "agent.cut_off"))
            self.result.cut_off.append(robot)
            return
        log.warning("sim: robot %d floods the run: %d of its messages refused", robot, refused)
        self._floods.append((robot, refused, "agent.flooding"))
        self.result.flooding.append(robot)

    def _on_stop(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, Stop)
        if msg is None:
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

    async def _settle(self, obs: TickObservation) -> None:
        """The step boundary: apply the commitments delivered by now (the tick step counts them), tell both sides of
        each refused one."""
        with self._desk_lock:
            _, refusals = self.step.settle(obs, self.desk, self.outcomes)
        for r in refusals:
            refusal = Refusal(t=obs.t + 1, picker=r.picker, agv=r.agv, commit_seq=r.commit_seq)
            await self.bus.publish(self.keys.refusal(r.agv), refusal)
            await self.bus.publish(self.keys.refusal(r.picker), refusal)
            self._refused[r.agv] += 1
            self._refused[r.picker] += 1
            if self.shared_air:
                air.refusal_publications(self.keys, (r.agv, r.picker), self._air_refusals)

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
        self.registry = await mount_registry(bus, k, self.config.n_agvs, self.config.n_pickers,
                                             policy=self.config.policy_announcement())
        prober = asyncio.get_running_loop().create_task(self._probe_loop())
        await self._declare_streams_probe()
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
                          wall_seconds=round(r.wall_seconds, 3), tick_clock=r.tick_clock.summary(),
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
        if self.bus.hosts_endpoint and await self._streams_followed():
            log.info("a client follows the metric streams: the endpoint stays open while it does, up to %.0f s",
                     STREAM_DRAIN_SECONDS)
            # A client following the metric streams (watch, a user's script) may still be reading what the monitor
            # published last, often a backlog of rows it sent out as it left; closing the endpoint now would cut it
            # off (seen on a busy machine: a client still reading rows 200-300 of a 300-tick run four seconds after
            # the run's end). A client that has what it wanted leaves, and then the endpoint closes at once.
            drain_until = time.monotonic() + STREAM_DRAIN_SECONDS
            while time.monotonic() < drain_until and await self._streams_followed():
                await asyncio.sleep(0.1)
        await self.registry.close()
        await token.close()
        return r

    async def _declare_streams_probe(self) -> None:
        """Ask :meth:`_streams_followed` once at startup: the bus declares its probe on the first ask, and a probe
        declared only at the run's end would not yet know of a subscriber that has followed the streams all along."""
        await self._streams_followed()

    async def _streams_followed(self) -> bool:
        """Whether a subscriber outside the run's own processes follows the run's metric streams. ``morph-sim up``'s
        progress line follows only ``deliveries_total`` and ``links`` and the monitor has left by the run's end, so
        a subscriber of another stream is a client's."""
        try:
            await self.bus.wait_for_subscribers(self.keys.metric("lambda2"), timeout=0.0)
        except TimeoutError:
            return False
        return True

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
        replied, refused, messaged, n_agvs = self._replied, self._refused, self._messaged, self.config.n_agvs
        # each robot takes its on-board state and the broadcast together (over Zenoh in one message: bus.put_together)
        bus.put_together((k.fleet, tick), [
            (self._onboard_keys[robot], encode_fields(OnBoard, **onboard_fields(
                body, robot, robot in free, replied[robot] if robot < n_agvs else 0, refused[robot],
                messaged[robot])))
            for robot in range(self.n)])
        if self.shared_air:
            self._announce_sim(obs)

    async def _event(self, kind: str, **details) -> None:
        t = self.ctl.t
        await self.bus.publish(self.keys.event("sim"), Event(
            kind=kind, source="sim", t=t, sim_time=t * self.config.dt, wall_time=time.time(), details=details))

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
        self.result.tick_clock = clock = TickClock.for_steps(cfg.steps)
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
            while self._floods:  # reported in the record as an event naming the robot
                robot, refused, kind = self._floods.pop(0)
                await self._event(kind, agent=robot, refused=refused)
            obs = self.step.begin()
            t = obs.t
            clock.started(t, started)
            if self.on_tick is not None:
                self.on_tick(t, obs)
            if self.faults is not None:
                self.faults.advance(t * cfg.dt)  # tick start: schedule, heals, what is due
            self._requests = {}
            self._commits = {}
            self._expected = {}
            ph = PhaseBarrier(t, Phase.TICK, self.present())
            t1 = time.monotonic()
            spent["controller"] += t1 - started
            self._phase = ph  # before the tick goes out: inline acks may arrive before _collect starts
            self._publish_tick(obs)
            await self._collect(ph, self._deadline(started, Phase.TICK))
            self._announce_robots(ph, t * cfg.dt)
            t2 = time.monotonic()
            spent["tick_phase"] += t2 - t1
            more, self._more = self._more, set()
            if cfg.mode == "paced":
                more = set(range(cfg.n_agvs, self.n))  # a real-time fleet: every picker decides every step
            if self._requests or more:
                self._expected = expected = self.step.decision_plan(obs, self._requests, more)
                pickers = sorted(expected)
                ph = PhaseBarrier(t, Phase.RESOLVE, {p for p in pickers if p in self.present()})
                self._phase = ph
                await self.bus.publish(k.resolve, Resolve(t=t, pickers=pickers,
                                                          requesters=[expected[p] for p in pickers]))
                await self._collect(ph, self._deadline(started, Phase.RESOLVE), on_acked=(
                    (lambda ph=ph, t=t: self._announce_robots(ph, t * cfg.dt + cfg.dt / 2)) if self.shared_air else None))
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
        clock.started(obs.t, time.monotonic(), last=True)
        if self.faults is not None:
            self.faults.advance(obs.t * cfg.dt)  # its boundary, as every tick: stamps and releases like the others
        ph = PhaseBarrier(obs.t, Phase.TICK, self.present())
        self._phase = ph
        self._publish_tick(obs)
        wait = 0.5 if self._stop is not None else cfg.phase_timeout if cfg.mode == "lockstep" else cfg.period
        await self._collect(ph, time.monotonic() + wait)
        self.result.wall_seconds = time.monotonic() - t0
