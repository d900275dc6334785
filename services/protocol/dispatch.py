"""Dispatch between AGVs, pickers and the sim, written once (docs/faults.md, "Late, not lost").

Nothing here does I/O or reads a clock: every method takes the sim time it happens at and returns the messages to
send. A driver (the lab's discrete-event network, a service over a bus) carries those messages, decides their fate
(delay, loss, duplicate) and hands each delivered message to its receiver with its delivery time. A message is never
discarded for being late: it waits in the receiver's inbox until the receiver's next decision point.

Decision points of step ``t`` (Δ sim seconds per step, :func:`decision_points`):

* ``t·Δ`` — an AGV: its on-board state says whether its mission needs a picker; if so and no request of its own is
  outstanding, it draws its gate (:func:`gate`) and may send one :class:`Request`;
* ``t·Δ + Δ/2`` — a picker: over the requests delivered to it by then, in delivery-time order with ties broken by
  the fleet's mission order, it takes the first if it is free and has no commitment in flight, and declines the
  others: one :class:`Commitment` to the sim and a :class:`Reply` to every requester;
* ``(t+1)·Δ`` — the sim: it applies the commitments delivered by then, in delivery order (ties: mission order), each
  only if still valid (the AGV still needs a picker at that cell, the picker is still free); a refused one is
  answered with a :class:`Refusal` to both sides.

An AGV waits for the answer to its request up to ``timeout`` sim seconds (then the request *expires* and it may ask
again); a picker holds itself for its commitment as long. Duplicated requests and commitments are recognised by
(sender, sequence number) and count once. With zero latency every message of step ``t`` is delivered within step
``t`` and the outcome is the concurrent resolution of the reference: each picker takes the first requester in
mission order.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields

from schemas.fields import DISPATCH_OUTCOMES
from schemas.tick import replace_fields

# Timestamps are sums of floats (t·Δ + Δ/2 + L): compare them with a tolerance, so that a message due exactly at a
# decision point is delivered by it.
EPS = 1e-9

#: An AGV's default request timeout, sim seconds (RunConfig.request_timeout). At zero latency the answer comes Δ/2
#: after the request and the commitment lands Δ later; a one-way latency L adds 2L to that. Five steps of Δ = 1 s
#: cover one-way delays up to 2 s (a slow Wi-Fi roam) before an AGV gives up, and bound what one lost message costs
#: an AGV to five steps of waiting.
DEFAULT_REQUEST_TIMEOUT = 5.0


def decision_points(t: int, dt: float) -> tuple[float, float, float]:
    """(AGV, picker, sim) decision times of step ``t``, sim seconds."""
    return t * dt, t * dt + dt / 2, (t + 1) * dt


# ---------------------------------------------------------------------------------------------------------------
# messages (the protocol's own records; the wire forms live in schemas.messages)
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Request:
    """AGV → picker: come to ``cell``, my mission's target."""

    agv: int
    picker: int
    cell: tuple[int, int]
    sent_at: float
    seq: int


@dataclass(frozen=True, slots=True)
class Reply:
    """Picker → AGV: the answer to one request."""

    picker: int
    agv: int
    accepted: bool
    sent_at: float
    request_seq: int


@dataclass(frozen=True, slots=True)
class Commitment:
    """Picker → sim: I take the mission of ``agv`` at ``cell``."""

    picker: int
    agv: int
    cell: tuple[int, int]
    sent_at: float
    seq: int


@dataclass(frozen=True, slots=True)
class Refusal:
    """Sim → AGV and picker: this commitment reached the sim when it was no longer valid."""

    picker: int
    agv: int
    sent_at: float
    commit_seq: int


