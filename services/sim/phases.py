"""The sim's phase barrier: who must still answer in a phase of the tick, and waiting for them within its deadline.

A phase (the Tick's, then the Resolve's) ends when every present agent has answered, or at its deadline (lockstep: the
phase timeout, after which a silent agent is absent; paced: a share of the period). In virtual time the boundary that
closes a phase releases what the fault layer held (:meth:`PhaseCollection._boundary`).
"""

from __future__ import annotations

import asyncio
import threading
import time

from schemas import Phase


class PhaseBarrier:
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
        # the shared air: what the acks of this phase say their robots published, and who has not acked yet (a
        # picker that acked may still owe its Commit's arrival, which waits for the air's verdict on it)
        self.air: dict[tuple[int | str, str], int] = {}
        self.acks_left = set(waiting)
        self.lock = threading.Lock()
        self.closed = False
        self._loop = asyncio.get_running_loop()
        self.done = self._loop.create_future()
        self.all_acked = self._loop.create_future()
        if not self.waiting:
            self.done.set_result(None)
            self.all_acked.set_result(None)

    def acked(self, agent: int) -> None:
        """Call with ``lock`` held, from any thread: ``agent``'s ack of this phase is in (or it is absent)."""
        self._strike(self.acks_left, agent, self.all_acked)

    def answered(self, agent: int) -> None:
        """Call with ``lock`` held, from any thread."""
        self.acked(agent)
        self._strike(self.waiting, agent, self.done)

    def _strike(self, left: set[int], agent: int, done: asyncio.Future) -> None:
        """``agent`` is no longer waited for in ``left``; the last one resolves ``done`` (on the loop)."""
        if agent in left:
            left.discard(agent)
            if not left:
                self._loop.call_soon_threadsafe(_resolve, done)

    def close(self) -> None:
        with self.lock:
            self.closed = True


def _resolve(done: asyncio.Future) -> None:
    if not done.done():
        done.set_result(None)


class PhaseCollection:
    """The sim service's side of the barrier (a mixin of :class:`services.sim.service.SimService`)."""

    @staticmethod
    def _commit_arrived(ph: PhaseBarrier, picker: int) -> None:
        """With ``ph.lock`` held."""
        ph.commit_arrived.add(picker)
        if ph.commit_wanted.pop(picker, None) is not None:
            ph.answered(picker)

    def _boundary(self, t: int, phase: int) -> None:
        """Virtual time: reach the boundary that closes ``phase`` of tick ``t`` (releases held answers)."""
        if self.faults is not None:
            from services.faults.vtime import boundaries

            self.faults.advance(boundaries(t, self.config.dt)[1 if phase == Phase.TICK else 2])

    def _deadline(self, started: float, phase: int) -> float:
        if self.config.mode == "paced":
            # a phase gets a share of the period; a late answer means no action this tick
            share = 0.45 if phase == Phase.TICK else 0.9
            return started + share * self.config.period
        return time.monotonic() + self.config.phase_timeout

    async def _collect(self, ph: PhaseBarrier, deadline: float, on_acked=None) -> None:
        """Wait for the phase's answers until ``deadline``; ``on_acked()`` runs once every ack is in (or at the
        deadline), before the phase waits for what the acks announced to arrive."""
        self._phase = ph
        if self._stop is not None:  # the run is ending: take what is already in, wait for nobody
            deadline = min(deadline, time.monotonic() + 0.2)
        try:
            if on_acked is not None:
                left = deadline - time.monotonic()
                try:
                    if left > 0:
                        await asyncio.wait_for(asyncio.shield(ph.all_acked), left)
                finally:
                    on_acked()
            left = deadline - time.monotonic()
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
