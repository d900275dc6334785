"""The agent service: one robot's coordination brain, learning and deciding from messages only.

It owns that robot's :class:`~services.policies.coordinators.Coordinator` (its plasticity state and its own seeded
RNG) and nothing else. Per tick ``t`` (docs/services.md):

* what it knows of the other robots is its latest fleet broadcast (``sim/fleet``, a network message that may be
  late or lost: a :class:`~services.protocol.dispatch.FleetView` with its age); what it knows of itself (cell,
  mission, target, load) comes on board (``sim/@onboard/<id>``), which is also its decision point;
* at its decision point it learns once from a fleet view it has not learnt from (the plasticity update of the step
  before that view), and, as an AGV that needs a picker, picks a candidate from that view with its own on-board
  cell and target, draws its gate and on success sends a ``HelpRequest`` to that picker; then it acks (with its
  out-links and its view's age, for the monitor);
* as a picker, on ``Resolve`` it waits for the requests it was told to expect, takes the first in mission order
  (deterministic), sends ``Commit`` to the sim and ``HelpReply`` to every requester;
* every ``state_every`` ticks (and at the final tick) it publishes its state (row of W, links, h, η).

The final tick (``t == steps``) only reports the last step: the agent learns and acks, and never asks.
Bad input never stops the agent: rejected messages are counted and logged.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from schemas import Ack, AgentState, Commit, Event, HelpReply, HelpRequest, OnBoard, Phase, Refusal, Resolve, Stop
from schemas.codec import encode_fields, unpack_envelope
from schemas.keys import RunKeys
from schemas.tick import decode_tick, observation_from_arrays, tick_number
from services.bus.base import Bus, Sample
from services.policies.coordinators import Fleet, MorphBrains
from services.protocol import dispatch as protocol
from services.rejects import Rejects
from services.runconfig import RunConfig
from services.tickorder import TickOrder

log = logging.getLogger("morph_sim.agent")

STOP_GRACE = 3.0  # seconds an agent waits for the sim's end of run after someone else's stop
RESTORE_TIMEOUT = 5.0  # seconds a (re)starting agent waits for the monitor's latest states


def _check_from_sim(sample: Sample, what: str) -> None:
    """ValueError unless the sim published ``sample``: only the sim speaks for the world and its clock."""
    if sample.sender != "sim":
        raise ValueError(f"{what} published by {sample.sender!r}, not the sim")


@dataclass
class AgentCounters:
    ticks: int = 0
    requests: int = 0
    commits: int = 0
    rejected: int = 0


class AgentService:
    """Agent ``agent_id`` of the run of ``config`` over ``bus``. ``await run()`` until stop."""

    def __init__(self, config: RunConfig, bus: Bus, agent_id: int, *, restore: bool = True, faults=None):
        # this process's FaultRuntime (ingress faults on what this agent receives, its ctl/faults
        # controller, sim-time stamps); in virtual time it advances on every on-board state, fleet broadcast and
        # Resolve of the sim that arrives (_on_arrival)
        self.faults = faults
        # picker, with faults: t -> AGVs whose request arrived but was dropped (or held past the boundary)
        self._arrived: dict[int, set[int]] = {}
        # restore: a (re)started agent loads its plasticity state from the monitor's latest states
        # (state/agent/*) before it joins; a first start finds none. restore=False is the cold restart.
        self.restore = restore
        self.restored_from: AgentState | None = None
        if not 0 <= agent_id < config.n_agents:
            raise ValueError(f"id: agent {agent_id} outside 0..{config.n_agents - 1} for this fleet")
        self.config = config
        self._rejects = Rejects(log, f"agent {agent_id}")
        self.bus = bus
        bus.reject_hook = self._reject  # oversized messages refused on arrival count here
        self.id = agent_id
        self.keys = RunKeys(config.run_id)
        self._onboard_key = self.keys.onboard(agent_id)
        self._ack_key, self._state_key = self.keys.ack(agent_id), self.keys.agent_state(agent_id)  # every tick
        self.is_agv = agent_id < config.n_agvs
        self.role = "agv" if self.is_agv else "picker"
        fleet = Fleet(config.n_agvs, config.n_pickers, config.scale)
        self.brains = config.make_policy().brains(fleet, [agent_id], config.seed)
        self.counters = AgentCounters()
        self.last_t = -1
        self._ticks = TickOrder(config.steps)  # which ticks this agent takes (services/tickorder.py)
        self._stop = asyncio.Event()
        self._seq = 0
        # picker side: requests received per tick, and the resolve being decided
        self._inbox: dict[int, dict[int, HelpRequest]] = {}
        self._pending: tuple[int, list[int]] | None = None
        self._resolved_t = -1  # the last tick this picker decided: a duplicated Resolve never decides twice
        self._pending_timer: asyncio.TimerHandle | None = None
        self._stop_timer: asyncio.TimerHandle | None = None
        # The hot path (tick, request, resolve) runs inline on the transport's receive thread; the resolve deadline
        # fires on the loop. This lock keeps the picker's inbox and pending resolve consistent between the two.
        self._lock = threading.RLock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._virtual = faults is not None and faults.vtime is not None
        # the dispatch protocol's endpoint of this robot (services/protocol), and what became of its messages
        self.outcomes = protocol.Outcomes()
        if self.is_agv:
            self.endpoint = protocol.AgvEndpoint(agent_id, config.request_timeout, self._next_seq)
        else:
            self.endpoint = protocol.PickerEndpoint(agent_id, config.request_timeout, self._next_seq)
        self._assigned = False  # on board: the picker has a mission (latest tick)
        # what this robot knows of the others: its latest fleet broadcast, with its age (services/protocol)
        self.fleet = protocol.FleetView()
        self._fleet_arrived = -1  # the newest tick whose fleet broadcast physically arrived (delivered, held, lost)
        self._onboard: OnBoard | None = None  # this tick's on-board state, its decision point not yet taken
        # AGV: replies that physically arrived, per picker decision step, and a decision point waiting for them
        self._reply_arrivals: dict[int, int] = {}  # step the picker decided at -> replies arrived
        self._reply_base = (0, 0)  # (step of the outstanding request, replies announced to this AGV before it)
        self._holding = False  # picker: the request arriving right now is about to be held by the fault layer
        self._replies_seen: set[tuple[str, int]] = set()
        self._refusal_key = self.keys.refusal(agent_id)
        # refusals to this robot that physically arrived, per boundary tick they were sent at, since the base: (the
        # tick of the last decision point that had them all, the sim's count then); None before the first one
        self._refusal_arrivals: dict[int, int] = {}
        self._refusal_base: tuple[int, int] | None = None
        self._refusals_seen: set[tuple[str, int]] = set()
        # (tick, refusals sent to this robot by then) of the newest on-board state that arrived, acted on or not: a
        # picker that skipped its tick still decides at that tick's Resolve, with the refusals it announced
        self._announced: tuple[int, int] | None = None

    def _reject(self, what: str, why: object) -> None:
        self._rejects.count(what, why)
        self.counters.rejected = self._rejects.total

    # -- lifecycle -----------------------------------------------------------------------------------------------------
    async def run(self) -> AgentCounters:
        k, bus = self.keys, self.bus
        self._loop = asyncio.get_running_loop()
        if self.faults is not None:
            layer = self.faults.attach(bus, meter=False, receiver=self.id)  # stamps sim time if virtual
            layer.on_fate = self._on_arrival
            self._layer = layer
            await self.faults.start()  # ctl/faults, and the schedule from time 0
        restored = await self._restore()
        # inline: the lock-step hot path skips the hop to the loop (3-4x the tick rate over Zenoh, docs/services.md)
        await bus.subscribe(k.fleet, self._on_fleet, inline=True)
        await bus.subscribe(k.onboard(self.id), self._on_onboard, inline=True)
        await bus.subscribe(k.event("sim"), self._on_probe)
        await bus.subscribe(k.stop, self._on_stop)
        if not self.is_agv:
            await bus.subscribe(k.resolve, self._on_resolve, inline=True)
            await bus.subscribe(k.requests_to(self.id), self._on_request, inline=True)
        else:
            await bus.subscribe(k.replies_to(self.id), self._on_reply, inline=True)
        await bus.subscribe(k.refusal(self.id), self._on_refusal, inline=True)
        # the token last: once the sim sees it, the subscriptions above are declared
        token = await bus.declare_token(k.alive(self.id))
        if restored is not None:  # published once the session is established, so the record does not miss it
            await bus.publish(k.event(self.id), restored)
        await self._stop.wait()
        for timer in (self._pending_timer, self._stop_timer):
            if timer is not None:
                timer.cancel()
        await token.close()
        return self.counters

    async def _restore(self) -> Event | None:
        """Load the monitor's latest states into the brain; the event to publish: ``agent.restored`` (with the tick),
        or ``agent.cold_start`` (with the reason) when the run is under way and this agent starts from zero."""
        from services.faults.restore import fetch_states, restore_brains

        def cold(reason: str) -> Event:
            log.warning("agent %d: starts cold: %s", self.id, reason)
            return Event(kind="agent.cold_start", source=self.id, details={"reason": reason})

        started = time.monotonic()
        try:
            # the monitor answers at once (its queries do not queue behind its samples); the timeout only matters
            # when no monitor is there
            states = await fetch_states(self.bus, self.config.run_id, timeout=RESTORE_TIMEOUT)
        except Exception as exc:
            self._reject("state/agent", f"restore failed: {exc}")
            return cold(f"restore failed: {exc}")
        under_way = bool(states)  # the monitor holds states: the run has started, this is a restart
        if not self.restore:
            return cold("cold restart requested") if under_way else None
        if not states:
            if time.monotonic() - started >= RESTORE_TIMEOUT:
                return cold(f"no answer from the monitor's state within {RESTORE_TIMEOUT:.0f} s")
            return None  # a first start: nothing recorded yet
        try:
            restored = restore_brains(self.brains, self.id, states)
            self.restored_from = states.get(self.id)
        except Exception as exc:  # a failed restore is a cold start, never a crash
            self._reject("state/agent", f"restore failed: {exc}")
            return cold(f"restore failed: {exc}")
        if restored is None:
            return cold("the monitor holds no state of this agent")
        log.info("agent %d: restored state of tick %d", self.id, restored)
        return Event(
            kind="agent.restored", source=self.id, t=restored,
            # the row the brain holds now (read back from it, not copied from the state): the record can show that a
            # restarted agent resumed with the W row last published 
            details={"from_t": restored, "w_row": self.state_message(restored).w_row})

    def stop(self) -> None:
        self._stop.set()

    def _on_stop(self, sample: Sample) -> None:
        try:
            sample.decode(Stop)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if sample.sender == "sim":
            self._stop.set()
        elif self._stop_timer is None:
            # someone else's stop: the sim ends the run (final tick, then its own stop); leave anyway if it cannot
            self._stop_timer = asyncio.get_running_loop().call_later(STOP_GRACE, self._stop.set)

    async def _on_probe(self, sample: Sample) -> None:
        if self._stop.is_set():
            return  # a stopped agent is gone, even while its session closes
        try:
            msg = sample.decode(Event)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if msg.kind == "ready.probe":
            await self.bus.publish(self.keys.event(self.id), Event(
                kind="ready.ack", source=self.id, details={"round": msg.details.get("round", 0), "role": self.role}))

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    # -- virtual time ----------------------------------------------------------------------------------------------
    def _on_arrival(self, sample: Sample, fate: list[float]) -> None:
        """Fault layer hook: a sample physically arrived (any thread, under the runtime's lock, before it is
        delivered, dropped or held). The sim's on-board state, fleet broadcast and Resolve carry its boundary: reach
        it first (releasing what is due by then, applying the schedule). An on-board state or Resolve that will not
        be delivered now cannot be answered in its phase: skip it at once, so the sim never waits on a wall timeout.
        A fleet broadcast, reply or request that will not be delivered now has arrived all the same: the decision
        point does not wait for it. (Wall time: a delayed fleet broadcast is not waited for either — a robot acts on
        the view it has; a delayed reply or request comes after a real sleep and is answered then.)"""
        k = self.keys
        key = sample.key
        if self._virtual:
            missed = not self._layer.delivers_now(sample, fate)
        else:
            missed = not fate
        onboard = key == self._onboard_key
        if onboard or key == k.fleet or key == k.resolve:
            if sample.sender != "sim":
                return  # only the sim's own samples carry its boundary (not a stray publisher's, nor a fuzzer's)
            if self._virtual:
                at = self._layer.sent_at(sample)
                if at > self.faults.now():  # a tick's on-board state and fleet broadcast share their boundary
                    self.faults.advance(at)
            elif onboard:
                self._advance_wall(sample)
            if key == k.fleet:
                if missed or (not self._virtual and min(fate) > 0.0):
                    t = self._tick_of(sample)
                    if t is not None:
                        with self._lock:
                            self._fleet_seen(t)
                return
            if not missed or self._stop.is_set():
                return
            try:
                if onboard:
                    ob = sample.decode(OnBoard)
                    t, phase = ob.t, Phase.TICK
                    if t <= self.last_t:
                        return
                    with self._lock:
                        self._announce(ob)
                else:
                    msg = sample.decode(Resolve)
                    if not msg.expected(self.id):
                        return
                    t, phase = msg.t, Phase.RESOLVE
            except ValueError:
                return  # the handler rejects it if it is ever delivered
            self.faults.skip(self.bus, self.id, t, phase)
        elif missed and key == self._refusal_key:
            if sample.sender != "sim":
                return
            try:
                msg = sample.decode(Refusal)
            except ValueError:
                return
            if self.id in (msg.agv, msg.picker):
                with self._lock:
                    self._count_refusal(sample, msg.t)
        elif missed and self.is_agv and "/reply/" in key:
            try:
                msg = sample.decode(HelpReply)
            except ValueError:
                return
            if msg.agv == self.id:
                with self._lock:
                    self._count_reply(sample, msg.t)
        elif missed and not self.is_agv and "/request/" in key:
            try:
                msg = sample.decode(HelpRequest)
            except ValueError:
                return
            if msg.picker != self.id:
                return
            with self._lock:
                self._arrived.setdefault(msg.t, set()).add(msg.agv)
                # this hook runs before the fault layer holds the sample: a decision taken now must count it as held
                self._holding = bool(fate)
                try:
                    self._try_decide()
                finally:
                    self._holding = False

    def _tick_of(self, sample: Sample) -> int | None:
        """The tick number of a fleet broadcast, without validating the rest (its handler does that)."""
        try:
            t = tick_number(sample.payload)
        except ValueError:
            return None
        if t > self.config.steps or (
                self.last_t >= 0 and t > self.last_t + self._ticks.max_gap):
            return None
        return t

    def _advance_wall(self, sample: Sample) -> None:
        """Wall time: the on-board state still marks its tick's start, where scheduled and ``at_tick`` commands apply (sim
        stamps are wall clock here, so the tick number is read off the message itself)."""
        try:
            t = unpack_envelope(sample.payload)[1].get("t")
        except ValueError:
            return
        if type(t) is int and t >= 0:
            self.faults.advance(t * self.config.dt)

    def _came_late(self, sample: Sample) -> bool:
        """Virtual time: an on-board state or Resolve released at a later boundary than it was sent at (it was held): this agent
        has skipped that phase already, so the protocol drops it as stale."""
        return self._virtual and sample.sent_at < self.faults.now() - 1e-9

    # -- tick: the fleet broadcast and the on-board state -----------------------------------------------------------
    def _on_fleet(self, sample: Sample) -> None:
        """The fleet broadcast (a network message, maybe late): it becomes this robot's view if newer."""
        if self._stop.is_set():
            return  # a stopped agent is gone, even while its session closes
        try:
            _check_from_sim(sample, "fleet state")
            tick = decode_tick(sample.payload)  # validated, straight into arrays (schemas/tick.py)
            if tick.n != self.config.n_agents:
                raise ValueError(f"fleet state has {tick.n} robots, this fleet {self.config.n_agents}")
            if not 0 <= tick.t <= self.config.steps:
                raise ValueError(f"fleet state of tick t={tick.t} outside 0..{self.config.steps} (steps)")
            if self.last_t >= 0 and tick.t > self.last_t + self._ticks.max_gap:
                # kept, a forged far-future view would hide every real one after it
                raise ValueError(f"fleet state of tick {tick.t}, this robot is at tick {self.last_t}")
            obs = observation_from_arrays(tick, self.config.steps)
        except (ValueError, IndexError) as exc:
            self._reject(sample.key, exc)
            return
        with self._lock:
            self.fleet.update(obs, tick.t * self.config.dt)  # an older copy arriving after a newer one is ignored
            self._fleet_seen(tick.t)

    def _fleet_seen(self, t: int) -> None:
        """The fleet broadcast of tick ``t`` has arrived (with ``_lock`` held): a decision point waiting for it goes."""
        if t > self._fleet_arrived:
            self._fleet_arrived = t
            self._try_act()

    def _on_onboard(self, sample: Sample) -> None:
        """This robot's own state at the start of a tick: its decision point, once what it waits for has arrived."""
        if self._stop.is_set() or self._came_late(sample):
            return  # a stopped agent is gone, even while its session closes
        try:
            _check_from_sim(sample, "on-board state")
            msg = sample.decode(OnBoard)
            if msg.robot != self.id:
                raise ValueError(f"on-board state of robot {msg.robot} on the key of {self.id}")
            if not self._ticks.admit(msg.t):
                return  # a duplicate or stale tick: each tick is acted on once
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        self.last_t = msg.t
        self.counters.ticks += 1
        with self._lock:
            self._announce(msg)
            self._onboard = msg
            self._try_act()

    def _try_act(self) -> None:
        """Take this tick's decision point once the fleet broadcast sent with its on-board state has arrived and, for
        an AGV with a request outstanding, every reply announced to it (with ``_lock`` held). Both travel other
        paths than the on-board state: waiting for their arrival (not their delivery) makes what the robot knows at
        its decision point independent of wall-clock races, while a late or lost one is still late or lost."""
        ob = self._onboard
        if ob is None or self._fleet_arrived < ob.t:
            return
        final = ob.final or ob.t >= self.config.steps
        lockstep = self.config.mode == "lockstep"
        if self.is_agv and not final and lockstep and self.endpoint.outstanding is not None \
                and self._replies_owed(ob.replied) > 0:
            return  # (paced: a real-time robot acts on what it has; an answer on its way counts when it arrives)
        if lockstep and self._refusals_owed() > 0:
            return
        self._onboard = None
        self._act(ob, final)

    def _replies_owed(self, announced: int) -> int:
        """Replies sent to this AGV since its request (the sim's cumulative count minus the count when it asked) that
        have not physically arrived yet; with ``_lock`` held."""
        since, base = self._reply_base
        arrived = sum(n for t, n in self._reply_arrivals.items() if t >= since)
        return announced - base - arrived

    def _announce(self, ob: OnBoard) -> None:
        """An on-board state arrived (delivered, or skipped by the fault layer); with ``_lock`` held."""
        if self._announced is None or ob.t > self._announced[0]:
            self._announced = (ob.t, ob.refused)

    def _refusals_owed(self) -> int:
        """Refusals the sim sent to this robot by the tick of its newest on-board state (each at a step boundary,
        before that tick's on-board state) that have not physically arrived yet; with ``_lock`` held. Those sent
        before this process's first on-board state are not waited for: a restarted robot's predecessor had them.
        Once none is owed, what arrived up to that tick becomes the base."""
        if self._announced is None:
            return 0
        upto, announced = self._announced
        since, count = self._refusal_base if self._refusal_base is not None else self._announced
        arrived = sum(n for t, n in self._refusal_arrivals.items() if since < t <= upto)
        owed = announced - count - arrived
        if owed <= 0:
            self._refusal_base = self._announced
            self._refusal_arrivals = {t: n for t, n in self._refusal_arrivals.items() if t > upto}
        return owed

    def _count_refusal(self, sample: Sample, t: int) -> None:
        """A refusal to this robot, sent at the boundary that starts tick ``t``, physically arrived."""
        self._note_arrival(sample, t, self._refusals_seen, self._refusal_arrivals)

    def _count_reply(self, sample: Sample, t: int) -> None:
        """A reply to this AGV, decided at step ``t``, physically arrived."""
        self._note_arrival(sample, t, self._replies_seen, self._reply_arrivals)

    def _note_arrival(self, sample: Sample, t: int, seen: set[tuple[str, int]], arrivals: dict[int, int]) -> None:
        """Count one arrival of ``sample`` (once per copy sent, whatever the network did to it) under its step ``t``;
        with ``_lock`` held. Resumes a decision point waiting for it."""
        key = (sample.sender, sample.seq)
        if key in seen:
            return
        seen.add(key)
        arrivals[t] = arrivals.get(t, 0) + 1
        self._try_act()
        self._try_decide()

    def _act(self, ob: OnBoard, final: bool) -> None:
        """This robot's decision point of step t (with ``_lock`` held): learn from a new fleet view, then, as an
        AGV, gate and request from that view and its own on-board state; then the ack."""
        asked: list[int] = []
        t = ob.t
        now = t * self.config.dt  # this robot's decision point of step t
        view = self.fleet.take_new()
        if view is not None and not (view.final and self.brains.memoryless):
            # the final view only reports the last step: a memoryless brain has nothing to learn from it
            self.brains.learn(view)
        age = self.fleet.age(now)
        with self._lock:
            if not self.is_agv and t > 0:
                # the decision point of step t−1 (again, if requests were decided there: idempotent): a commitment in
                # flight ends there (refused, took effect, expired) with what the picker knew then, requests or not
                self.endpoint.check_pending((t - 1) * self.config.dt + self.config.dt / 2, self._assigned,
                                            self.outcomes)
            # what became of this robot's dispatch messages by this boundary, for the record (on the ack)
            counts = self.outcomes.counts()
        if not self.is_agv:
            self._assigned = not ob.free
        elif not final:
            may_ask = self.endpoint.may_ask(now, ob.needs_picker, self.outcomes)
            if may_ask and self.fleet.view is not None:  # no fleet view yet: nothing to choose a picker from
                cell, target = (ob.x, ob.y), (ob.target_x, ob.target_y)
                g = protocol.gate(self.brains, self.id, protocol.with_own_state(self.fleet.view, self.id, cell, target))
                if g.ask:
                    reqs = [self.endpoint.request(p, target, now, self.outcomes) for p in g.targets]
                    self._reply_base = (t, ob.replied)
                    self._reply_arrivals = {s: n for s, n in self._reply_arrivals.items() if s >= t}
                    for req in reqs:  # one (a broadcasting policy: one per free picker it knows of)
                        tx, ty = req.cell
                        self.bus.put(self.keys.request(self.id, req.picker), encode_fields(
                            HelpRequest, t=t, agv=self.id, picker=req.picker, target_x=tx, target_y=ty,
                            mission=ob.mission, seq=req.seq))
                        self.counters.requests += 1
                        asked.append(req.picker)
        eta = float(self.brains.state.eta) if isinstance(self.brains, MorphBrains) else None
        publish_state = t % self.config.state_every == 0 or final
        # encoded from plain values (no model round trip: the hot path, codec.encode_fields)
        ack = encode_fields(Ack, t=t, agent=self.id, phase=int(Phase.TICK), requests_sent=asked,
                            seq=self._next_seq(), links=self.brains.out_links(self.id), eta=eta,
                            view_age=None if age == float("inf") else float(age), outcomes=counts)
        if final:
            # Before the ack, on the same link: the last state must reach the monitor before the run ends.
            self.bus.put(self._state_key, self.state_message(t))
            publish_state = False
        self.bus.put(self._ack_key, ack)  # the ack first: it is on the sim's critical path
        if publish_state:
            # still before this agent's ack of t+1, hence before tick t+2, when the monitor closes row t
            self.bus.put(self._state_key, self.state_message(t))

    def state_message(self, t: int) -> AgentState:
        b = self.brains
        w = b.weight_rows()[0]
        a = b.link_rows()[0]
        n = len(w)
        theta = np.zeros(n)
        age = np.zeros(n, dtype=int)
        h = eta = d_hat = 0.0
        if isinstance(b, MorphBrains):
            s = b.state
            if b.preset == "reference":
                theta, age = s.theta_bcm[0, self.id], s.age[0, self.id]
            else:
                theta, age = s.theta_bcm[0], s.age[0]
            h, eta, d_hat = float(b.h()[0]), float(s.eta), float(s.dhat)
        return AgentState(
            agent=self.id, role=self.role, t=t, w_row=[float(v) for v in w], a_row=[bool(v) for v in a],
            theta_row=[float(v) for v in theta], age_row=[int(v) for v in age], h=h, eta=eta, d_hat=d_hat,
            seq=self._next_seq())

    # -- AGV side --------------------------------------------------------------------------------------------------------
    def _on_reply(self, sample: Sample) -> None:
        try:
            msg = sample.decode(HelpReply)
            self.keys.check_author(sample.key, msg.picker, "reply of picker")
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if msg.agv != self.id:
            self._reject(sample.key, f"reply addressed to AGV {msg.agv}")
            return
        with self._lock:  # takes effect at once: it only frees the AGV to ask again at its next decision point
            self.endpoint.receive(protocol.Reply(msg.picker, msg.agv, msg.accepted, msg.t * self.config.dt,
                                                 msg.request_seq), self.outcomes)
            self._count_reply(sample, msg.t)

    def _on_refusal(self, sample: Sample) -> None:
        try:
            msg = sample.decode(Refusal)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if sample.sender != "sim" or self.id not in (msg.agv, msg.picker):
            self._reject(sample.key, f"refusal of {msg.picker}->{msg.agv} from {sample.sender!r}")
            return
        refusal = protocol.Refusal(msg.picker, msg.agv, msg.t * self.config.dt, msg.commit_seq)
        with self._lock:
            if self.is_agv:
                self.endpoint.receive(refusal, self.outcomes)
            else:
                self.endpoint.receive(refusal, self._due(sample, msg.t * self.config.dt), self.outcomes)
            self._count_refusal(sample, msg.t)  # after it took effect: a decision point waiting for it goes now

    def _due(self, sample: Sample, sent: float) -> float:
        """A protocol message's delivery time, sim seconds: the fault layer's (send time + latency, continuous), or
        its send time when nothing delayed it."""
        return sample.due if sample.due >= 0.0 else sent

    # -- picker side -----------------------------------------------------------------------------------------------------
    def _on_request(self, sample: Sample) -> None:
        if self._stop.is_set():
            return  # a stopped agent is gone, even while its session closes
        try:
            msg = sample.decode(HelpRequest)
            sender = self.keys.sender_of(sample.key)
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if msg.picker != self.id or sender != msg.agv:
            self._reject(sample.key, f"request {msg.agv}->{msg.picker} on key of {sender}")
            return
        if self.last_t >= 0 and msg.t > self.last_t + self._ticks.max_gap:  # a request for a far future tick is
            # forged or corrupt: kept, it would wait forever
            self._reject(sample.key, f"request for tick {msg.t}, this picker is at tick {self.last_t}")
            return
        # never dropped for being late: it waits in the endpoint's inbox for this picker's next decision point
        req = protocol.Request(msg.agv, msg.picker, (msg.target_x, msg.target_y), msg.t * self.config.dt, msg.seq)
        with self._lock:
            self.endpoint.receive(req, self._due(sample, req.sent_at), self.outcomes)
            self._inbox.setdefault(msg.t, {})[msg.agv] = msg
            self._try_decide()

    def _on_resolve(self, sample: Sample) -> None:
        if self._stop.is_set() or self._came_late(sample):
            return  # a stopped agent is gone, even while its session closes
        try:
            _check_from_sim(sample, "resolve")
            msg = sample.decode(Resolve)
            if self.last_t >= 0 and msg.t > self.last_t + self._ticks.max_gap:  # of the tick just taken (or of one
                # lost on the way)
                raise ValueError(f"resolve of tick {msg.t}, this picker is at tick {self.last_t}")
        except ValueError as exc:
            self._reject(sample.key, exc)
            return
        if self.id not in msg.pickers or msg.t < self.last_t or msg.t <= self._resolved_t:
            return
        expected = msg.expected(self.id)
        with self._lock:
            self._pending = (msg.t, expected)
            self._try_decide()
            if self._pending is not None:
                # Lockstep: wait for every expected request; past the deadline decide over those that arrived.
                wait = self.config.phase_timeout if self.config.mode == "lockstep" else 0.4 * self.config.period
                assert self._loop is not None
                self._loop.call_soon_threadsafe(self._arm_deadline, msg.t, wait)

    def _arm_deadline(self, t: int, wait: float) -> None:  # on the loop
        with self._lock:
            if self._pending is None or self._pending[0] != t:
                return  # decided already
            if self._pending_timer is not None:
                self._pending_timer.cancel()
            self._pending_timer = self._loop.call_later(wait, self._decide_now, t)

    def _try_decide(self) -> None:
        if self._pending is None:
            return
        t, expected = self._pending
        if self.config.mode == "lockstep" and self._refusals_owed() > 0:
            return  # a refusal announced by this tick's on-board state is on its way: it may end the commitment
        got = self._inbox.get(t, {})
        # with faults: decide once every expected request has *arrived* — delivered by the resolve boundary (in got),
        # or dropped / held past it (in _arrived, virtual time: the same set whatever the wall order of arrivals)
        lost = self._arrived.get(t, ())
        if all(a in got or a in lost for a in expected):
            self._decide()

    def _decide_now(self, t: int) -> None:  # on the loop, at the resolve's deadline
        with self._lock:
            self._pending_timer = None
            if self._pending is not None and self._pending[0] == t:
                self._decide()

    def _decide(self) -> None:
        assert self._pending is not None
        t, expected = self._pending
        self._pending = None
        self._resolved_t = t
        timer, self._pending_timer = self._pending_timer, None
        if timer is not None:
            self._loop.call_soon_threadsafe(timer.cancel)  # TimerHandle.cancel is not thread-safe
        for old in [s for s in self._inbox if s <= t]:
            del self._inbox[old]
        for old in [s for s in self._arrived if s <= t]:
            del self._arrived[old]
        now = t * self.config.dt + self.config.dt / 2  # the picker's decision point of step t
        view = self.fleet.view  # the mission order as this picker last heard it (the tie-break)
        rank = {int(a): i for i, a in enumerate(view.request_order)} if view is not None else {}
        commit, replies = self.endpoint.decide(now, self._assigned, rank, self.outcomes)
        # requests delivered later, or still held by the network, need this picker's next decision point too
        held = self._virtual and (self.faults.vtime.pending > 0 or self._holding)
        self._answer(t, commit, replies, bool(self.endpoint.inbox) or held)

    def _answer(self, t: int, commit, replies, more: bool) -> None:
        k = self.keys
        if commit is not None:
            # the commitment (communication, faultable) before the ack that announces it (synchronisation)
            self.bus.put(k.commit(self.id), Commit(t=t, picker=self.id, agv=commit.agv, seq=commit.seq,
                                                   target_x=commit.cell[0], target_y=commit.cell[1]))
            self.counters.commits += 1
        for reply in replies:
            self.bus.put(k.reply(self.id, reply.agv), HelpReply(
                t=t, picker=self.id, agv=reply.agv, accepted=reply.accepted, request_seq=reply.request_seq,
                seq=self._next_seq()))
        self.bus.put(self._ack_key, Ack(t=t, agent=self.id, phase=Phase.RESOLVE, seq=self._next_seq(),
                                         committed_to=None if commit is None else commit.agv, more=more,
                                         replied_to=[r.agv for r in replies]))


async def run_agent(config: RunConfig, bus: Bus, agent_id: int) -> AgentCounters:
    return await AgentService(config, bus, agent_id).run()


__all__ = ["AgentCounters", "AgentService", "run_agent"]