@dataclass
class Outcomes:
    """What became of the protocol's messages; one set per run (or per endpoint, summed)."""

    requests: int = 0  # requests sent
    declined: int = 0  # requests a picker answered with no
    expired: int = 0  # requests unanswered within the AGV's timeout
    commitment_expired: int = 0  # a picker's commitment neither applied nor refused within the timeout
    on_time: int = 0  # commitments applied at the boundary of the step they were sent in
    late_applied: int = 0  # commitments applied at a later boundary
    refused_stale: int = 0  # commitments no longer valid when they reached the sim
    duplicates: int = 0  # copies of a request or commitment already seen

    def add(self, other: Outcomes) -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def counts(self) -> dict[str, int]:
        """The nonzero counters (the wire form, schemas.fields.OutcomeCounts: a counter left out is zero)."""
        return {name: v for name, v in vars(self).items() if v}  # every ack carries them: no fields() walk


if tuple(f.name for f in fields(Outcomes)) != DISPATCH_OUTCOMES:  # the wire names the same counters
    raise ImportError("Outcomes and schemas.fields.DISPATCH_OUTCOMES must list the same counters in the same order")


class OutcomeTally:
    """A run's outcome counters summed over endpoints that each report their own cumulative counts (the robots, on
    their acks). Each endpoint's latest report counts once; a report below the previous one comes from an endpoint
    that restarted from zero, and what it had counted before is kept."""

    def __init__(self) -> None:
        self._latest: dict[object, dict[str, int]] = {}
        self._tick: dict[object, int] = {}
        self._sum = dict.fromkeys(DISPATCH_OUTCOMES, 0)

    def report(self, who, t: int, counts: Mapping[str, int]) -> None:
        """``who``'s counts as of its report at tick ``t``; an older report than one already taken is ignored."""
        if t <= self._tick.get(who, -1):
            return
        self._tick[who] = t
        prev = self._latest.get(who, {})
        if counts == prev:
            return  # the common report: nothing changed since this endpoint's last one
        restarted = any(counts.get(name, 0) < v for name, v in prev.items())
        for name, v in counts.items():
            self._sum[name] += v if restarted else v - prev.get(name, 0)
        self._latest[who] = dict(counts)

    def total(self, plus: Mapping[str, int] | None = None) -> dict[str, int]:
        """Every counter (zeros included), with ``plus`` (another endpoint's counts, e.g. the sim's) added."""
        if not plus:
            return dict(self._sum)
        return {name: v + plus.get(name, 0) for name, v in self._sum.items()}


# ---------------------------------------------------------------------------------------------------------------
# the gate: the one place where an AGV decides whether to ask
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Gate:
    picker: int  # the candidate, -1 if none is free
    p: float  # P(respond) of the policy for that pair
    ask: bool
    also: tuple[int, ...] = ()  # a broadcasting policy asks these pickers too, in the same decision point

    @property
    def targets(self) -> tuple[int, ...]:
        """Every picker this AGV sends a request to now (none if it does not ask)."""
        return (self.picker, *self.also) if self.ask else ()


def gate(coordinator, agv: int, view, draw: Callable[[], float] | None = None, free=None) -> Gate:
    """AGV ``agv``'s gate over its fleet ``view`` (a TickObservation): the policy's candidate picker, its
    probability, and whether to ask. Policies that draw consume one uniform from ``draw`` (default: the agent's own
    stream) per candidate; the others ask iff P = 1, as in the reference. ``free`` overrides the view's free pickers
    (the reference's sequential dispatch removes those taken earlier in the step). A broadcasting policy
    (``coordinator.broadcast``: all-to-all, the paper's Full-Graph) asks every free picker of the view at once,
    nearest first; the desk resolves the conflict (:class:`CommitmentDesk`)."""
    picker = coordinator.candidate(agv, view, free)
    if picker < 0:
        return Gate(-1, 0.0, False)
    if getattr(coordinator, "broadcast", False):
        return Gate(picker, 1.0, True, tuple(p for p in free_pickers(view, agv, free) if p != picker))
    p = coordinator.probability(agv, picker, view)
    if not coordinator.draws:
        return Gate(picker, p, p >= 1.0)
    u = draw() if draw is not None else coordinator.draw(agv)
    return Gate(picker, p, u < p)


