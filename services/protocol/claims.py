"""What a receiver lets one author claim: pure bounds on ticks, outcome counts, answers per tick, header senders and
sequence numbers.

Access control (docs/deploy.md) makes sure a robot publishes only under its own keys; it cannot stop a robot (its
own credentials, used by whoever holds them) from saying anything there. These bounds are what the sim and the
monitor check before they act on what a robot says of itself, so that one robot's lies stay its own: a claim outside
them raises ``ValueError``, which the service counts as a refusal (services/intake.py) and does not act on.

Nothing here does I/O or reads a clock; the services call it with the tick they are at.
"""

from __future__ import annotations

from collections.abc import Mapping

from services.protocol.tickorder import MAX_TICK_GAP

#: ticks behind the receiver's clock a message of a tick may still come: the fault layer delays messages by a few
#: ticks at most (and the clock itself may jump this far, services/protocol/tickorder.py), so older than this is a replay
TICKS_BEHIND = MAX_TICK_GAP
#: ticks ahead of the receiver's clock: an agent answers tick t once it has it, and the monitor may see an agent's
#: message just before the sim's tick that caused it (different paths), so one tick ahead is all the protocol needs
TICKS_AHEAD = 1


def check_tick(t: int, now: int, steps: int, what: str, ahead: int = TICKS_AHEAD, behind: int = TICKS_BEHIND) -> None:
    """ValueError unless tick ``t`` of ``what`` is one the receiver at tick ``now`` can use: within ``0..steps`` and
    within ``now - behind .. now + ahead`` (``now < 0``: the receiver has no clock yet, only the run's range holds)."""
    if not 0 <= t <= steps:
        raise ValueError(f"{what} of tick {t}: outside 0..{steps} (steps)")
    if now < 0:
        return
    if t > now + ahead:
        raise ValueError(f"{what} of tick {t}: ahead of tick {now} by more than {ahead}")
    if t < now - behind:
        raise ValueError(f"{what} of tick {t}: behind tick {now} by more than {behind}")


def outcome_step_bound(n_agents: int) -> int:
    """How much one robot's outcome counter may grow per tick.

    In one tick a robot exchanges at most one dispatch message (request, reply, commitment, refusal) with each other
    robot: an AGV asks each picker at most once, a picker answers each AGV once. Each of those ends in at most one
    counted outcome, so a counter grows by at most ``n_agents`` a tick; twice that again covers the fault layer's
    copies (``duplicates``) and late messages of earlier ticks that all come due in the same tick."""
    return 4 * max(1, int(n_agents))


#: unused allowance a robot carries from quiet ticks (a burst of late outcomes after a few ticks of delay)
OUTCOME_CARRY_TICKS = MAX_TICK_GAP


class OutcomeBound:
    """Per robot, whether its cumulative outcome counts grew by more than its ticks can produce.

    Each robot has an allowance of ``per_tick`` per counter and tick since its last accepted report (carried for up
    to :data:`OUTCOME_CARRY_TICKS` ticks); a report whose increase exceeds it is refused. A report below the last
    one (a robot restarted from zero) is held to the same allowance from zero. A report older than the last taken
    is left to the tally (which ignores it)."""

    def __init__(self, per_tick: int):
        self.per_tick = int(per_tick)
        self._last: dict[object, tuple[int, dict[str, int]]] = {}  # robot -> (tick, counts) of its last report

    def check(self, who, t: int, counts: Mapping[str, int]) -> None:
        """ValueError when ``who``'s ``counts`` at tick ``t`` grew by more than allowed; else they are taken."""
        last_t, prev = self._last.get(who, (-1, {}))
        if t <= last_t:
            return
        allowance = self.per_tick * min(t - last_t, OUTCOME_CARRY_TICKS)
        restarted = any(counts.get(name, 0) < v for name, v in prev.items())
        for name, v in counts.items():
            grew = v if restarted else v - prev.get(name, 0)
            if grew > allowance:
                raise ValueError(f"outcome {name} of robot {who} grew by {grew} in {t - last_t} tick(s), at most "
                                 f"{allowance}")
        self._last[who] = (t, dict(counts))


