"""What one robot's decision points still wait for in a distributed lockstep run, as pure code.

Over a bus a picker's request, a picker's reply, the sim's refusal and the fleet broadcast travel other paths than
the robot's on-board state, so a receiver cannot tell "not sent" from "not yet here" by waiting. Each decision point
therefore waits for a count carried by synchronisation traffic, and a message counts once it has *arrived*:
delivered, held for later or lost by the receiver's fault layer (docs/decisions.md, "What a decision point waits for
in a distributed run"):

* the tick's decision point (``t·Δ``) waits for the fleet broadcast of its tick;
* an AGV with a request outstanding waits for every reply sent to it since it asked: its on-board state carries the
  number of replies sent to it so far (``replied``, cumulative, so a skipped tick hides nothing);
* every robot waits for the refusals the sim sent to it by its newest on-board state (``refused``, cumulative): the
  sim sends them at the step boundary, before that tick's on-board states;
* a picker's decision point (``t·Δ + Δ/2``) waits for the requests its ``Resolve`` lists for it.

:class:`Readiness` keeps those counts and arrivals for one robot: arrivals and announced counts in, "may act now" and
"still owed N" out. No bus, no clock, no lock: its driver (the agent service) calls it under its own lock, and
resumes a waiting decision point whenever a call says something new arrived. Only a lockstep run waits; a paced
(real-time) robot acts on what it has.
"""

from __future__ import annotations

from collections.abc import Iterable


class Readiness:
    """The readiness bookkeeping of one robot's decision points (see the module's docstring)."""

    __slots__ = ("_announced", "_lockstep", "_refusal_arrivals", "_refusal_base", "_refusals_seen", "_reply_arrivals",
                 "_reply_base", "_replies_seen", "_requests", "fleet_arrived")

    def __init__(self, lockstep: bool) -> None:
        self._lockstep = lockstep
        self.fleet_arrived = -1  # the newest tick whose fleet broadcast arrived (delivered, held or lost)
        # refusals to this robot that arrived, per boundary tick they were sent at, since the base: (the tick of the
        # last decision point that had them all, the sim's count then); None before the first on-board state
        self._refusal_arrivals: dict[int, int] = {}
        self._refusal_base: tuple[int, int] | None = None
        self._refusals_seen: set[tuple[str, int]] = set()
        # (tick, refusals sent to this robot by then) of the newest on-board state that arrived, acted on or not: a
        # picker that skipped its tick still decides at that tick's Resolve, with the refusals it announced
        self._announced: tuple[int, int] | None = None
        # AGV: replies that arrived, per step the picker decided at, and (step of the outstanding request, replies
        # announced to this AGV before it)
        self._reply_arrivals: dict[int, int] = {}
        self._reply_base = (0, 0)
        self._replies_seen: set[tuple[str, int]] = set()
        # picker: tick -> AGVs whose request of that tick arrived (delivered, or dropped / held past the boundary)
        self._requests: dict[int, set[int]] = {}

    # -- the decision points -------------------------------------------------------------------------------------------
    def may_act(self, t: int, replied: int, awaiting_replies: bool) -> bool:
        """Whether the tick's decision point of tick ``t`` may be taken now: its fleet broadcast has arrived and, in
        lockstep, every reply announced (``replied``, for an AGV ``awaiting_replies`` — a request outstanding, not
        the final tick) and every refusal announced has arrived."""
        if self.fleet_arrived < t:
            return False
        if not self._lockstep:
            return True
        if awaiting_replies and self.replies_owed(replied) > 0:
            return False
        return self.refusals_owed() <= 0

    def may_decide(self, t: int, expected: Iterable[int]) -> bool:
        """Whether a picker's decision point of step ``t`` may be taken now: (in lockstep) every refusal announced
        has arrived — one may end its commitment in flight — and every request of ``expected`` (the AGVs its
        ``Resolve`` lists) has arrived."""
        if self._lockstep and self.refusals_owed() > 0:
            return False
        arrived = self._requests.get(t, ())
        return all(a in arrived for a in expected)

    # -- the fleet broadcast --------------------------------------------------------------------------------------------
    def fleet(self, t: int) -> bool:
        """The fleet broadcast of tick ``t`` arrived; True when it is newer than any before (a decision point
        waiting for it may go)."""
        if t > self.fleet_arrived:
            self.fleet_arrived = t
            return True
        return False

    # -- refusals --------------------------------------------------------------------------------------------------------
    def announce(self, t: int, refused: int) -> None:
        """An on-board state of tick ``t`` arrived (delivered, or skipped by the fault layer), announcing ``refused``
        refusals sent to this robot so far. Only the newest counts."""
        if self._announced is None or t > self._announced[0]:
            self._announced = (t, refused)

    def refusal(self, sender: str, seq: int, t: int) -> bool:
        """A copy of refusal (``sender``, ``seq``), sent at the boundary that starts tick ``t``, arrived; True the
        first time (each refusal counts once, whatever the network did to its copies)."""
        return _count(self._refusals_seen, self._refusal_arrivals, sender, seq, t)

    def refusals_owed(self) -> int:
        """Refusals the sim sent to this robot by the tick of its newest on-board state that have not arrived yet.
        Those announced by the newest on-board state when this is first asked (this process's first decision point)
        are not waited for: a restarted robot's predecessor had them. Once none is owed, what arrived up to that tick
        becomes the base."""
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

    # -- replies (an AGV) ------------------------------------------------------------------------------------------------
    def asked(self, t: int, replied: int) -> None:
        """The AGV sent a request at step ``t``, when ``replied`` replies had been sent to it: those are not waited
        for, and arrivals from steps before ``t`` are forgotten."""
        self._reply_base = (t, replied)
        self._reply_arrivals = {s: n for s, n in self._reply_arrivals.items() if s >= t}

    def reply(self, sender: str, seq: int, t: int) -> bool:
        """A copy of reply (``sender``, ``seq``), decided at step ``t``, arrived; True the first time."""
        return _count(self._replies_seen, self._reply_arrivals, sender, seq, t)

    def replies_owed(self, replied: int) -> int:
        """Replies sent to this AGV since its request (the sim's cumulative count ``replied`` minus the count when it
        asked) that have not arrived yet."""
        since, base = self._reply_base
        arrived = sum(n for t, n in self._reply_arrivals.items() if t >= since)
        return replied - base - arrived

    # -- requests (a picker) ---------------------------------------------------------------------------------------------
    def request(self, t: int, agv: int) -> None:
        """AGV ``agv``'s request of tick ``t`` arrived (delivered, or dropped / held past the boundary)."""
        self._requests.setdefault(t, set()).add(agv)

    def decided(self, t: int) -> None:
        """The picker decided at step ``t``: requests of that step and before are no longer waited for."""
        for old in [s for s in self._requests if s <= t]:
            del self._requests[old]


def _count(seen: set[tuple[str, int]], arrivals: dict[int, int], sender: str, seq: int, t: int) -> bool:
    """Count one arrival of message (``sender``, ``seq``) under its step ``t``, once per message sent."""
    key = (sender, seq)
    if key in seen:
        return False
    seen.add(key)
    arrivals[t] = arrivals.get(t, 0) + 1
    return True


__all__ = ["Readiness"]