def free_pickers(view, agv: int, free=None) -> list[int]:
    """The free pickers of ``view`` (``free`` overrides), nearest (Manhattan) to ``agv``'s target first; ties to the
    lowest id, as the nearest-picker rule."""
    free = view.free_picker if free is None else free
    pickers = [int(p) for p in free.nonzero()[0]]
    tx, ty = int(view.target[agv][0]), int(view.target[agv][1])
    cells = view.cells
    return sorted(pickers, key=lambda p: (abs(int(cells[p][0]) - tx) + abs(int(cells[p][1]) - ty), p))


# ---------------------------------------------------------------------------------------------------------------
# endpoints
# ---------------------------------------------------------------------------------------------------------------
class AgvEndpoint:
    """One AGV's side: its requests outstanding (one per picker asked: one, or every free picker when it broadcasts),
    each answered, refused or expired."""

    def __init__(self, agv: int, timeout: float = DEFAULT_REQUEST_TIMEOUT, next_seq: Callable[[], int] | None = None):
        self.agv = agv
        self.timeout = float(timeout)
        self.asked: dict[int, Request] = {}  # picker -> the request outstanding to it
        self.accepted: set[int] = set()  # pickers that accepted: their commitments are on their way
        self._seq = 0
        self._next_seq = next_seq  # a service numbers all its messages in one sequence

    @property
    def outstanding(self) -> Request | None:
        """A request still outstanding (the first sent), or None."""
        return next(iter(self.asked.values()), None)

    def receive(self, msg: Reply | Refusal, outcomes: Outcomes) -> None:
        """A reply or refusal delivered to this AGV (takes effect at once: it only frees the AGV to ask again)."""
        out = self.asked.get(msg.picker)
        if out is None:
            return  # the answer to an earlier request, already given up
        if isinstance(msg, Reply):
            if msg.request_seq and msg.request_seq != out.seq:
                return
            if msg.accepted:
                self.accepted.add(msg.picker)
            else:
                del self.asked[msg.picker]
        elif isinstance(msg, Refusal):
            del self.asked[msg.picker]
            self.accepted.discard(msg.picker)

    def may_ask(self, now: float, needs_picker: bool, outcomes: Outcomes) -> bool:
        """At this AGV's decision point: whether it may send a request, given its on-board state.

        A mission that no longer needs a picker (one was assigned, or the mission moved on) ends the outstanding
        requests; one unanswered for ``timeout`` expires and is counted."""
        if self.asked:
            if not needs_picker:
                self.asked.clear()
                self.accepted.clear()
            else:
                for picker, req in list(self.asked.items()):
                    if now - req.sent_at >= self.timeout - EPS:
                        outcomes.expired += 1
                        del self.asked[picker]
                        self.accepted.discard(picker)
        return needs_picker and not self.asked

    def request(self, picker: int, cell: tuple[int, int], now: float, outcomes: Outcomes) -> Request:
        self._seq = self._next_seq() if self._next_seq is not None else self._seq + 1
        req = Request(self.agv, picker, (int(cell[0]), int(cell[1])), now, self._seq)
        self.asked[picker] = req
        outcomes.requests += 1
        return req


#: receptions of one AGV's request a picker takes: the request and the network's copies of it (each fault in force
#: on a link delivers a message at most twice); more is not an AGV's traffic
MAX_REQUEST_COPIES = 8
#: requests a picker remembers having received (per AGV and tick), to tell a second request from a copy: more than
#: a large fleet's AGVs ask in the ticks a copy may come late
REQUESTS_REMEMBERED = 16384


