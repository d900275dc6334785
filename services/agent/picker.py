"""A picker's agent: requests wait in its endpoint's inbox; at the sim's ``Resolve`` it waits for the requests it
was told to expect (and, in lockstep, for the refusals announced to it), takes the first in mission order and
answers: ``Commit`` to the sim, ``HelpReply`` to every requester, then its resolve ack. Past the deadline it decides
over those that arrived."""

from __future__ import annotations

import asyncio

from schemas import Ack, Commit, HelpReply, HelpRequest, OnBoard, Phase, Resolve
from services.agent.service import AgentService, check_from_sim
from services.bus.base import Sample
from services.policies.interface import policy_choice
from services.protocol import dispatch as protocol


class PickerService(AgentService):
    """The agent of picker ``agent_id`` (build it with :func:`services.agent.roles.make_agent`)."""

    is_agv = False
    role = "picker"

    def __init__(self, config, bus, agent_id: int, **kwargs):
        super().__init__(config, bus, agent_id, **kwargs)
        self.endpoint = protocol.PickerEndpoint(agent_id, config.request_timeout, self._next_seq)
        self._assigned = False  # on board: the picker has a mission (latest tick)
        self._pending: tuple[int, list[int]] | None = None  # the resolve being decided: (tick, AGVs expected)
        self._resolved_t = -1  # the last tick this picker decided: a duplicated Resolve never decides twice
        self._pending_timer: asyncio.TimerHandle | None = None
        self._holding = False  # the request arriving right now is about to be held by the fault layer

    async def _subscribe_role(self) -> None:
        k = self.keys
        await self.bus.subscribe(k.resolve, self._on_resolve, inline=True)
        await self.bus.subscribe(k.requests_to(self.id), self._on_request, inline=True)

    def _cancel_timers(self) -> None:
        if self._pending_timer is not None:
            self._pending_timer.cancel()
        super()._cancel_timers()

    def _resume(self) -> None:
        super()._resume()
        self._try_decide()

    # -- the tick's decision point ---------------------------------------------------------------------------------
    def _check_commitment(self, t: int) -> None:
        if t > 0:
            # the decision point of step t−1 (again, if requests were decided there: idempotent): a commitment in
            # flight ends there (refused, took effect, expired) with what the picker knew then, requests or not
            self.endpoint.check_pending((t - 1) * self.config.dt + self.config.dt / 2, self._assigned, self.outcomes)

    def _decide_on_board(self, ob: OnBoard, now: float, final: bool) -> list[int]:
        self._assigned = not ob.free
        return []

    def _receive_refusal(self, refusal: protocol.Refusal, sample: Sample) -> None:
        self.endpoint.receive(refusal, self._due(sample, refusal.sent_at), self.outcomes)

    # -- requests ----------------------------------------------------------------------------------------------------
    def _on_request(self, sample: Sample) -> None:
        if self._stop.is_set():
            return  # a stopped agent is gone, even while its session closes
        try:
            msg = sample.decode(HelpRequest)
            sender = self.keys.sender_of(sample.key)
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return
        if msg.picker != self.id or sender != msg.agv:
            self.intake.refuse(sample.key, f"request {msg.agv}->{msg.picker} on key of {sender}")
            return
        if self.last_t >= 0 and msg.t > self.last_t + self._ticks.max_gap:  # a request for a far future tick is
            # forged or corrupt: kept, it would wait forever
            self.intake.refuse(sample.key, f"request for tick {msg.t}, this picker is at tick {self.last_t}")
            return
        # never dropped for being late: it waits in the endpoint's inbox for this picker's next decision point
        req = protocol.Request(msg.agv, msg.picker, (msg.target_x, msg.target_y), msg.t * self.config.dt, msg.seq)
        with self._lock:
            try:
                self.endpoint.receive(req, self._due(sample, req.sent_at), self.outcomes)
            except ValueError as exc:  # a second request of the AGV for its tick, or too many copies of one
                self.intake.refuse(sample.key, exc)
                return
            self.readiness.request(msg.t, msg.agv)
            self._try_decide()

    def missed(self, sample: Sample, fate: list[float]) -> None:
        if "/request/" not in sample.key:
            return
        try:
            msg = sample.decode(HelpRequest)
        except ValueError:
            return
        if msg.picker != self.id:
            return
        with self._lock:
            self.readiness.request(msg.t, msg.agv)
            # the hook runs before the fault layer holds the sample: a decision taken now must count it as held
            self._holding = bool(fate)
            try:
                self._try_decide()
            finally:
                self._holding = False

    # -- the picker's decision point: Resolve, deadline, decision ------------------------------------------------------
    def _on_resolve(self, sample: Sample) -> None:
        if self._stop.is_set() or self._came_late(sample):
            return  # a stopped agent is gone, even while its session closes
        try:
            check_from_sim(sample, "resolve")
            msg = sample.decode(Resolve)
            if self.last_t >= 0 and msg.t > self.last_t + self._ticks.max_gap:  # of the tick just taken (or of one
                # lost on the way)
                raise ValueError(f"resolve of tick {msg.t}, this picker is at tick {self.last_t}")
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return
        if self.id not in msg.pickers or msg.t < self.last_t or msg.t <= self._resolved_t:
            return
        expected = msg.expected(self.id)
        with self._lock:
            self._pending = (msg.t, expected)
            self._try_decide()
            if self._pending is not None:
                # Lockstep: wait for every expected request; past the deadline decide over those that arrived.
                wait = self.config.phase_timeout if self._lockstep else 0.4 * self.config.period
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
        """Decide once what the pending resolve waits for has arrived (services/protocol/readiness.py): every expected
        request delivered by the resolve boundary, or dropped / held past it (virtual time: the same set whatever the
        wall order of arrivals), and in lockstep every refusal announced — one may end the commitment in flight."""
        if self._pending is None:
            return
        t, expected = self._pending
        if self.readiness.may_decide(t, expected):
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
        self.readiness.decided(t)
        now = t * self.config.dt + self.config.dt / 2  # the picker's decision point of step t
        view = self.fleet.view  # the mission order as this picker last heard it (the tie-break)
        rank = {int(a): i for i, a in enumerate(view.request_order)} if view is not None else {}
        commit, replies = self.endpoint.decide(now, self._assigned, rank, self.outcomes,
                                               policy_choice(self.brains, self.id, view))
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
