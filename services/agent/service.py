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

This module is the shell both roles share: the subscriptions and the run loop, the tick's decision point and the
refusals. What a decision point waits for is pure protocol code (:mod:`services.protocol.readiness`); the roles are
:class:`~services.agent.agv.AgvService` and :class:`~services.agent.picker.PickerService`
(:func:`services.agent.roles.make_agent` builds the one a robot id names); the crash restore is :mod:`services.agent.restore`, the fault layer's arrival hook
:mod:`services.agent.arrivals`.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from dataclasses import dataclass

from schemas import Ack, AgentState, Event, OnBoard, Phase, PolicyMessage, Refusal, Stop
from schemas.codec import encode_fields
from schemas.keys import RunKeys
from schemas.tick import decode_tick, observation_from_arrays
from services.agent.arrivals import ArrivalHook
from services.agent.restore import restore_state
from services.bus.base import Bus, Sample
from services.intake import Intake
from services.policies.coordinators import MorphBrains
from services.policies.interface import Fleet, state_message
from services.protocol import dispatch as protocol
from services.protocol.readiness import Readiness
from services.protocol.tickorder import TickOrder
from services.runconfig import RunConfig

log = logging.getLogger("morph_sim.agent")

STOP_GRACE = 3.0  # seconds an agent waits for the sim's end of run after someone else's stop


