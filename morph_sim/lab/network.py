"""The lab's in-process discrete-event network and its driver of the dispatch protocol (services/protocol).

:class:`EventNetwork` carries protocol messages between the robots and the sim: each message's fate (delays, loss,
duplicate) comes from the fault layer's per-link decision (:meth:`FaultLayer.fate`, the one fault interface), and a
message sent at sim time ``s`` with delay ``L`` is delivered at ``s + L`` exactly, never dropped for being late. A
network profile (services/faults/network.py) sits under the fault specs exactly as in the services: the same
:class:`FaultLayer` judges the radio legs first, with the same message identities (publisher, per-(publisher, key)
sequence number), so every draw is the one the services' processes make, and the robots' positions reach the model
from every Tick as they do there.

:class:`LabDispatch` runs one step of the protocol on the pure core: the AGVs' gates at ``t·Δ``, the pickers'
decisions at ``t·Δ + Δ/2``, the sim's commitments at ``(t+1)·Δ`` (services.protocol.dispatch.decision_points).
When a fault can touch the fleet broadcast (``sim/fleet``), every agent has its own brain and learns and gates from its
own latest view of the fleet; otherwise one brain owns the whole team (identical results, vectorised).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from schemas.codec import encode
from schemas.faults import FaultSpec
from schemas.keys import FLEET, RunKeys, matches
from schemas.messages import PolicyMessage
from schemas.tick import TickObservation
from services.faults.air import (
    dispatch_size,
    fleet_size,
    has_shared_capacity,
    instant,
    publisher_rank,
    receiver_rank,
)
from services.faults.layer import FaultLayer
from services.faults.network import NetworkModel
from services.policies.interface import policy_choice
from services.protocol.dispatch import (
    EPS,
    Commitment,
    Endpoints,
    FleetView,
    Mailbox,
    Refusal,
    Reply,
    Request,
    decision_points,
    gate,
    view_age_stats,
    with_own_state,
)

RUN = "lab"
#: the fleet broadcast's key (relative to morph/<run>/), the services' own (schemas.keys)
FLEET_KEY = FLEET
#: the dispatch protocol's keys (relative to morph/<run>/), the scope of "faults on dispatch messages"
DISPATCH_KEYS = ("agent/*/request/*", "agent/*/reply/*", "agent/*/commit", "sim/refusal/*")
#: a policy's own messages (bids, claims, consensus rounds): the same radio, scoped apart from the dispatch protocol
POLICY_KEYS = "agent/*/policy/*"


@dataclass
class DispatchStats:
    decisions: int = 0  # gate evaluations (a request that reached a candidate)
    dispatched: int = 0
    requests: int = 0  # help requests sent: one per dispatch, one per picker asked by a broadcasting policy
    p_sum: float = 0.0
    w_positive: int = 0  # decisions where the gate was above its floor
    divergent_ticks: int = 0  # ticks where the other dispatch mode would have committed differently

    def count(self, ask: bool, p: float, requests: int | None = None) -> None:
        self.decisions += 1
        self.dispatched += int(ask)
        self.requests += int(ask) if requests is None else requests
        self.p_sum += p
        self.w_positive += int(p > 0.25 + 1e-12)


@dataclass(frozen=True, slots=True)
class FleetBroadcast:
    """The sim's fleet state of one tick, as one agent receives it."""

    view: TickObservation
    stamp: float


@dataclass
class NetworkStats:
    sent: int = 0  # dispatch messages sent (request, reply, commitment, refusal)
    broadcasts: int = 0  # fleet-state copies sent through the network (one per receiver)
    delivered: int = 0  # copies delivered (a duplicate counts twice)
    dropped: int = 0
    delay_sum: float = 0.0  # over delivered copies, sim seconds
    bytes: int = 0  # wire bytes sent (each message's encoded size, schemas.codec)


def wire_size(msg) -> int:
    """Bytes of a protocol message on the radio (services.faults.air.dispatch_size: one definition for every
    driver)."""
    if isinstance(msg, Request):
        return dispatch_size("request")
    if isinstance(msg, Reply):
        return dispatch_size("reply")
    return dispatch_size("refusal" if isinstance(msg, Refusal) else "commit")