class PickerEndpoint:
    """One picker's side: an inbox of delivered requests and at most one commitment in flight.

    An AGV asks a picker at most once a tick: a second, different request of that AGV for the same tick, or more
    than :data:`MAX_REQUEST_COPIES` receptions of one, is refused (ValueError) rather than held and answered, so an
    AGV cannot make a picker hold, weigh and answer thousands of requests in one decision."""

    def __init__(self, picker: int, timeout: float = DEFAULT_REQUEST_TIMEOUT,
                 next_seq: Callable[[], int] | None = None):
        self.picker = picker
        self.timeout = float(timeout)
        self._next_seq = next_seq
        self.inbox: list[tuple[float, Request]] = []  # (delivery time, request)
        self.pending: Commitment | None = None
        self.refusals: list[tuple[float, Refusal]] = []  # (delivery time, refusal) not yet taken into account
        # (agv, sent_at) -> (seq, receptions) of the requests delivered: the first is the request, the others copies
        # (told by the AGV and the tick as well as the number, so a number reused for another tick is no copy)
        self._asked: dict[tuple[int, float], tuple[int, int]] = {}
        # delivery times of copies of requests already seen, counted at the first decision point at or after them:
        # when a copy reaches a robot's process is a matter of threads, its decision points are not
        self.copies: list[float] = []
        self._seq = 0

    def receive(self, msg: Request | Refusal, due: float, outcomes: Outcomes) -> None:
        if isinstance(msg, Request):
            if self._count_reception(msg) > 1:
                self.copies.append(due)
                return
            self.inbox.append((due, msg))
        elif isinstance(msg, Refusal):
            self.refusals.append((due, msg))  # takes effect at the first decision point after it was delivered

    def _count_reception(self, msg: Request) -> int:
        """How many times ``msg`` has been received, this one included; ValueError for one a picker does not take."""
        slot = (msg.agv, msg.sent_at)
        seq, received = self._asked.get(slot, (msg.seq, 0))
        if seq != msg.seq:
            raise ValueError(f"a second request of AGV {msg.agv} sent at {msg.sent_at:g} s (number {msg.seq}; it "
                             f"asked with number {seq})")
        if received >= MAX_REQUEST_COPIES:
            raise ValueError(f"request {msg.seq} of AGV {msg.agv} received more than {MAX_REQUEST_COPIES} times")
        self._asked[slot] = (seq, received + 1)
        while len(self._asked) > REQUESTS_REMEMBERED:  # the oldest first (insertion order)
            del self._asked[next(iter(self._asked))]
        return received + 1

    def check_pending(self, now: float, assigned: bool, outcomes: Outcomes) -> None:
        """At the picker's decision point ``now``: a commitment in flight ends when its refusal was delivered by
        then, when the on-board state says the picker has a mission (it took effect), or expires unanswered after
        ``timeout``. Called at every decision point of a picker with a commitment in flight, whether or not
        requests wait (idempotent at one ``now``). Copies of requests delivered by then are counted here."""
        if self.copies:
            counted = [d for d in self.copies if d <= now + EPS]
            if counted:
                outcomes.duplicates += len(counted)
                self.copies = [d for d in self.copies if d > now + EPS]
        if self.refusals:
            due = [r for d, r in self.refusals if d <= now + EPS]
            self.refusals = [(d, r) for d, r in self.refusals if d > now + EPS]
            if self.pending is not None and any(r.commit_seq == self.pending.seq for r in due):
                self.pending = None
        if self.pending is not None and (assigned or now - self.pending.sent_at >= self.timeout - EPS):
            if not assigned:
                outcomes.commitment_expired += 1
            self.pending = None

    def decide(self, now: float, assigned: bool, rank: Mapping[int, int],
               outcomes: Outcomes, choose: Callable[[list[int]], int] | None = None
               ) -> tuple[Commitment | None, list[Reply]]:
        """At the picker's decision point ``now``: the commitment to send (or None) and the replies.

        ``assigned``: the picker's on-board state says it has a mission (then its commitment, if any, took effect).
        ``rank``: the fleet's mission order as the picker last saw it (AGV → position), the tie-break between
        requests delivered at the same time. Requests delivered after ``now`` wait for the next decision point.
        ``choose(agvs)``: the policy's choice among the requesting AGVs when the picker may commit (an index into
        ``agvs``, -1 for none; :meth:`services.policies.interface.Coordinator.choose`); default the first."""
        self.check_pending(now, assigned, outcomes)
        if not self.inbox:
            return None, []
        ready = [(due, req) for due, req in self.inbox if due <= now + EPS]
        if not ready:
            return None, []
        self.inbox = [(due, req) for due, req in self.inbox if due > now + EPS]
        last = len(rank)
        ready.sort(key=lambda dr: (dr[0], rank.get(dr[1].agv, last), dr[1].agv, dr[1].seq))
        commit = None
        replies = []
        chosen = 0
        if choose is not None and not assigned and self.pending is None:
            chosen = check_choice(choose([req.agv for _, req in ready]), len(ready), self.picker)
        for k, (_, req) in enumerate(ready):
            take = k == chosen and not assigned and self.pending is None
            if take:
                self._seq = self._next_seq() if self._next_seq is not None else self._seq + 1
                commit = Commitment(self.picker, req.agv, req.cell, now, self._seq)
                self.pending = commit
            else:
                outcomes.declined += 1
            replies.append(Reply(self.picker, req.agv, take, now, req.seq))
        return commit, replies