#: copies of one answer a receiver ignores quietly: each fault in force on a link delivers a message at most twice;
#: more copies than this are not the network's, and are refused (and so counted towards a flood)
MAX_COPIES = 8


class OncePerTick:
    """One answer per (author, tick, phase): a copy the network made (same header sequence number) is ignored, up to
    :data:`MAX_COPIES` of them; a second, different answer is refused rather than taken or preferred. Remembers
    ``keep`` ticks."""

    def __init__(self, keep: int = TICKS_BEHIND + TICKS_AHEAD + 1):
        self.keep = int(keep)
        self._seen: dict[tuple[object, int, int], tuple[int, int]] = {}  # (author, t, phase) -> (header seq, copies)
        self._newest = -1

    def admit(self, who, t: int, phase: int, seq: int) -> bool:
        """True: the first answer; False: a copy of it; ValueError: a second, different answer, or a copy too many."""
        key = (who, t, phase)
        held = self._seen.get(key)
        if held is not None:
            if held[0] != seq:
                raise ValueError(f"a second answer of {who} for tick {t} (phase {phase})")
            if held[1] >= MAX_COPIES:
                raise ValueError(f"more than {MAX_COPIES} copies of {who}'s answer for tick {t} (phase {phase})")
            self._seen[key] = (seq, held[1] + 1)
            return False
        self._seen[key] = (seq, 0)
        if t > self._newest:
            self._newest = t
            if len(self._seen) > 64 * self.keep:  # older ticks are refused by the tick window before they get here
                self._seen = {k: s for k, s in self._seen.items() if k[1] >= t - self.keep}
        return True

    def forget(self, who, t: int, phase: int) -> None:
        """Undo :meth:`admit` for an answer refused on its content afterwards: it must not take the genuine one's
        place."""
        self._seen.pop((who, t, phase), None)


def agent_identity(robot: int) -> str:
    """The header sender of robot ``robot``'s own session (services/credentials.py user_of_agent names it too)."""
    return f"agent-{int(robot)}"


class SenderBinding:
    """The header sender a robot's keys may carry: its session identity ``agent-<id>``, or the first name seen under
    that robot's keys (an agent that joined without an id and claimed one has a session named after its instance).
    Any other name under the same robot's keys is refused: a robot cannot open new streams under new names."""

    def __init__(self) -> None:
        self._bound: dict[int, str] = {}

    def check(self, robot: int, sender: str) -> None:
        if not sender:
            raise ValueError(f"message under robot {robot}'s key without a sender")
        bound = self._bound.setdefault(robot, sender)  # the first name seen under the robot's keys
        if sender != bound and sender != agent_identity(robot):
            raise ValueError(f"sender {sender!r} under robot {robot}'s key, which is {bound!r}'s")


#: how far one stream's (sender, key) sequence number may jump and count as lost messages: a key carries a few
#: messages of one publisher a tick, and the tick window is TICKS_BEHIND ticks
SEQ_WINDOW = 4 * TICKS_BEHIND


class SeqWindow:
    """The sequence numbers of one stream: a number more than ``window`` ahead of the last is refused (once: it is
    neither taken nor counted as a gap, so a forged far-ahead number cannot hide the genuine stream or claim millions
    of losses), unless the next one follows it (two consecutive numbers: the stream really is there, e.g. after its
    publisher reconnected)."""

    __slots__ = ("last", "_jump")

    def __init__(self) -> None:
        self.last: int | None = None
        self._jump: int | None = None

    def take(self, seq: int, window: int = SEQ_WINDOW) -> int:
        """The messages lost before ``seq`` (0 for the next, a stale or the first); ValueError for a jump."""
        last = self.last
        if last is None:
            self.last = seq
            return 0
        if seq <= last:
            return 0
        if seq > last + window:
            resync = self._jump is not None and seq == self._jump + 1
            self._jump = seq
            if not resync:
                raise ValueError(f"sequence number {seq} jumps {seq - last} ahead of {last} (at most {window})")
            self.last = seq
            return 0
        self._jump = None
        self.last = seq
        return seq - last - 1


