"""Virtual time for fault injection (docs/faults.md): latency and deadlines in sim seconds, deterministic.

Within one phase of a tick everything happens at the same sim time: the phase's boundary. A message sent at sim
time ``s`` with latency ``L`` is released at the first phase boundary ``b >= s + L``. The receiver's deadline for a
phase is the boundary that closes it, so a message released at a later boundary is *late*: the protocol drops it as
stale (a late ack means no action that tick), and :class:`VirtualTime` counts it.

Phase boundaries of tick ``t`` with Δ seconds per step (:func:`boundaries`)::

    t·Δ            Tick published (TICK phase opens)
    t·Δ + Δ/2      TICK phase deadline; Resolve published (RESOLVE phase opens)
    (t+1)·Δ        RESOLVE phase deadline; the world steps; next Tick

The seam: whoever owns the phase loop (the sim clock; in another process, the agent when a Tick or Resolve of the
sim *arrives* — its stamp is the boundary — before it is handled, dropped or held) calls :meth:`VirtualTime.advance`
with the boundary it has reached, which releases every held message due by then,
in (due time, sender, key, sequence) order — an order that does not depend on arrival order, so the run does not
depend on process timing. A bus stamps its samples with :meth:`VirtualTime.now` (``bus.set_clock(vt.now)``), so the
send time ``s`` is the sender's current boundary.

Nothing here sleeps or reads the wall clock: the same seed and fault configuration give the same releases on any
machine. Wall-time runs do not use this module (the fault layer then uses ``loop.call_later``: real sleeps).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

# Boundaries are sums of floats (t·Δ + Δ/2, s + L): compare with a tolerance so that a latency of exactly half a
# step lands on the half-step boundary rather than one boundary later because of rounding.
EPS = 1e-9

PHASES_PER_TICK = 2


def boundaries(t: int, dt: float) -> tuple[float, float, float]:
    """(tick start, TICK deadline = resolve start, RESOLVE deadline = next tick start) of tick ``t``, sim seconds."""
    start = t * dt
    return start, start + dt / PHASES_PER_TICK, (t + 1) * dt


def release_boundary(due: float, dt: float) -> float:
    """The first phase boundary at or after ``due`` (boundaries are the multiples of Δ/2)."""
    step = dt / PHASES_PER_TICK
    k = -(-(due - EPS) // step)  # ceil with tolerance
    return max(0.0, k * step)


@dataclass(order=True)
class _Held:
    due: float
    order: tuple
    fn: Callable[[], None] = field(compare=False)
    deadline: float | None = field(compare=False, default=None)


@dataclass
class VirtualTimeStats:
    held: int = 0  # messages that had to wait for a boundary
    released: int = 0
    late: int = 0  # released after the deadline the sender gave them
    dropped_at_close: int = 0


class VirtualTime:
    """A sim-seconds clock advanced by phase boundaries, holding delayed messages until their boundary.

    Several fault layers (one per bus) may share one VirtualTime when all participants live in one process
    (LocalBus); each process has its own otherwise.
    """

    def __init__(self, dt: float = 1.0, start: float = 0.0):
        if not dt > 0:
            raise ValueError(f"dt: must be > 0, got {dt}")
        self.dt = float(dt)
        self.phase = self.dt / PHASES_PER_TICK  # a message's deadline is one phase after it was sent
        self._now = float(start)
        self._heap: list[_Held] = []
        self._tie = itertools.count()
        self._listeners: list[Callable[[float], None]] = []
        self.stats = VirtualTimeStats()

    def now(self) -> float:
        """Current sim time: the last boundary reached."""
        return self._now

    @property
    def pending(self) -> int:
        return len(self._heap)

    def on_advance(self, fn: Callable[[float], None]) -> None:
        """Call ``fn(boundary)`` after every advance (fault auto-heal, metrics)."""
        self._listeners.append(fn)

    def hold(self, due: float, fn: Callable[[], None], *, order: tuple = (), deadline: float | None = None) -> bool:
        """Run ``fn`` at the first boundary at or after ``due``; at once (returns True) if that is now.

        ``order`` breaks ties between messages due at the same time (sender, key, seq): pass it so the release
        order does not depend on arrival order. ``deadline`` (sim seconds), if given, marks the message late when
        it is released after it.
        """
        if due <= self._now + EPS:
            fn()
            return True
        self.stats.held += 1
        heapq.heappush(self._heap, _Held(due, (*order, next(self._tie)), fn, deadline))
        return False

    def deadline_of(self, sent_at: float) -> float:
        """The deadline of a message sent at ``sent_at``: the boundary that closes the phase it was sent in."""
        return release_boundary(sent_at, self.dt) + self.phase if sent_at >= 0 else self._now + self.phase

    def is_late(self, sent_at: float) -> bool:
        """Would a message sent at ``sent_at`` be late if handled now?"""
        return self._now > self.deadline_of(sent_at) + EPS

    def schedule(self, delay: float, fn: Callable[[], None]) -> None:
        """``FaultLayer`` scheduler form: ``fn`` after ``delay`` sim seconds from now."""
        self.hold(self._now + delay, fn)

    def advance(self, boundary: float) -> int:
        """Move to ``boundary`` and release every message due by then; returns how many were released.

        Time never goes backwards: an older boundary (a duplicated or reordered Tick) releases nothing new.
        """
        if boundary > self._now:
            self._now = float(boundary)
        released = 0
        heap = self._heap
        while heap and heap[0].due <= self._now + EPS:
            held = heapq.heappop(heap)
            if held.deadline is not None and self._now > held.deadline + EPS:
                self.stats.late += 1
            held.fn()
            released += 1
        self.stats.released += released
        for fn in self._listeners:
            fn(self._now)
        return released

    def clear(self) -> int:
        """Forget every held message (end of run); returns how many were dropped."""
        n = len(self._heap)
        self._heap.clear()
        self.stats.dropped_at_close += n
        return n
