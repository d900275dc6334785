"""The live line of ``morph-sim up``: what the run is at, as one line shown four times a second.

:func:`live_line` is pure (the line for a state of :class:`~services.supervisor.observer.Progress`);
:class:`LiveLine` paces it and hands it to the caller's ``on_progress(progress, line)``.
"""

from __future__ import annotations

from collections.abc import Callable

SHOW_EVERY = 0.25  # seconds between live lines; also the longest the supervisor's loops sleep without news


def live_line(progress, *, steps: int, n_agents: int, endpoint: str) -> str:
    """Before the first tick: who is awaited where; then the tick, deliveries, links and ticks/s."""
    p = progress
    if p.t < 0:
        return f"waiting for {n_agents} agents to join {endpoint} …"
    return (f"tick {p.t + 1}/{steps}  deliveries {p.deliveries:.0f}  links {p.links:.0f}  "
            f"{p.ticks_per_s:.0f} ticks/s")


class LiveLine:
    """Shows the line through ``on_progress`` (None: nobody watches), at most once per :data:`SHOW_EVERY`."""

    def __init__(self, on_progress: Callable[[object, str], None] | None, *, steps: int, n_agents: int,
                 endpoint: str):
        self.on_progress = on_progress
        self.steps, self.n_agents, self.endpoint = steps, n_agents, endpoint
        self.last_shown = 0.0  # monotonic time of the last paced line

    def due(self, now: float) -> bool:
        """A paced line is due at ``now`` (monotonic): it counts as shown from then on."""
        if now - self.last_shown >= SHOW_EVERY:
            self.last_shown = now
            return True
        return False

    def next_in(self, now: float) -> float:
        """Seconds from ``now`` until the next paced line (at least 10 ms, so a late loop still yields)."""
        return max(0.01, self.last_shown + SHOW_EVERY - now)

    def show(self, progress) -> None:
        self.say(progress, live_line(progress, steps=self.steps, n_agents=self.n_agents, endpoint=self.endpoint))

    def say(self, progress, line: str) -> None:
        if self.on_progress is not None:
            self.on_progress(progress, line)
