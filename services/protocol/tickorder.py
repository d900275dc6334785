"""Which ticks a receiver takes: the sim's clock only moves forward, one tick at a time, and ends at ``steps``.

Every receiver of the sim's ticks (an agent its on-board state ``sim/@onboard/<id>``, the monitor ``sim/tick``) checks
each tick with a :class:`TickOrder` before acting on it,
so that a tick that the sim cannot have sent (forged, or replayed out of place) is refused instead of moving the
receiver's clock: a receiver that took a tick ``t = 100000`` would drop every real tick after it as stale.

The rules (``last`` is the last tick taken):

* ``t`` outside ``0..steps`` is refused (ValueError: the caller counts a reject with the reason);
* ``t <= last`` is stale or a duplicate: ignored, not an error (the fault layer duplicates and reorders);
* the first tick a receiver sees is taken whatever its number (a restarted agent or monitor joins mid-run);
* ``t == last + 1`` is taken; so is a jump of at most ``max_gap`` ticks (ticks lost in transit, e.g. to a loss
  fault, leave such gaps);
* **resync**: a longer jump is refused, unless the tick right before it was refused as a jump too (two consecutive
  ticks beyond the gap: the clock really is there, e.g. after a partition healed). A lone far-ahead tick can therefore
  never move a receiver's clock.

On an open (``--insecure``) endpoint a forger who sends consecutive plausible ticks is not stopped by this; the
endpoint's access control is what stops anyone but the sim from publishing ticks (docs/deploy.md).
"""

from __future__ import annotations

MAX_TICK_GAP = 64


class TickOrder:
    def __init__(self, steps: int, max_gap: int = MAX_TICK_GAP):
        self.steps = int(steps)
        self.max_gap = int(max_gap)
        self.last = -1
        self._refused_jump: int | None = None

    def admit(self, t: int) -> bool:
        """True: take tick ``t`` (``last`` becomes ``t``); False: stale, ignore it; ValueError: refuse it."""
        if not 0 <= t <= self.steps:
            raise ValueError(f"tick t={t} outside 0..{self.steps} (steps)")
        if t <= self.last:
            return False
        if self.last >= 0 and t - self.last > self.max_gap:
            resync = self._refused_jump is not None and t == self._refused_jump + 1
            if not resync:
                self._refused_jump = t
                raise ValueError(f"tick t={t} jumps {t - self.last} ticks ahead of t={self.last} (at most "
                                 f"{self.max_gap} unless the next tick confirms it)")
        self._refused_jump = None
        self.last = t
        return True
