"""The shared air as pure code: every message that crosses a profile's rate-limited radio, judged by one
:class:`~services.faults.network.NetworkModel` in one deterministic order.

A queue's verdict on a message depends on every message that entered the queue before it, from any robot. So where a
network profile limits rates (``link_rate``, ``ap_rate``), one judge must see all of a run's radio traffic and take
it in an order that does not depend on who saw what first: by send time, then publisher (the sim before the robots,
robots by id), key and sequence number, and each publication's copies by receiver. The lab's event network
(morph_sim/lab/network.py) and the services' medium process (services/air/) both judge through :class:`Medium`, so
they give every message the same fate.

A message's bytes on the radio are the protocol's own definition (:func:`radio_size`), the same in every driver:
a dispatch message's encoded size (one representative per kind: sizes of one kind differ only by a few bytes of
integers), a policy message's encoded payload, and a fleet broadcast's observation fields (the services' Tick
carries the world's record too, which is not radio traffic: the monitor is wired).

In a distributed run the medium learns what was sent at each instant from the sim (:class:`Ledger`): after each
phase the sim lists the publications it knows of (its own, and the robots' from their acks), and the medium judges
them once all have reached it. The sim's part of an instant (its refusals and the fleet broadcast) is judged before
the robots act on it, the robots' part once they have answered.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

from schemas.keys import FLEET
from services.faults.network import Fate, NetworkModel

#: the sim's part of an instant (its refusals, the fleet broadcast) and the robots' part (what they sent when acting)
SIM_PART, ROBOTS_PART = 0, 1
_ROUND = 9  # send times are sums of Δ and Δ/2: equal instants compare equal after rounding


def publisher_rank(publisher: int | str) -> int:
    """The sim publishes first at an instant (its Tick and refusals come before the robots act on them); robots by
    id."""
    return -1 if publisher == "sim" else int(publisher)


def receiver_rank(receiver: int | str) -> tuple[int, int]:
    return (0, -1) if receiver == "sim" else (1, int(receiver)) if isinstance(receiver, int) else (2, 0)


def part_of(publisher: int | str) -> int:
    return SIM_PART if publisher == "sim" else ROBOTS_PART


def instant(sent_at: float) -> float:
    return round(float(sent_at), _ROUND)


@dataclass(frozen=True, slots=True)
class Publication:
    """One message as published once (a fleet broadcast or a policy message to everyone reaches several
    receivers): its identity is (publisher, key, seq), ``key`` relative to ``morph/<run>/``."""

    sent_at: float
    publisher: int | str
    key: str
    seq: int
    receivers: tuple[int | str, ...]
    size: int

    def order(self) -> tuple:
        return (instant(self.sent_at), publisher_rank(self.publisher), self.key, self.seq)


@dataclass(frozen=True, slots=True)
class Verdict:
    """The radio's verdict on one copy: delivered at ``at`` (sim seconds) or lost with ``cause``."""

    publisher: int | str
    key: str
    seq: int
    receiver: int | str
    at: float | None
    cause: str | None = None

    @property
    def fate(self) -> Fate:
        return Fate(self.at, self.cause)


class Medium:
    """The judge of a run's radio: publications in, verdicts out, in :meth:`Publication.order` whatever order they
    are given in (the draws are hashes of the message identity; only the queues depend on order)."""

    def __init__(self, model: NetworkModel):
        self.model = model
        # the protocol's messages (every publication but the fleet broadcast) and their bytes on the radio, counted
        # once per publication as a bus sends it: the lab's messages_sent and bytes_sent
        self.messages = 0
        self.bytes = 0

    def judge(self, publications: Iterable[Publication]) -> list[Verdict]:
        out: list[Verdict] = []
        fate = self.model.fate
        for pub in sorted(publications, key=Publication.order):
            if pub.key != FLEET:
                self.messages += 1
                self.bytes += pub.size
            identity = ((pub.publisher, pub.seq), pub.key)  # as a receiver's fault layer names it
            for receiver in sorted(pub.receivers, key=receiver_rank):
                f = fate(pub.sent_at, pub.publisher, receiver, identity, size=pub.size)
                out.append(Verdict(pub.publisher, pub.key, pub.seq, receiver, f.delivered_at, f.cause))
        return out


