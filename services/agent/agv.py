"""An AGV's agent: at its decision point it gates from its fleet view and may ask a picker for help; it hears the
pickers' replies and the sim's refusals, and (in lockstep) waits for the replies announced to it while a request of
its own is outstanding."""

from __future__ import annotations

from schemas import HelpReply, HelpRequest, OnBoard
from schemas.codec import encode_fields
from services.agent.service import AgentService
from services.bus.base import Sample
from services.protocol import dispatch as protocol


class AgvService(AgentService):
    """The agent of AGV ``agent_id`` (build it with :func:`services.agent.roles.make_agent`)."""

    is_agv = True
    role = "agv"

    def __init__(self, config, bus, agent_id: int, **kwargs):
        super().__init__(config, bus, agent_id, **kwargs)
        self.endpoint = protocol.AgvEndpoint(agent_id, config.request_timeout, self._next_seq)

    async def _subscribe_role(self) -> None:
        await self.bus.subscribe(self.keys.replies_to(self.id), self._on_reply, inline=True)

    def _awaits_replies(self, final: bool) -> bool:
        return not final and self.endpoint.outstanding is not None

    def _decide_on_board(self, ob: OnBoard, now: float, final: bool) -> list[int]:
        """Gate and request: from its fleet view with its own on-board cell and target, when its mission needs a
        picker and no request of its own is outstanding (never at the final tick)."""
        asked: list[int] = []
        if final:
            return asked
        t = ob.t
        may_ask = self.endpoint.may_ask(now, ob.needs_picker, self.outcomes)
        if may_ask and self.fleet.view is not None:  # no fleet view yet: nothing to choose a picker from
            cell, target = (ob.x, ob.y), (ob.target_x, ob.target_y)
            g = protocol.gate(self.brains, self.id, protocol.with_own_state(self.fleet.view, self.id, cell, target))
            if g.ask:
                reqs = [self.endpoint.request(p, target, now, self.outcomes) for p in g.targets]
                self.readiness.asked(t, ob.replied)
                for req in reqs:  # one (a broadcasting policy: one per free picker it knows of)
                    tx, ty = req.cell
                    self.bus.put(self.keys.request(self.id, req.picker), encode_fields(
                        HelpRequest, t=t, agv=self.id, picker=req.picker, target_x=tx, target_y=ty,
                        mission=ob.mission, seq=req.seq))
                    self.counters.requests += 1
                    asked.append(req.picker)
        return asked

    def _on_reply(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, HelpReply, "picker", "reply of picker")
        if msg is None:
            return
        if msg.agv != self.id:
            self.intake.refuse(sample.key, f"reply addressed to AGV {msg.agv}")
            return
        with self._lock:  # takes effect at once: it only frees the AGV to ask again at its next decision point
            self.endpoint.receive(protocol.Reply(msg.picker, msg.agv, msg.accepted, msg.t * self.config.dt,
                                                 msg.request_seq), self.outcomes)
            self._count_reply(sample, msg.t)

    def _count_reply(self, sample: Sample, t: int) -> None:
        """A reply to this AGV, decided at step ``t``, physically arrived (with ``_lock`` held)."""
        if self.readiness.reply(sample.sender, sample.seq, t):
            self._resume()

    def _receive_refusal(self, refusal: protocol.Refusal, sample: Sample) -> None:
        self.endpoint.receive(refusal, self.outcomes)

    def missed(self, sample: Sample, fate: list[float]) -> None:
        if "/reply/" not in sample.key:
            return
        try:
            msg = sample.decode(HelpReply)
        except ValueError:
            return
        if msg.agv == self.id:
            with self._lock:
                self._count_reply(sample, msg.t)
