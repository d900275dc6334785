"""What a sim run reports: its result, and how real-time a paced run's ticks were."""

from __future__ import annotations

from dataclasses import dataclass, field

SETTLE_TICKS = 10  # a paced run's first ticks, left out of its settled interval maximum
TICK_CLOCK_POINTS = 256  # a run's tick clock keeps about this many tick starts, spread evenly over the run


@dataclass
class TickClock:
    """When ticks started, on this host's monotonic clock: every ``stride``-th tick and the final tick.

    ``time.monotonic()`` reads CLOCK_MONOTONIC, one clock for every process on the host, so an observer on the same
    host (a bench sampling the processes' CPU) can place its own readings among the sim's ticks without trusting when
    the ticks reached it: on a loaded machine they reach an observer late and in bursts."""

    stride: int = 1
    points: list[tuple[int, float]] = field(default_factory=list)

    @classmethod
    def for_steps(cls, steps: int) -> TickClock:
        return cls(stride=max(1, -(-steps // TICK_CLOCK_POINTS)))

    def started(self, t: int, now: float, *, last: bool = False) -> None:
        if last or t % self.stride == 0:
            self.points.append((t, now))

    def summary(self) -> list[list[float]]:
        return [[t, round(now, 6)] for t, now in self.points]


@dataclass
class Pace:
    """When the ticks of a paced run started (wall clock): what the fleet saw of its real-time period."""

    period: float = 0.0
    ticks: int = 0
    interval_max: float = 0.0  # wall seconds between two tick starts, at most
    interval_min: float = float("inf")  # ... and at least
    interval_sum: float = 0.0
    late: int = 0  # intervals longer than 1.5 periods
    early: int = 0  # intervals shorter than half a period (a tick after one that overran its period)
    rescheduled: int = 0  # times the sim was more than a period behind and started again from the present
    worst: list[tuple[int, float]] = field(default_factory=list)  # the 5 longest intervals: (tick, seconds)
    # the longest interval once the fleet has settled: the first ticks wait for processes still warming up (their
    # first messages, the first plans), which a real fleet's start hides too
    interval_max_settled: float = 0.0
    _last: float | None = None

    def started(self, t: int, now: float) -> None:
        if self._last is not None:
            gap = now - self._last
            self.interval_sum += gap
            self.interval_max = max(self.interval_max, gap)
            if t > SETTLE_TICKS:
                self.interval_max_settled = max(self.interval_max_settled, gap)
            self.interval_min = min(self.interval_min, gap)
            self.late += gap > 1.5 * self.period
            self.early += gap < 0.5 * self.period
            self.worst = sorted([*self.worst, (t, gap)], key=lambda w: -w[1])[:5]
        self._last = now
        self.ticks += 1

    def summary(self) -> dict:
        n = max(1, self.ticks - 1)
        return {"period": self.period, "ticks": self.ticks, "interval_mean": round(self.interval_sum / n, 4),
                "interval_min": round(self.interval_min, 4) if self.ticks > 1 else None,
                "interval_max": round(self.interval_max, 4),
                "interval_max_settled": round(self.interval_max_settled, 4), "late": self.late, "early": self.early, "rescheduled": self.rescheduled,
                "worst": [[t, round(g, 4)] for t, g in self.worst]}


@dataclass
class SimResult:
    steps: int = 0
    deliveries: int = 0
    per_tick_deliveries: list[int] = field(default_factory=list)
    commits_applied: int = 0
    rejected: int = 0
    absences: int = 0
    flooding: list[int] = field(default_factory=list)  # robots reported for flooding (agent.flooding events)
    cut_off: list[int] = field(default_factory=list)  # robots cut off for flooding (agent.cut_off events)
    wall_seconds: float = 0.0
    stopped_early: str | None = None
    protocol: dict[str, int] = field(default_factory=dict)  # the dispatch protocol's outcome counters (sim + robots)
    network_stops: int = 0  # robot-steps a network profile's silence stop held a robot in place
    pace: Pace = field(default_factory=Pace)  # paced mode: the tick starts' intervals
    tick_clock: TickClock = field(default_factory=TickClock)  # when the ticks started (monotonic clock)
    # wall seconds spent per part of the tick (where a distributed tick's time goes)
    phase_seconds: dict[str, float] = field(default_factory=lambda: {
        "controller": 0.0, "tick_phase": 0.0, "resolve_phase": 0.0, "step": 0.0})

    @property
    def ticks_per_s(self) -> float:
        return self.steps / self.wall_seconds if self.wall_seconds > 0 else 0.0