def has_shared_capacity(profile) -> bool:
    """Whether a network profile's verdicts depend on other robots' traffic (rate limits with queues)."""
    return profile is not None and profile.shared_capacity


# -- sizes --------------------------------------------------------------------------------------------------------------
_KIND_SIZES: dict[str, int] = {}


def dispatch_size(kind: str) -> int:
    """Bytes of a dispatch message of ``kind`` (request, reply, commit, refusal) on the radio."""
    size = _KIND_SIZES.get(kind)
    if size is None:
        from schemas import Commit, HelpReply, HelpRequest
        from schemas.codec import encode

        if kind == "request":
            wire = HelpRequest(t=100, agv=1, picker=2, target_x=10, target_y=10, seq=100)
        elif kind == "reply":
            wire = HelpReply(t=100, picker=2, agv=1, accepted=True, seq=100)
        elif kind in ("commit", "refusal"):  # the same three numbers and a sequence number
            wire = Commit(t=100, picker=2, agv=1, seq=100)
        else:
            raise ValueError(f"no dispatch message kind {kind!r}")
        size = _KIND_SIZES[kind] = len(encode(wire))
    return size


def fleet_size(obs, dt: float) -> int:
    """Bytes of the fleet broadcast of ``obs`` (a TickObservation) on the radio: its observation fields."""
    from schemas.tick import encode_tick_body, tick_fields

    return len(encode_tick_body(tick_fields(obs, obs.t * dt)))


def kind_of(rel_key: str) -> str:
    """The radio kind of a key relative to ``morph/<run>/``: request, reply, commit, policy, refusal, fleet; else
    ''."""
    chunks = rel_key.split("/")
    if chunks[0] == "agent" and len(chunks) >= 3 and chunks[2] in ("request", "reply", "commit", "policy"):
        return chunks[2]
    if chunks[0] == "sim" and len(chunks) >= 2:
        if chunks[1] == "refusal":
            return "refusal"
        if chunks[1] == "fleet":
            return "fleet"
    return ""


def receivers_of(rel_key: str, publisher: int | str, n_robots: int) -> tuple[int | str, ...]:
    """Who a publication on ``rel_key`` reaches over the radio."""
    chunks = rel_key.split("/")
    kind = kind_of(rel_key)
    if kind == "fleet":
        return tuple(range(n_robots))
    if kind == "commit":
        return ("sim",)
    if kind == "refusal":
        return (int(chunks[2]),)
    if kind == "policy" and chunks[3] == "all":
        return tuple(r for r in range(n_robots) if r != publisher)
    if kind in ("request", "reply", "policy"):
        return (int(chunks[3]),)
    return ()


# -- a distributed run's bookkeeping ------------------------------------------------------------------------------------
@dataclass
class _Part:
    sent_at: float
    part: int
    wanted: dict[tuple[int | str, str], int]  # (publisher, key) -> publications announced