def check_choice(chosen, n: int, picker: int) -> int:
    """A policy's choice among ``n`` requests as an index (-1: none); ValueError naming the picker otherwise."""
    try:
        k = operator.index(chosen)
    except TypeError:
        k = None
    if k is None or not -1 <= k < n:
        raise ValueError(f"choose: picker {picker} chose {chosen!r} of {n} requests (an index, or -1 for none)")
    return k


#: commitments of one picker the desk holds at once: a picker has one in flight, and the network may deliver a copy
#: or a late one of each of the few ticks it delays; more than this is not a picker's traffic
MAX_HELD_PER_PICKER = 16


class CommitmentDesk:
    """The sim's side: commitments delivered and not yet applied, applied in order at each step boundary.

    A copy of a commitment already received counts as a duplicate. A copy is the same commitment: same picker,
    AGV, cell, tick and sequence number. Keyed by all of them, a message that reuses a picker's sequence number for
    another tick or AGV (forged, or a restarted picker numbering from one again) is judged on its own and never
    shadows the genuine commitment that later carries that number."""

    def __init__(self, dt: float):
        self.dt = float(dt)
        self.inbox: list[tuple[float, Commitment]] = []
        self._seen: dict[Commitment, float] = {}  # commitment -> its sent_at

    def receive(self, msg: Commitment, due: float, outcomes: Outcomes, now: float | None = None) -> None:
        """Hold ``msg`` (delivered at ``due``) for the next step boundary. With ``now`` (the sim time of the desk's
        current tick; a service's desk, whose commitments come over a bus from robots it does not control) it is
        first judged: ValueError, and nothing held, for a commitment sent at a tick far from ``now``
        (services/protocol/claims.py: ahead of it by more than a tick, or older than any late one) or from a picker
        that already has :data:`MAX_HELD_PER_PICKER` waiting."""
        if now is not None:
            from services.protocol.claims import TICKS_AHEAD, TICKS_BEHIND

            tick, at = round((msg.sent_at - self.dt / 2) / self.dt), round(now / self.dt)
            if tick > at + TICKS_AHEAD or tick < at - TICKS_BEHIND:
                raise ValueError(f"commitment of picker {msg.picker} of tick {tick}, the sim is at tick {at} "
                                 f"(at most {TICKS_AHEAD} ahead, {TICKS_BEHIND} behind)")
        if msg in self._seen:
            outcomes.duplicates += 1
            return
        if now is not None:
            if sum(1 for _, c in self.inbox if c.picker == msg.picker) >= MAX_HELD_PER_PICKER:
                raise ValueError(f"picker {msg.picker} has {MAX_HELD_PER_PICKER} commitments waiting already")
            if len(self._seen) > 64 * MAX_HELD_PER_PICKER:  # older ones are refused above: forget them
                oldest = now - (TICKS_BEHIND + 1) * self.dt
                self._seen = {c: sent for c, sent in self._seen.items() if sent >= oldest}
        self._seen[msg] = msg.sent_at
        self.inbox.append((due, msg))

    def settle(self, boundary: float, rank: Mapping[int, int], wanted: Mapping[int, tuple[int, int]],
               apply: Callable[[list[tuple[int, int]]], Iterable[tuple[int, int]]],
               outcomes: Outcomes) -> tuple[list[tuple[int, int]], list[Refusal]]:
        """At the step boundary: apply every commitment delivered by then, in delivery order (ties: mission order).

        ``wanted``: AGV → the cell its mission needs a picker at, now; a commitment to another cell (or to an AGV
        that needs none) is refused before it reaches the world. ``apply(pairs)`` is the world's own check (picker
        free, one picker per cell), given (picker, AGV) pairs in order and returning those it applied.
        Returns (applied pairs, refusals to send)."""
        ready = [(due, c) for due, c in self.inbox if due <= boundary + EPS]
        if not ready:
            return [], []
        self.inbox = [(due, c) for due, c in self.inbox if due > boundary + EPS]
        last = len(rank)
        ready.sort(key=lambda dc: (dc[0], rank.get(dc[1].agv, last), dc[1].picker, dc[1].seq))
        valid = [c for _, c in ready if wanted.get(c.agv) == c.cell]
        applied = set(apply([(c.picker, c.agv) for c in valid]))
        done: list[tuple[int, int]] = []
        refusals: list[Refusal] = []
        for _, c in ready:
            pair = (c.picker, c.agv)
            if pair in applied and pair not in done:
                done.append(pair)
                if c.sent_at > boundary - self.dt - EPS:
                    outcomes.on_time += 1
                else:
                    outcomes.late_applied += 1
            else:
                outcomes.refused_stale += 1
                refusals.append(Refusal(c.picker, c.agv, boundary, c.seq))
        return done, refusals


