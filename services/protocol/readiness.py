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


class _Announced:
    """Messages to this robot that its on-board state announces by a cumulative count (refusals, policy messages):
    the arrivals per tick they were sent at, since the base (the tick of the last decision point that had them all,
    and the count then)."""

    __slots__ = ("announced", "arrivals", "base", "seen")

    def __init__(self) -> None:
        self.arrivals: dict[int, int] = {}
        self.base: tuple[int, int] | None = None
        self.seen: set[tuple[str, int]] = set()
        # (tick, count) of the newest on-board state that arrived, acted on or not
        self.announced: tuple[int, int] | None = None

    def announce(self, t: int, count: int) -> None:
        if self.announced is None or t > self.announced[0]:
            self.announced = (t, count)

    def arrived(self, sender: str, seq: int, t: int) -> bool:
        return _count(self.seen, self.arrivals, sender, seq, t)

    def owed(self) -> int:
        """Announced by the newest on-board state and not arrived. Those announced by the newest on-board state when
        this is first asked (this process's first decision point) are not waited for: a restarted robot's
        predecessor had them. Once none is owed, what arrived up to that tick becomes the base."""
        if self.announced is None:
            return 0
        upto, announced = self.announced
        since, count = self.base if self.base is not None else self.announced
        arrived = sum(n for t, n in self.arrivals.items() if since < t <= upto)
        owed = announced - count - arrived
        if owed <= 0:
            self.base = self.announced
            self.arrivals = {t: n for t, n in self.arrivals.items() if t > upto}
        return owed


class Readiness:
    """The readiness bookkeeping of one robot's decision points (see the module's docstring)."""

    __slots__ = ("_lockstep", "_mail", "_refusals", "_reply_arrivals", "_reply_base", "_replies_seen", "_requests",
                 "fleet_arrived")

    def __init__(self, lockstep: bool) -> None:
        self._lockstep = lockstep
        self.fleet_arrived = -1  # the newest tick whose fleet broadcast arrived (delivered, held or lost)
        # refusals to this robot, per boundary tick they were sent at; policy messages to it, per tick they were sent
        # at. A picker that skipped its tick still decides at that tick's Resolve, with the refusals announced.
        self._refusals = _Announced()
        self._mail = _Announced()
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
        the final tick), every refusal and every policy message announced has arrived."""
        if self.fleet_arrived < t:
            return False
        if not self._lockstep:
            return True
        if awaiting_replies and self.replies_owed(replied) > 0:
            return False
        return self.refusals_owed() <= 0 and self._mail.owed() <= 0

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

    # -- refusals and policy messages ------------------------------------------------------------------------------------
    def announce(self, t: int, refused: int, messaged: int = 0) -> None:
        """An on-board state of tick ``t`` arrived (delivered, or skipped by the fault layer), announcing ``refused``
        refusals and ``messaged`` policy messages sent to this robot so far. Only the newest counts."""
        self._refusals.announce(t, refused)
        self._mail.announce(t, messaged)

    def refusal(self, sender: str, seq: int, t: int) -> bool:
        """A copy of refusal (``sender``, ``seq``), sent at the boundary that starts tick ``t``, arrived; True the
        first time (each refusal counts once, whatever the network did to its copies)."""
        return self._refusals.arrived(sender, seq, t)

    def refusals_owed(self) -> int:
        """Refusals the sim sent to this robot by the tick of its newest on-board state that have not arrived yet."""
        return self._refusals.owed()

    def message(self, sender: str, seq: int, t: int) -> bool:
        """A copy of policy message (``sender``, ``seq``), sent at tick ``t``, arrived; True the first time. It was
        announced by the on-board state of tick ``t + 1``, whose arrivals are counted from ``t + 1`` on."""
        return self._mail.arrived(sender, seq, t + 1)

    def messages_owed(self) -> int:
        """Policy messages sent to this robot in the ticks before its newest on-board state, not arrived yet."""
        return self._mail.owed()

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