#: refusals of one robot's messages after which the receiver reports it as flooding (once per run): a robot that
#: follows the protocol has none (late and duplicate copies are ignored, not refused), so this many is no accident
FLOOD_REFUSALS = 256
#: refusals after which the sim cuts the robot off for the rest of the run: its messages are refused unread and its
#: robot is held, as a crashed robot's; the run goes on without it. A refusal is cheap (the bounds above, the inbox's
#: share per robot), so a burst of tens of thousands costs the run little pace and no memory, and cutting the robot
#: off would cost it that robot's work: this is for a flood that goes on (a 20-s flood at a tiny run's sim was
#: about 10,000 refusals, the rest dropped by the transport).
CUT_OFF_REFUSALS = 256 * FLOOD_REFUSALS


class FloodWatch:
    """Counts the refusals of each robot's messages; :meth:`note` says when a robot crosses :data:`FLOOD_REFUSALS`
    (reported) and :data:`CUT_OFF_REFUSALS` (cut off), once each. Robots only (ints below ``n_agents``): the table is
    bounded by the fleet."""

    def __init__(self, n_agents: int, threshold: int = FLOOD_REFUSALS, cut_off: int | None = None):
        self.n_agents, self.threshold = int(n_agents), int(threshold)
        self.cut_off = int(CUT_OFF_REFUSALS if cut_off is None else cut_off)
        self.refused: dict[int, int] = {}

    def note(self, author: object) -> int | None:
        """Count one refusal of ``author``'s; its count when this one reaches a threshold, else None."""
        if not isinstance(author, int) or isinstance(author, bool) or not 0 <= author < self.n_agents:
            return None
        count = self.refused.get(author, 0) + 1
        self.refused[author] = count
        return count if count in (self.threshold, self.cut_off) else None


#: events of one robot recorded in one tick: a robot's recorded events are a restore or cold start (once per process
#: start) and its fault layer's windows (one per command that reached it); more than this in one tick is a flood, not
#: a report (its ready answers are not recorded and not counted here)
ROBOT_EVENTS_PER_TICK = 16


def robot_event_bytes(n_agents: int) -> int:
    """The largest event payload a robot needs: a restore event carries its W row (a float per robot)."""
    return 2048 + 16 * max(1, int(n_agents))


class EventBudget:
    """Per robot, the events it may have recorded: payloads up to :func:`robot_event_bytes` and at most
    :data:`ROBOT_EVENTS_PER_TICK` a tick (the receiver's tick: a robot's events carry no tick of their own that could
    be trusted). Over either, the event is refused, so a robot cannot fill the record or the receiver's memory with
    events. Holds one counter per robot of the fleet."""

    def __init__(self, n_agents: int, per_tick: int = ROBOT_EVENTS_PER_TICK):
        self.n_agents, self.per_tick = int(n_agents), int(per_tick)
        self.max_bytes = robot_event_bytes(n_agents)
        self._used: dict[int, tuple[int, int]] = {}  # robot -> (tick, events taken in it)

    def check_size(self, robot: int, size: int) -> None:
        """ValueError for an event payload of ``size`` bytes that no robot needs (checked before it is decoded)."""
        if size > self.max_bytes:
            raise ValueError(f"event of robot {robot}: {size} bytes, at most {self.max_bytes}")

    def take(self, robot: int, now: int) -> None:
        """Count one event of robot ``robot`` to be recorded at the receiver's tick ``now``; ValueError when the robot
        has used up this tick's budget (or is not of the fleet)."""
        if not 0 <= robot < self.n_agents:
            raise ValueError(f"event of robot {robot}: outside 0..{self.n_agents - 1}")
        t, used = self._used.get(robot, (now, 0))
        if t != now:
            t, used = now, 0
        if used >= self.per_tick:
            raise ValueError(f"event of robot {robot}: more than {self.per_tick} in tick {now}")
        self._used[robot] = (t, used + 1)