class EventNetwork:
    """Messages in flight, delivered in (delivery time, send order). ``faults``: fault specs (schemas.faults) with
    their scopes; ``model``: the run's radio network (a network profile's :class:`NetworkModel`); neither = a perfect
    network."""

    def __init__(self, faults: Sequence[FaultSpec] = (), *, seed: int = 0, run: str = RUN,
                 model: NetworkModel | None = None):
        self.keys = RunKeys(run)
        self.now = 0.0
        self.layer: FaultLayer | None = None
        self.model = model
        if faults or model is not None:
            # one random stream per (fault, link, key), as every service process draws them: the same faults
            # give the lab and the services the same fates, message for message
            self.layer = FaultLayer(run, base_seed=seed, clock=lambda: self.now, per_key=True)
            self.layer.network = model
            for spec in faults:
                if spec.rate is not None:  # the shared air's airtime, from the start: the model's own queues
                    if model is None or not model.has_ap_budget:
                        raise ValueError("rate: an airtime fault needs a network profile whose access points have "
                                         "an airtime budget (ap_rate, ap_uplink_rate, ap_downlink_rate)")
                    model.set_airtime(spec.rate.rate, spec.rate.limit, 0.0, spec.duration, spec.id)
                    continue
                self.layer.set(spec, at=0.0)
        self.faults = tuple(faults)
        self._heap: list[tuple[float, int, object, object]] = []
        self._order = itertools.count()
        # a message's identity is (publisher, sequence number per (publisher, key)), numbered from 0 as a bus does
        # (services/bus/base.py): the network model's draws are a function of it
        self._seqs: dict[str, itertools.count] = {}
        self.stats = NetworkStats()
        # A profile with shared capacity (rate-limited queues) judges the messages of an instant in one order, the
        # medium's (services/faults/air.py: send time, publisher, key, sequence number, receiver), whatever order the
        # lab happens to send them in: they wait here until the next delivery.
        self.shared_air = model is not None and has_shared_capacity(model.profile)
        self._unjudged: list[tuple[tuple, str, object, object, object, float, int, int]] = []

    def touches(self, rel_key: str) -> bool:
        """Whether some fault's scope, or the radio network, can apply to messages on ``rel_key``."""
        return self.model is not None or any(matches(f.scope.key_expr, rel_key) for f in self.faults)

    def observe(self, obs: TickObservation, dt: float) -> list:
        """The sim's Tick of ``obs`` goes out: the radio model learns where the robots are (from ``(t+1)·Δ`` on, as
        every process of the services does with every Tick); returns the hand-overs it caused."""
        if self.model is None:
            return []
        return self.model.observe_tick(obs.t, dt, obs.cells.tolist())

    def next_seq(self, key: str) -> int:
        """The next sequence number on ``key`` (one publication's, when it reaches several receivers)."""
        counter = self._seqs.get(key)
        if counter is None:
            counter = self._seqs[key] = itertools.count()
        return next(counter)

    def send(self, key: str, sender, receiver, msg, at: float, *, seq: int | None = None, size: int | None = None,
             count: bool = True) -> None:
        """Send ``msg`` from ``sender`` to ``receiver`` on ``key`` at sim time ``at``. ``seq``: the message's sequence
        number when one publication reaches several receivers (a Tick: its t); default the next on (sender, key).
        ``size``: bytes on the wire (default: the protocol message's encoded size)."""
        if seq is None:
            seq = self.next_seq(key)
        if isinstance(msg, FleetBroadcast):
            self.stats.broadcasts += 1
            size = size or 0
        else:
            size = wire_size(msg) if size is None else size
            if count:  # one publication to several receivers counts once, as a bus sends it once
                self.stats.sent += 1
                self.stats.bytes += size
        if self.shared_air:
            order = (instant(at), publisher_rank(sender), self.keys.local(key), seq, receiver_rank(receiver))
            self._unjudged.append((order, key, sender, receiver, msg, at, seq, size))
            return
        self._judge(key, sender, receiver, msg, at, seq, size)

    def broadcast(self, key: str, sender, receivers: Sequence, msg: FleetBroadcast, at: float, *, seq: int,
                  size: int = 0) -> None:
        """:meth:`send` of one fleet broadcast to each of ``receivers``: one publication (``seq``), a copy each,
        judged copy by copy in that order."""
        self.stats.broadcasts += len(receivers)
        if self.shared_air:
            head = (instant(at), publisher_rank(sender), self.keys.local(key), seq)
            self._unjudged.extend(((*head, receiver_rank(receiver)), key, sender, receiver, msg, at, seq, size)
                                  for receiver in receivers)
            return
        self._judge_copies(key, sender, receivers, msg, at, seq, size)

    def _judge_copies(self, key: str, sender, receivers: Sequence, msg, at: float, seq: int, size: int) -> None:
        """:meth:`_judge` of one publication's copies, in the order of ``receivers``."""
        if self.layer is None:
            fates: list[list[float]] = [[0.0]] * len(receivers)
        else:
            fates = self.layer.fate_copies(key, sender, receivers, at, msg=(sender, seq), size=size)
        for receiver, fate in zip(receivers, fates):
            self._enqueue(receiver, msg, at, fate)

    def _judge(self, key: str, sender, receiver, msg, at: float, seq: int, size: int) -> None:
        fate = (self.layer.fate(key, sender, receiver, at, msg=(sender, seq), size=size)
                if self.layer is not None else [0.0])
        self._enqueue(receiver, msg, at, fate)

    def _enqueue(self, receiver, msg, at: float, fate: list[float]) -> None:
        """Put a message sent at ``at`` in flight to ``receiver`` with the delays ``fate`` gave it (none: dropped)."""
        if not fate:
            self.stats.dropped += 1
        for delay in fate:
            heapq.heappush(self._heap, (at + delay, next(self._order), receiver, msg))

    def until(self, t: float) -> list[tuple[float, object, object]]:
        """Every copy due by ``t``: (delivery time, receiver, message), in delivery order."""
        if self._unjudged:
            unjudged, self._unjudged = self._unjudged, []
            unjudged.sort(key=lambda u: u[0])
            # in the medium's order, the copies of one publication come together (same instant, publisher, key and
            # sequence number): they are judged together, in that order
            i, end = 0, len(unjudged)
            while i < end:
                _, key, sender, receiver, msg, at, seq, size = unjudged[i]
                j = i + 1
                while j < end and unjudged[j][4] is msg and unjudged[j][6] == seq and unjudged[j][1] == key:
                    j += 1
                if j == i + 1:
                    self._judge(key, sender, receiver, msg, at, seq, size)
                else:
                    self._judge_copies(key, sender, [u[3] for u in unjudged[i:j]], msg, at, seq, size)
                i = j
        self.now = max(self.now, t)
        out = []
        heap = self._heap
        while heap and heap[0][0] <= t + EPS:
            due, _, receiver, msg = heapq.heappop(heap)
            out.append((due, receiver, msg))
        self.stats.delivered += len(out)
        return out

    def observe_delay(self, due: float, sent_at: float) -> None:
        self.stats.delay_sum += due - sent_at


