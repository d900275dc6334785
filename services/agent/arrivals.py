"""The agent's fault-layer hook: what a message's *arrival* means for this robot, whatever the layer does with it.

The fault layer calls it for every sample this agent receives (any thread, under the runtime's lock), before the
sample is delivered, dropped or held. The sim's on-board state, fleet broadcast and Resolve carry its boundary:
reach it first (releasing what is due by then, applying the schedule). An on-board state or Resolve that will not be
delivered now cannot be answered in its phase: skip it at once, so the sim never waits on a wall timeout. A fleet
broadcast, refusal, reply or request that will not be delivered now has arrived all the same: the decision point
does not wait for it (:mod:`services.protocol.readiness`). (Wall time: a delayed fleet broadcast is not waited for
either — a robot acts on the view it has; a delayed reply or request comes after a real sleep and is answered then.)
"""

from __future__ import annotations

from schemas import OnBoard, Phase, Refusal, Resolve
from schemas.codec import unpack_envelope
from schemas.tick import tick_number
from services.bus.base import Sample


class ArrivalHook:
    """``layer.on_fate`` of agent ``agent``'s fault layer ``layer``.

    ``agent`` is the robot's :class:`~services.agent.service.AgentService`, which builds this hook: it is not imported
    here, so the service and its hook do not import each other.
    """

    def __init__(self, agent, layer) -> None:
        self.agent = agent
        self.layer = layer
        self.faults = agent.faults
        self.virtual = agent._virtual
        keys = agent.keys
        self.onboard_key, self.fleet_key, self.resolve_key = keys.onboard(agent.id), keys.fleet, keys.resolve
        self.refusal_key = keys.refusal(agent.id)

    def __call__(self, sample: Sample, fate: list[float]) -> None:
        agent, key = self.agent, sample.key
        if self.virtual:
            missed = not self.layer.delivers_now(sample, fate)
        else:
            missed = not fate
        onboard = key == self.onboard_key
        if onboard or key == self.fleet_key or key == self.resolve_key:
            if sample.sender != "sim":
                return  # only the sim's own samples carry its boundary (not a stray publisher's, nor a fuzzer's)
            if self.virtual:
                at = self.layer.sent_at(sample)
                if at > self.faults.now():  # a tick's on-board state and fleet broadcast share their boundary
                    self.faults.advance(at)
            elif onboard:
                self._advance_wall(sample)
            if key == self.fleet_key:
                if missed or (not self.virtual and min(fate) > 0.0):
                    t = self._tick_of(sample)
                    if t is not None:
                        with agent._lock:
                            agent._fleet_seen(t)
                return
            if not missed or agent._stop.is_set():
                return
            try:
                if onboard:
                    ob = sample.decode(OnBoard)
                    t, phase = ob.t, Phase.TICK
                    if t <= agent.last_t:
                        return
                    with agent._lock:
                        agent.readiness.announce(ob.t, ob.refused, ob.messaged)
                else:
                    msg = sample.decode(Resolve)
                    if not msg.expected(agent.id):
                        return
                    t, phase = msg.t, Phase.RESOLVE
            except ValueError:
                return  # the handler rejects it if it is ever delivered
            self.faults.skip(agent.bus, agent.id, t, phase)
        elif not missed:
            return
        elif key == self.refusal_key:
            if sample.sender != "sim":
                return
            try:
                msg = sample.decode(Refusal)
            except ValueError:
                return
            if agent.id in (msg.agv, msg.picker):
                with agent._lock:
                    agent.count_refusal(sample, msg.t)
        elif "/policy/" in key:
            agent.mail_missed(sample)
        else:
            agent.missed(sample, fate)  # a reply to an AGV, a request to a picker

    def _tick_of(self, sample: Sample) -> int | None:
        """The tick number of a fleet broadcast, without validating the rest (its handler does that)."""
        agent = self.agent
        try:
            t = tick_number(sample.payload)
        except ValueError:
            return None
        if t > agent.config.steps or (agent.last_t >= 0 and t > agent.last_t + agent._ticks.max_gap):
            return None
        return t

    def _advance_wall(self, sample: Sample) -> None:
        """Wall time: the on-board state still marks its tick's start, where scheduled and ``at_tick`` commands apply
        (sim stamps are wall clock here, so the tick number is read off the message itself)."""
        try:
            t = unpack_envelope(sample.payload)[1].get("t")
        except ValueError:
            return
        if type(t) is int and t >= 0:
            self.faults.advance(t * self.agent.config.dt)
