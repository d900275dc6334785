"""The stall watchdog: a run that stops advancing ends with a clear failure instead of a silent hang.

Every phase of a tick has a deadline, so a run without a new tick for :attr:`StallWatch.timeout` seconds is stuck
somewhere no deadline of ours reaches (inside Zenoh). :class:`StallWatch` decides, from the clock and the times it
is shown; the supervisor fails the run with :class:`~services.supervisor.errors.RunStalled`.
"""

from __future__ import annotations


def default_stall_timeout(phase_timeout: float, period: float) -> float:
    """The default: a tick may legitimately take a phase deadline per phase (or a paced period): three times that,
    at least 30 s."""
    return max(30.0, 3 * 2 * phase_timeout, 3 * period)


class StallWatch:
    """Is the run stalled? ``check(t, now)`` is shown the run's clock ``t`` (-1 before the first tick) and the
    monotonic time ``now``; a run stalls when its clock has not moved for more than ``timeout`` seconds once it
    runs. After the last tick nothing is watched: the sim ends the run."""

    def __init__(self, steps: int, timeout: float, t: int, now: float):
        self.steps = steps
        self.timeout = timeout
        self.last_tick, self.last_tick_at = t, now

    def check(self, t: int, now: float) -> bool:
        if t != self.last_tick:
            self.last_tick, self.last_tick_at = t, now
            return False
        return 0 <= t < self.steps - 1 and now - self.last_tick_at > self.timeout

    def reason(self) -> str:
        return f"no tick after tick {self.last_tick} for {self.timeout:.0f} s"