class Mailbox:
    """One robot's policy messages delivered and not yet taken by its policy (services.policies.interface.Mail).

    A message sent at tick ``t`` is taken at the robot's first decision point of a later tick by which it was
    delivered (its due time), so what a policy hears does not depend on when, within a tick, a message physically
    arrived; messages taken together come in (due, sender, the sender's order). A copy of one already held is
    dropped; more than a policy may send in one tick (``schemas.fields.MAX_POLICY_MESSAGES``) from one sender for
    one tick are refused, so a robot cannot fill another's mailbox."""

    #: ticks a message's identity is remembered after it was taken (a late duplicate beyond it would be taken again;
    #: no network here delays a copy that long)
    REMEMBER = 64

    def __init__(self) -> None:
        self.items: list[tuple[float, int, int, int, dict]] = []  # (due, sender, pseq, t sent, content)
        self._seen: dict[tuple[int, int], int] = {}  # (sender, pseq) -> tick sent
        self._sent: dict[tuple[int, int], int] = {}  # (sender, tick sent) -> its messages held or taken
        self._pseq = 0

    def next_pseq(self) -> int:
        """The number of this robot's next policy message."""
        self._pseq += 1
        return self._pseq

    def receive(self, msg, due: float) -> bool:
        """Hold policy message ``msg`` (a schemas PolicyMessage) delivered at ``due``; False for a copy of one held.
        ValueError when its content is not a packed mapping."""
        from schemas.fields import MAX_POLICY_MESSAGES
        from services.policies.interface import unpack_mail

        key = (msg.sender, msg.pseq)
        if key in self._seen:
            return False
        per_tick = (msg.sender, msg.t)
        if self._sent.get(per_tick, 0) >= MAX_POLICY_MESSAGES:
            raise ValueError(f"policy message: robot {msg.sender} sent more than {MAX_POLICY_MESSAGES} of tick {msg.t}")
        content = unpack_mail(msg.data)
        self._sent[per_tick] = self._sent.get(per_tick, 0) + 1
        self._seen[key] = msg.t
        self.items.append((due, msg.sender, msg.pseq, msg.t, content))
        return True

    def take(self, t: int, now: float) -> list:
        """The messages the decision point of tick ``t`` (at sim time ``now``) hands to the policy."""
        if not self.items:
            return []
        from services.policies.interface import Mail

        ready = [m for m in self.items if m[3] < t and m[0] <= now + EPS]
        if not ready:
            return []
        self.items = [m for m in self.items if not (m[3] < t and m[0] <= now + EPS)]
        ready.sort(key=lambda m: (m[0], m[1], m[2]))
        if len(self._seen) > 4096:
            self._seen = {k: sent for k, sent in self._seen.items() if sent >= t - self.REMEMBER}
            self._sent = {k: n for k, n in self._sent.items() if k[1] >= t - self.REMEMBER}
        return [Mail(sender, sent, content) for _, sender, _, sent, content in ready]