class Team:
    """The whole fleet's brains as one: one brain per agent (own views), with the team views metrics need."""

    def __init__(self, brains: list):
        self.brains = brains
        self.memoryless = brains[0].memoryless
        self.draws = brains[0].draws

    def team_links(self) -> np.ndarray:
        return np.vstack([b.link_rows() for b in self.brains])

    def team_weights(self) -> np.ndarray:
        return np.vstack([b.weight_rows() for b in self.brains])

    def extra_metrics(self) -> dict[str, float]:
        rows = [b.extra_metrics() for b in self.brains]
        return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} if rows and rows[0] else {}

    @property
    def h(self):
        """Every robot's homeostatic variable, for brains that have one (MORPH's); None otherwise."""
        if not all(callable(getattr(b, "h", None)) for b in self.brains):
            return None
        return lambda: np.concatenate([b.h() for b in self.brains])


class LabDispatch:
    """One fleet's protocol endpoints on an :class:`EventNetwork`, stepped by the lab's tick loop."""

    def __init__(self, n_agvs: int, n_pickers: int, *, dt: float, timeout: float, network: EventNetwork,
                 team_brain=None, agent_brains: list | None = None, fleet_brain=None):
        """One brain for the fleet: ``team_brain`` (every robot holds the sim's tick) or ``fleet_brain`` (every robot
        learns from its own view, in one brain: CoordinationPolicy.fleet_brains); or a brain per robot with its own
        view: ``agent_brains``."""
        self.n_agvs, self.n = n_agvs, n_agvs + n_pickers
        self.dt = dt
        self.net = network
        self.keys = network.keys
        self.ep = Endpoints(n_agvs, n_pickers, dt, timeout)
        self.team_brain = team_brain
        self.agent_brains = agent_brains
        self.fleet_brain = fleet_brain
        self._one = team_brain if team_brain is not None else fleet_brain  # the fleet's one brain, if it has one
        own_views = agent_brains is not None or fleet_brain is not None
        self.views = [FleetView() for _ in range(self.n)] if own_views else None
        self._everyone = list(range(self.n))
        self.mail = [Mailbox() for _ in range(self.n)]  # each robot's policy messages delivered, not yet taken
        # per tick: mean and max view age over the agents that hold a view, sim seconds (per-agent views only;
        # nan before any agent holds one) -- the monitor's view_age_mean / view_age_max columns
        self.view_ages: list[float] = []
        self.view_age_max: list[float] = []
        self.last_draws: dict[int, float] = {}
        self.sent_commits: list[tuple[int, int]] = []
        self._waiting_since: dict[int, int] = {}  # AGV -> first tick of its current wait for a picker
        self.dispatch_delays: list[int] = []  # ticks each served AGV waited for its picker

    @property
    def outcomes(self):
        return self.ep.outcomes

    def brains(self):
        return Team(self.agent_brains) if self.agent_brains is not None else self._one

    # -- delivery -------------------------------------------------------------------------------------------------
    def _deliver(self, until: float) -> None:
        ep, out = self.ep, self.ep.outcomes
        for due, receiver, msg in self.net.until(until):
            if isinstance(msg, FleetBroadcast):
                self.views[receiver].update(msg.view, msg.stamp)
                continue
            if isinstance(msg, PolicyMessage):
                self.net.observe_delay(due, msg.t * self.dt)
                try:
                    self.mail[receiver].receive(msg, due)
                except ValueError:  # content that is not a packed mapping: the agent refuses it too
                    pass
                continue
            self.net.observe_delay(due, msg.sent_at)
            if isinstance(msg, Request):
                try:
                    ep.pickers[receiver].receive(msg, due, out)
                except ValueError:  # more copies of a request than a picker takes: its agent refuses them too
                    pass
            elif isinstance(msg, Commitment):
                ep.desk.receive(msg, due, out)
            elif isinstance(msg, Reply):
                ep.agvs[receiver].receive(msg, out)
            elif isinstance(msg, Refusal):
                if receiver < self.n_agvs:
                    ep.agvs[receiver].receive(msg, out)
                else:
                    ep.pickers[receiver].receive(msg, due, out)

    # -- step t -----------------------------------------------------------------------------------------------------
    def learn(self, obs: TickObservation) -> None:
        """Tick start: the fleet broadcast goes out, what is due arrives, every agent learns from its view."""
        s = obs.t * self.dt
        self.net.observe(obs, self.dt)
        if self.views is None:
            self._deliver(s)
            self.team_brain.learn(obs)
            self._hand_mail(obs.t, s)
            return
        size = self._tick_size(obs)
        # one publication: one sequence number (its t), a copy per receiver
        self.net.broadcast(self.keys.fleet, "sim", self._everyone, FleetBroadcast(obs, s), s, seq=obs.t, size=size)
        self._deliver(s)
        ages = []
        # the robots that take a new view now, by view: every copy of one broadcast is the same observation, so
        # the fleet's brain steps each view's robots together
        taking: dict[int, tuple[TickObservation, list[int]]] = {}
        for robot, view in enumerate(self.views):
            new = view.take_new()
            if new is not None and not (new.final and self._brain(robot).memoryless):
                if self.agent_brains is not None:
                    self.agent_brains[robot].learn(new)
                else:
                    taking.setdefault(id(new), (new, []))[1].append(robot)
            ages.append(view.age(s))
        for new, robots in taking.values():
            self.fleet_brain.learn_for(new, robots)
        self._hand_mail(obs.t, s)
        mean, top = view_age_stats(ages)
        self.view_ages.append(float("nan") if mean is None else mean)
        self.view_age_max.append(float("nan") if top is None else top)

    # -- policy messages ----------------------------------------------------------------------------------------------
    def _brain(self, robot: int):
        return self.agent_brains[robot] if self.agent_brains is not None else self._one

    def _hand_mail(self, t: int, s: float) -> None:
        """At the tick's decision point, after learning: each robot's policy takes what was delivered to it."""
        for robot, box in enumerate(self.mail):
            mail = box.take(t, s)
            if mail:
                self._brain(robot).receive(robot, mail)

    def _send_mail(self, t: int, at: float) -> None:
        """What each robot's policy wrote since its last decision point goes out (an agent sends it after its
        decision, before its ack)."""
        net, k = self.net, self.keys
        for robot in range(self.n):
            for to, data in self._brain(robot).take_outbox(robot):
                msg = PolicyMessage(t=t, sender=robot, to=to, pseq=self.mail[robot].next_pseq(), data=data)
                key, size = k.policy(robot, to), len(encode(msg))
                seq = net.next_seq(key)
                receivers = [to] if to is not None else [r for r in range(self.n) if r != robot]
                for i, receiver in enumerate(receivers):
                    net.send(key, robot, receiver, msg, at, seq=seq, size=size, count=i == 0)

    def _tick_size(self, obs: TickObservation) -> int:
        """The fleet broadcast's bytes on the radio, for a profile's rate limits (services.faults.air.fleet_size);
        0 when no queue counts bytes."""
        return fleet_size(obs, self.dt) if self.net.shared_air else 0

    def _gating(self, agv: int, obs: TickObservation):
        """(brain, view) an AGV gates with: its fleet view, with its own cell and target from on board."""
        if self.views is None:
            return self.team_brain, obs
        view = self.views[agv].view
        if view is None:
            return self._brain(agv), None
        return self._brain(agv), with_own_state(view, agv, obs.cells[agv], obs.target[agv])

    def dispatch(self, obs: TickObservation, settle: Callable, count: DispatchStats,
                 draw: Callable[[int], float] | None = None) -> list[tuple[int, int]]:
        """AGVs ask, pickers decide, the sim settles what has arrived (``settle``: the tick step's,
        :meth:`services.protocol.tick.TickStep.settle`); returns the (picker, AGV) pairs applied."""
        ep, out, net, k = self.ep, self.ep.outcomes, self.net, self.keys
        s_agv, s_pick, s_sim = decision_points(obs.t, self.dt)
        needs = obs.needs_picker
        for agv, endpoint in enumerate(ep.agvs):
            if not needs[agv]:
                endpoint.may_ask(s_agv, False, out)
                self._waiting_since.pop(agv, None)
            else:
                self._waiting_since.setdefault(agv, obs.t)
        self.last_draws = draws = {}
        for agv in obs.requesters().tolist():  # mission order: a shared stream is drawn in this order
            endpoint = ep.agvs[agv]
            if not endpoint.may_ask(s_agv, True, out):
                continue
            brain, view = self._gating(agv, obs)
            if view is None:
                continue  # no fleet view yet: nothing to choose a picker from

            def u(agv=agv, brain=brain):
                draws[agv] = draw(agv) if draw is not None else brain.draw(agv)
                return draws[agv]

            g = gate(brain, agv, view, u)
            if g.picker < 0:
                continue
            count.count(g.ask, g.p, len(g.targets))
            for picker in g.targets:  # one, or every free picker of the view for a broadcasting policy
                req = endpoint.request(picker, obs.target[agv], s_agv, out)
                net.send(k.request(agv, picker), agv, picker, req, s_agv)
        self._send_mail(obs.t, s_agv)
        self._deliver(s_pick)
        self.sent_commits = []
        for picker, endpoint in ep.pickers.items():
            if not endpoint.inbox and endpoint.pending is None and not endpoint.copies:
                continue
            view = obs if self.views is None else self.views[picker].view
            order = view.request_order if view is not None else ()
            rank = {int(a): i for i, a in enumerate(order)}
            brain = self._brain(picker)
            commit, replies = endpoint.decide(s_pick, not obs.free_picker[picker], rank, out,
                                              policy_choice(brain, picker, view))
            if commit is not None:
                self.sent_commits.append((picker, commit.agv))
                net.send(k.commit(picker), picker, "sim", commit, s_pick)
            for reply in replies:
                net.send(k.reply(picker, reply.agv), picker, reply.agv, reply, s_pick)
        self._deliver(s_sim)
        if not ep.desk.inbox:
            return []
        applied, refusals = settle(obs, ep.desk, out)
        for _, agv in applied:
            self.dispatch_delays.append(obs.t - self._waiting_since.pop(agv, obs.t))
        for r in refusals:
            net.send(k.refusal(r.agv), "sim", r.agv, r, s_sim)
            net.send(k.refusal(r.picker), "sim", r.picker, r, s_sim)
        return applied


def dispatch_faults(spec: FaultSpec) -> list[FaultSpec]:
    """``spec`` on every dispatch-protocol key (request, reply, commit, refusal), one fault per key class."""
    base = spec.id or "dispatch"
    return [spec.model_copy(update={"id": f"{base}-{i}", "scope": spec.scope.model_copy(update={"key_expr": key})})
            for i, key in enumerate(DISPATCH_KEYS)]


def fleet_faults(spec: FaultSpec) -> list[FaultSpec]:
    """``spec`` on the fleet broadcast (``sim/fleet``)."""
    return [spec.model_copy(update={"id": (spec.id or "fleet") + "-tick",
                                    "scope": spec.scope.model_copy(update={"key_expr": FLEET_KEY})})]