@dataclass
class Ledger:
    """The medium's bookkeeping in a distributed run (no I/O): what the sim announced was sent at each instant and
    what has arrived, in; the verdicts of each part once all of it is here, out, in the order of the parts.

    ``announce(sent_at, part, counts)`` lists the publications of one part of an instant as
    ``{(publisher, key): count}``; ``arrive(pub)`` gives one that reached the medium. Parts are judged in the order
    they were announced (the sim announces them in time order); a part waits for all it announced. A publication
    that no announced part expects (a robot that answered too late to be counted, a forged one) is judged when it
    arrives if its part was judged already, else when its part is."""

    medium: Medium
    parts: list[_Part] = field(default_factory=list)
    arrived: dict[tuple[float, int], list[Publication]] = field(default_factory=dict)
    judged_through: tuple[float, int] = (-1.0, -1)
    judged: int = 0
    strays: int = 0
    #: called after each part is judged, with its (send time, part): a point in the judging that is the same in every
    #: run of the same configuration (the air publishes its per access point counters there)
    on_part: Callable[[float, int], None] | None = None

    def announce(self, sent_at: float, part: int, counts: dict[tuple[int | str, str], int]) -> list[Verdict]:
        self.parts.append(_Part(instant(sent_at), part, {k: v for k, v in counts.items() if v > 0}))
        return self._judge_ready()

    def arrive(self, pub: Publication) -> list[Verdict]:
        where = (instant(pub.sent_at), part_of(pub.publisher))
        if where <= self.judged_through:
            self.strays += 1
            return self.medium.judge([pub])
        self.arrived.setdefault(where, []).append(pub)
        return self._judge_ready()

    def waiting_for(self) -> dict[tuple[int | str, str], int]:
        """What the oldest announced part still waits for: {(publisher, key): publications missing}."""
        if not self.parts:
            return {}
        head = self.parts[0]
        have = self._counts(self.arrived.get((head.sent_at, head.part), ()))
        return {k: n - have.get(k, 0) for k, n in head.wanted.items() if have.get(k, 0) < n}

    def force(self) -> list[Verdict]:
        """Judge the oldest announced part with what has arrived of it (a publication announced and never sent must
        not stall the run; the driver decides when to give up waiting)."""
        if not self.parts:
            return []
        head = self.parts[0]
        head.wanted = {}
        return self._judge_ready()

    @staticmethod
    def _counts(pubs: Sequence[Publication]) -> dict[tuple[int | str, str], int]:
        out: dict[tuple[int | str, str], int] = {}
        for p in pubs:
            out[(p.publisher, p.key)] = out.get((p.publisher, p.key), 0) + 1
        return out

    def _judge_ready(self) -> list[Verdict]:
        out: list[Verdict] = []
        while self.parts and not self.waiting_for():
            head = self.parts.pop(0)
            where = (head.sent_at, head.part)
            # everything before this part that arrived unannounced goes first, in order
            for earlier in sorted(k for k in self.arrived if k < where):
                self.strays += len(self.arrived[earlier])
                out += self.medium.judge(self.arrived.pop(earlier))
            pubs = self.arrived.pop(where, [])
            self.judged += len(pubs)
            out += self.medium.judge(pubs)
            self.judged_through = max(self.judged_through, where)
            if self.on_part is not None:
                self.on_part(head.sent_at, head.part)
        return out


__all__ = ["ROBOTS_PART", "SIM_PART", "Ledger", "Medium", "Publication", "Verdict", "dispatch_size", "fleet_size",
           "has_shared_capacity", "kind_of", "receivers_of"]


class VerdictBook:
    """A receiver's side of the air (no I/O): the verdicts on its radio messages and the messages that reached it
    before their verdict. A message counts as arrived only with both, so a decision point that waits for it waits for
    the air too. Bounded: the oldest entries go first beyond ``limit`` (a verdict or a message that never finds its
    partner: a message of a robot nobody announced, a verdict of a copy this receiver's transport never saw)."""

    def __init__(self, limit: int = 65536):
        self.limit = limit
        self.verdicts: dict[tuple, Fate] = {}
        self.parked: dict[tuple, list] = {}
        self.dropped = 0

    def verdict(self, identity: tuple, fate: Fate) -> list:
        """The air's verdict on ``identity`` (publisher, key, seq); returns what was parked waiting for it."""
        self.verdicts[identity] = fate
        self._bound(self.verdicts)
        return self.parked.pop(identity, [])

    def take(self, identity: tuple) -> Fate | None:
        """The verdict on ``identity`` if it came (kept: one message may reach several subscriptions)."""
        return self.verdicts.get(identity)

    def park(self, identity: tuple, item) -> None:
        self.parked.setdefault(identity, []).append(item)
        self._bound(self.parked)

    def _bound(self, table: dict) -> None:
        while len(table) > self.limit:
            del table[next(iter(table))]
            self.dropped += 1