@dataclass
class FleetView:
    """An agent's latest view of the fleet state (a broadcast), with the sim time it describes.

    What a robot knows of the *others* is this view only; what it knows of itself comes from on board
    (:func:`with_own_state`). Its plasticity learns from each new view once (:meth:`take_new`), at its decision
    point: a view that arrives late is learnt from late, one that is lost is never learnt from."""

    view: object | None = None
    stamp: float = -1.0
    received: int = 0  # broadcasts delivered (an older one arriving after a newer one is ignored)
    learnt: float = -1.0  # the stamp of the last view learnt from

    def update(self, view, stamp: float) -> bool:
        """Take ``view`` if it is newer than the one held; returns whether it was."""
        if self.view is not None and stamp <= self.stamp + EPS:
            return False
        self.view, self.stamp = view, float(stamp)
        self.received += 1
        return True

    def age(self, now: float) -> float:
        """Sim seconds since the held view was taken (infinite before the first)."""
        return now - self.stamp if self.view is not None else float("inf")

    def take_new(self):
        """The held view if it has not been learnt from yet (it is now), else None."""
        if self.view is None or self.stamp <= self.learnt + EPS:
            return None
        self.learnt = self.stamp
        return self.view


def with_own_state(view, agent: int, cell, target):
    """The observation an agent gates with: its fleet ``view`` (a TickObservation), with its own ``cell`` and
    mission ``target`` as its on-board state gives them now (a robot knows where it is even when the fleet's
    broadcast is late). The view itself is not changed; it is returned as is when it already agrees."""
    c, g = view.cells[agent], view.target[agent]
    if c[0] == cell[0] and c[1] == cell[1] and g[0] == target[0] and g[1] == target[1]:
        return view
    cells, own_target = view.cells.copy(), view.target.copy()
    cells[agent], own_target[agent] = cell, target
    return replace_fields(view, cells=cells, target=own_target)


def view_age_stats(ages: Iterable[float | None]) -> tuple[float | None, float | None]:
    """(mean, max) of the agents' view ages, sim seconds, over the agents that hold a view (None if none does)."""
    held = [a for a in ages if a is not None and a != float("inf")]
    if not held:
        return None, None
    return sum(held) / len(held), max(held)


@dataclass
class Endpoints:
    """Every robot's protocol endpoint of one fleet (AGVs ``0..n_agvs-1``, then pickers)."""

    n_agvs: int
    n_pickers: int
    dt: float
    timeout: float = DEFAULT_REQUEST_TIMEOUT
    agvs: list[AgvEndpoint] = field(init=False)
    pickers: dict[int, PickerEndpoint] = field(init=False)
    desk: CommitmentDesk = field(init=False)
    outcomes: Outcomes = field(default_factory=Outcomes)

    def __post_init__(self) -> None:
        self.agvs = [AgvEndpoint(a, self.timeout) for a in range(self.n_agvs)]
        n = self.n_agvs + self.n_pickers
        self.pickers = {p: PickerEndpoint(p, self.timeout) for p in range(self.n_agvs, n)}
        self.desk = CommitmentDesk(self.dt)