def check_from_sim(sample: Sample, what: str) -> None:
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
    """Agent ``agent_id`` of the run of ``config`` over ``bus``. ``await run()`` until stop.

    What both roles share; a robot's agent is an :class:`~services.agent.agv.AgvService` or a
    :class:`~services.agent.picker.PickerService` (:func:`services.agent.roles.make_agent`), each overriding the few
    steps where the roles differ (their subscriptions, what a decision point waits for and does, the refusal's
    effect)."""

    is_agv: bool
    role: str

    def __init__(self, config: RunConfig, bus: Bus, agent_id: int, *, restore: bool = True, faults=None):
        # this process's FaultRuntime (ingress faults on what this agent receives, its ctl/faults
        # controller, sim-time stamps); in virtual time it advances on every on-board state, fleet broadcast and
        # Resolve of the sim that arrives (services/agent/arrivals.py)
        self.faults = faults
        # restore: a (re)started agent loads its plasticity state from the monitor's latest states
        # (state/agent/*) before it joins; a first start finds none. restore=False is the cold restart.
        self.restore = restore
        self.restored_from: AgentState | None = None
        if not 0 <= agent_id < config.n_agents:
            raise ValueError(f"id: agent {agent_id} outside 0..{config.n_agents - 1} for this fleet")
        self.config = config
        self.bus = bus
        self.id = agent_id
        self.keys = RunKeys(config.run_id)
        self.intake = Intake(bus, self.keys, log, f"agent {agent_id}", on_refused=self._count_refused)
        self._ack_key, self._state_key = self.keys.ack(agent_id), self.keys.agent_state(agent_id)  # every tick
        fleet = Fleet(config.n_agvs, config.n_pickers, config.scale)
        self.brains = config.make_policy().brains(fleet, [agent_id], config.seed)
        self.counters = AgentCounters()
        self.last_t = -1
        self._ticks = TickOrder(config.steps)  # which ticks this agent takes (services/protocol/tickorder.py)
        self._stop = asyncio.Event()
        self._seq = 0
        self._stop_timer: asyncio.TimerHandle | None = None
        # The hot path (tick, request, resolve) runs inline on the transport's receive thread; the resolve deadline
        # fires on the loop. This lock keeps the readiness, the endpoint and a pending decision consistent between
        # the two.
        self._lock = threading.RLock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._virtual = faults is not None and faults.vtime is not None
        self._lockstep = config.mode == "lockstep"
        # the dispatch protocol's endpoint of this robot (services/protocol; set by the role), and what became of its
        # messages
        self.outcomes = protocol.Outcomes()
        # what this robot knows of the others: its latest fleet broadcast, with its age (services/protocol)
        self.fleet = protocol.FleetView()
        self.mailbox = protocol.Mailbox()  # policy messages delivered, until a decision point takes them
        # what its decision points still wait for (replies, refusals, the fleet broadcast, requests)
        self.readiness = Readiness(self._lockstep)
        self._onboard: OnBoard | None = None  # this tick's on-board state, its decision point not yet taken

    def _count_refused(self, total: int) -> None:
        self.counters.rejected = total

    # -- lifecycle -----------------------------------------------------------------------------------------------------
    async def run(self) -> AgentCounters:
        k, bus = self.keys, self.bus
        self._loop = asyncio.get_running_loop()
        if self.faults is not None:
            layer = self.faults.attach(bus, meter=False, receiver=self.id)  # stamps sim time if virtual
            layer.on_fate = ArrivalHook(self, layer)
            await self.faults.start()  # ctl/faults, and the schedule from time 0
        restored = await restore_state(self)
        # inline: the lock-step hot path skips the hop to the loop (3-4x the tick rate over Zenoh, docs/services.md)
        await bus.subscribe(k.fleet, self._on_fleet, inline=True)
        await bus.subscribe(k.onboard(self.id), self._on_onboard, inline=True)
        await bus.subscribe(k.event("sim"), self._on_probe)
        await bus.subscribe(k.stop, self._on_stop)
        await self._subscribe_role()
        await bus.subscribe(k.refusal(self.id), self._on_refusal, inline=True)
        await bus.subscribe(k.policies_to(self.id), self._on_mail, inline=True)
        await bus.subscribe(k.policies_to_all, self._on_mail, inline=True)
        # the token last: once the sim sees it, the subscriptions above are declared
        token = await bus.declare_token(k.alive(self.id))
        if restored is not None:  # published once the session is established, so the record does not miss it
            await bus.publish(k.event(self.id), restored)
        await self._stop.wait()
        self._cancel_timers()
        await token.close()
        return self.counters

    async def _subscribe_role(self) -> None:
        """Subscribe to the messages of this robot's role (an AGV's replies, a picker's Resolve and requests)."""
        raise NotImplementedError

    def _cancel_timers(self) -> None:
        if self._stop_timer is not None:
            self._stop_timer.cancel()

    def stop(self) -> None:
        self._stop.set()

    def _on_stop(self, sample: Sample) -> None:
        if self.intake.decode(sample, Stop) is None:
            return
        if sample.sender == "sim":
            self._stop.set()
        elif self._stop_timer is None:
            # someone else's stop: the sim ends the run (final tick, then its own stop); leave anyway if it cannot
            self._stop_timer = asyncio.get_running_loop().call_later(STOP_GRACE, self._stop.set)

    async def _on_probe(self, sample: Sample) -> None:
        if self._stop.is_set():
            return  # a stopped agent is gone, even while its session closes
        msg = self.intake.decode(sample, Event)
        if msg is None:
            return
        if msg.kind == "ready.probe":
            await self.bus.publish(self.keys.event(self.id), Event(
                kind="ready.ack", source=self.id, details={"round": msg.details.get("round", 0), "role": self.role}))

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _came_late(self, sample: Sample) -> bool:
        """Virtual time: an on-board state or Resolve released at a later boundary than it was sent at (it was held):
        this agent has skipped that phase already, so the protocol drops it as stale."""
        return self._virtual and sample.sent_at < self.faults.now() - 1e-9

    # -- tick: the fleet broadcast and the on-board state -----------------------------------------------------------
    def _on_fleet(self, sample: Sample) -> None:
        """The fleet broadcast (a network message, maybe late): it becomes this robot's view if newer."""
        if self._stop.is_set():
            return  # a stopped agent is gone, even while its session closes
        try:
            check_from_sim(sample, "fleet state")
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
            self.intake.refuse(sample.key, exc)
            return
        with self._lock:
            self.fleet.update(obs, tick.t * self.config.dt)  # an older copy arriving after a newer one is ignored
            self._fleet_seen(tick.t)

    def _fleet_seen(self, t: int) -> None:
        """The fleet broadcast of tick ``t`` has arrived (with ``_lock`` held): a decision point waiting for it goes."""
        if self.readiness.fleet(t):
            self._try_act()

    def _on_onboard(self, sample: Sample) -> None:
        """This robot's own state at the start of a tick: its decision point, once what it waits for has arrived."""
        if self._stop.is_set() or self._came_late(sample):
            return  # a stopped agent is gone, even while its session closes
        try:
            check_from_sim(sample, "on-board state")
            msg = sample.decode(OnBoard)
            if msg.robot != self.id:
                raise ValueError(f"on-board state of robot {msg.robot} on the key of {self.id}")
            if not self._ticks.admit(msg.t):
                return  # a duplicate or stale tick: each tick is acted on once
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return
        self.last_t = msg.t
        self.counters.ticks += 1
        with self._lock:
            self.readiness.announce(msg.t, msg.refused, msg.messaged)
            self._onboard = msg
            self._try_act()

    def _try_act(self) -> None:
        """Take this tick's decision point once the fleet broadcast sent with its on-board state has arrived and, for
        an AGV with a request outstanding, every reply announced to it, and every refusal announced (with ``_lock``
        held). They travel other paths than the on-board state: waiting for their arrival (not their delivery) makes
        what the robot knows at its decision point independent of wall-clock races, while a late or lost one is
        still late or lost. (Paced: a real-time robot acts on what it has; an answer on its way counts when it
        arrives.)"""
        ob = self._onboard
        if ob is None:
            return
        final = ob.final or ob.t >= self.config.steps
        if not self.readiness.may_act(ob.t, ob.replied, self._awaits_replies(final)):
            return
        self._onboard = None
        self._act(ob, final)

    def _awaits_replies(self, final: bool) -> bool:
        """Whether this tick's decision point waits for the replies announced to this robot (an AGV's request)."""
        return False

    def _resume(self) -> None:
        """Something a decision point may wait for arrived (with ``_lock`` held): take what is ready now."""
        self._try_act()

    def _act(self, ob: OnBoard, final: bool) -> None:
        """This robot's decision point of step t (with ``_lock`` held): learn from a new fleet view, then decide as
        its role does (an AGV gates and requests from that view and its own on-board state); then the ack."""
        t = ob.t
        now = t * self.config.dt  # this robot's decision point of step t
        view = self.fleet.take_new()
        if view is not None and not (view.final and self.brains.memoryless):
            # the final view only reports the last step: a memoryless brain has nothing to learn from it
            self.brains.learn(view)
        age = self.fleet.age(now)
        with self._lock:
            self._check_commitment(t)
            # what became of this robot's dispatch messages by this boundary, for the record (on the ack)
            counts = self.outcomes.counts()
            mail = self.mailbox.take(t, now)
        if mail:
            self.brains.receive(self.id, mail)
        asked = self._decide_on_board(ob, now, final)
        policy_to = self._send_mail(t)
        eta = self.brains.eta(self.id) if isinstance(self.brains, MorphBrains) else None
        publish_state = t % self.config.state_every == 0 or final
        # encoded from plain values (no model round trip: the hot path, codec.encode_fields)
        ack = encode_fields(Ack, t=t, agent=self.id, phase=int(Phase.TICK), requests_sent=asked,
                            seq=self._next_seq(), links=self.brains.out_links(self.id), eta=eta,
                            view_age=None if age == float("inf") else float(age), outcomes=counts,
                            **({"policy_to": policy_to} if policy_to else {}))
        if final:
            # Before the ack, on the same link: the last state must reach the monitor before the run ends.
            self.bus.put(self._state_key, self.state_message(t))
            publish_state = False
        self.bus.put(self._ack_key, ack)  # the ack first: it is on the sim's critical path
        if publish_state:
            # still before this agent's ack of t+1, hence before tick t+2, when the monitor closes row t
            self.bus.put(self._state_key, self.state_message(t))

    # -- policy messages ----------------------------------------------------------------------------------------------
    def _send_mail(self, t: int) -> list[int]:
        """Send what this robot's policy wrote since its last decision point; the receivers, for the ack (-1: all)."""
        out = self.brains.take_outbox(self.id)
        for to, data in out:
            self.bus.put(self.keys.policy(self.id, to), encode_fields(
                PolicyMessage, t=t, sender=self.id, to=to, pseq=self.mailbox.next_pseq(), data=data))
        return [-1 if to is None else to for to, _ in out]

    def _on_mail(self, sample: Sample) -> None:
        if self._stop.is_set():
            return
        msg = self.intake.decode(sample, PolicyMessage)
        if msg is None:
            return
        author = self.keys.sender_of(sample.key)
        if author != msg.sender or msg.sender == self.id or msg.to not in (None, self.id):
            self.intake.refuse(sample.key, f"policy message of {msg.sender} to {msg.to} on the key of {author}")
            return
        if self.last_t >= 0 and msg.t > self.last_t + self._ticks.max_gap:
            self.intake.refuse(sample.key, f"policy message of tick {msg.t}, this robot is at tick {self.last_t}")
            return
        with self._lock:
            try:
                self.mailbox.receive(msg, self._due(sample, msg.t * self.config.dt))
            except ValueError as exc:
                self.intake.refuse(sample.key, exc)
            # arrived, kept or not: the decision point that waits for it goes
            if self.readiness.message(sample.sender, sample.seq, msg.t):
                self._resume()

    def mail_missed(self, sample: Sample) -> None:
        """A policy message to this robot arrived and the fault layer will not deliver it now (dropped or held): it
        has arrived all the same (with the runtime's lock held, not ours)."""
        try:
            msg = sample.decode(PolicyMessage)
        except ValueError:
            return
        if msg.to in (None, self.id) and msg.sender != self.id:
            with self._lock:
                if self.readiness.message(sample.sender, sample.seq, msg.t):
                    self._resume()

    def _check_commitment(self, t: int) -> None:
        """At the decision point of tick ``t``, before the outcomes are counted (with ``_lock`` held): a picker's
        commitment in flight may end there."""

    def _decide_on_board(self, ob: OnBoard, now: float, final: bool) -> list[int]:
        """The role's decision from its on-board state at ``now``; the pickers it sent requests to."""
        raise NotImplementedError

    def state_message(self, t: int) -> AgentState:
        return state_message(self.brains, self.id, self.role, t, self._next_seq())

    # -- refusals (both roles) -------------------------------------------------------------------------------------
    def _on_refusal(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, Refusal)
        if msg is None:
            return
        if sample.sender != "sim" or self.id not in (msg.agv, msg.picker):
            self.intake.refuse(sample.key, f"refusal of {msg.picker}->{msg.agv} from {sample.sender!r}")
            return
        refusal = protocol.Refusal(msg.picker, msg.agv, msg.t * self.config.dt, msg.commit_seq)
        with self._lock:
            self._receive_refusal(refusal, sample)
            self.count_refusal(sample, msg.t)  # after it took effect: a decision point waiting for it goes now

    def _receive_refusal(self, refusal: protocol.Refusal, sample: Sample) -> None:
        """The refusal takes effect on this robot's endpoint (with ``_lock`` held)."""
        raise NotImplementedError

    def count_refusal(self, sample: Sample, t: int) -> None:
        """A refusal to this robot, sent at the boundary that starts tick ``t``, physically arrived (with ``_lock``
        held): counted once per copy sent, whatever the network did to it."""
        if self.readiness.refusal(sample.sender, sample.seq, t):
            self._resume()

    def missed(self, sample: Sample, fate: list[float]) -> None:
        """A dispatch message of this robot's role arrived and the fault layer will not deliver it now (dropped or
        held): it has arrived all the same (services/agent/arrivals.py)."""

    def _due(self, sample: Sample, sent: float) -> float:
        """A protocol message's delivery time, sim seconds: the fault layer's (send time + latency, continuous), or
        its send time when nothing delayed it."""
        return sample.due if sample.due >= 0.0 else sent


__all__ = ["AgentCounters", "AgentService"]
