"""The sim's answers in a phase: robots' acks and commitments taken in (checked, counted, held or refused) and the
phase barrier told who has answered (a mixin of :class:`services.sim.service.SimService`, whose state it uses)."""

from __future__ import annotations

from schemas import Ack, Commit, Phase
from services.bus.base import Sample
from services.protocol import dispatch as protocol
from services.protocol.claims import check_tick


class Answers:
    """Acks and commits of the robots (on the transport's receive thread: the subscriptions are inline)."""

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

    def _claims(self, sample: Sample, robot: int, t: int, what: str) -> bool:
        """Whether a robot's ack or commit of tick ``t`` is one the sim can take; a refused one is counted."""
        try:
            self._senders.check(robot, sample.sender)
            check_tick(t, self.ctl.t, self.config.steps, what)
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return False
        return True

    def _on_ack(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, Ack, "agent", "ack of agent")
        if msg is None or not self._claims(sample, msg.agent, msg.t, "ack"):
            return
        with self._desk_lock:  # (the receive thread and the loop both take acks)
            try:
                if not self._once.admit(msg.agent, msg.t, msg.phase, sample.seq):
                    return  # the network's copy of an ack taken
                if msg.outcomes is not None and msg.phase == Phase.TICK:
                    try:
                        self._outcome_bound.check(msg.agent, msg.t, msg.outcomes)
                    except ValueError:
                        self._once.forget(msg.agent, msg.t, msg.phase)  # a refused lie keeps no genuine ack out
                        raise
                    self.robot_outcomes.report(msg.agent, msg.t, msg.outcomes)
            except ValueError as exc:
                self.intake.refuse(sample.key, exc)
                return
        ph = self._phase
        if ph is None or msg.t != ph.t or msg.phase != ph.phase:
            return  # an ack of another phase: synchronisation only, nothing to do
        with ph.lock:
            if ph.closed or (msg.agent not in ph.waiting and msg.agent not in ph.held):
                return  # duplicate
            ph.held.discard(msg.agent)
            if self.shared_air:
                self._air_count(ph, msg)
            if ph.phase == Phase.TICK:
                for to in msg.policy_to:  # its policy's messages: the receivers wait for them next tick
                    if to == -1:
                        for r in range(self.n):
                            self._messaged[r] += r != msg.agent
                    elif 0 <= to < self.n and to != msg.agent:
                        self._messaged[to] += 1
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
                    ph.acked(msg.agent)
                    return
            ph.answered(msg.agent)

    def _on_commit(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, Commit, "picker", "commit of picker")
        if msg is None or not self._claims(sample, msg.picker, msg.t, "commit"):
            return
        if not (self.config.n_agvs <= msg.picker < self.n and 0 <= msg.agv < self.config.n_agvs):
            self.intake.refuse(sample.key, f"commit of robot {msg.picker} to robot {msg.agv}: not a picker and an AGV")
            return
        # never discarded for being late: it waits on the desk for the next step boundary, where it is applied if
        # still valid (else refused, and both sides told)
        sent = msg.t * self.config.dt + self.config.dt / 2
        cell = (msg.target_x, msg.target_y) if msg.target_x >= 0 and msg.target_y >= 0 else None
        with self._desk_lock:
            try:  # judged against the sim's tick and what the desk holds before it is held (dispatch.py)
                # a picker commits at most once a tick (its one decision point); the network's copies go on to the
                # desk, which counts them as duplicates
                self._once.admit(msg.picker, msg.t, -1, sample.seq)
                self.desk.receive(protocol.Commitment(msg.picker, msg.agv, cell, sent, msg.seq),
                                  sample.due if sample.due >= 0.0 else sent, self.outcomes,
                                  now=self.ctl.t * self.config.dt)
            except ValueError as exc:
                self.intake.refuse(sample.key, exc)
                return
        ph = self._phase
        if ph is not None and ph.phase == Phase.RESOLVE and msg.t == ph.t:
            with ph.lock:
                if not ph.closed and msg.picker in ph.waiting:
                    self._commit_arrived(ph, msg.picker)
