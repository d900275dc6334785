"""What the supervisor learns from the run's traffic: the sim's ticks, and the monitor's deliveries and links.

:class:`Progress` (what the live line shows, and the clock the crash faults and the stall watchdog go by),
:func:`counts_metric` and :class:`TickGate` (which samples move it) are pure; :class:`RunObserver` subscribes them
to the bus.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from services.protocol.tickorder import TickOrder


@dataclass
class Progress:
    """What the live line shows; fed from the run's metric streams :attr:`STREAMS` (and the tick from every Tick)."""

    STREAMS = ("deliveries_total", "links")

    t: int = -1
    deliveries: float = 0.0
    links: float = 0.0
    ticks_per_s: float = 0.0
    started: float | None = None
    first_t: int = 0
    finished: bool = False

    def update(self, name: str, t: int, value: float, now: float | None = None) -> None:
        """Take stream ``name``'s ``value`` at tick ``t``, seen at monotonic time ``now`` (default: this moment);
        ticks/s run from the first sample seen."""
        now = time.monotonic() if now is None else now
        if self.started is None:
            self.started, self.first_t = now, t
        if t > self.t:
            self.t = t
            if now > self.started:
                self.ticks_per_s = (t - self.first_t) / (now - self.started)
        if name == "deliveries_total":
            self.deliveries = value
        elif name == "links":
            self.links = value


def counts_metric(sender: str, t: int, steps: int) -> bool:
    """A metric sample moves the progress only when the monitor sent it for a tick within the run: progress drives
    crash faults and the stall watchdog."""
    return sender == "monitor" and 0 <= t <= steps


class TickGate:
    """Which of the run's Tick messages move the supervisor's clock: the sim's, in order (:class:`TickOrder`: a
    forged tick must not fire the crash faults of the ticks it skips), newer than the clock and before the final
    Tick ``t = steps``, which closes the run."""

    def __init__(self, steps: int):
        self.steps = steps
        self.order = TickOrder(steps)

    def admit(self, sender: str, t: int, clock: int) -> bool:
        if sender != "sim":
            return False
        try:
            if not self.order.admit(t):
                return False
        except ValueError:
            return False
        return clock < t < self.steps


class RunObserver:
    """Feeds ``progress`` from the bus; ``on_tick(t)`` runs on every tick that moved it (every tick, where the metric
    streams are decimated: crash faults hit their tick)."""

    def __init__(self, progress: Progress, steps: int, on_tick: Callable[[int], None]):
        self.progress = progress
        self.steps = steps
        self.on_tick = on_tick
        self.gate = TickGate(steps)

    async def attach(self, bus, keys) -> None:
        from schemas import MetricSample
        from schemas.tick import tick_number

        def on_metric(sample) -> None:
            try:
                msg = sample.decode(MetricSample)
            except ValueError:
                return
            if not counts_metric(sample.sender, msg.t, self.steps):
                return
            if msg.value is not None:
                self.progress.update(msg.name, msg.t, msg.value)

        for name in Progress.STREAMS:  # only what the line shows: a run has many more streams, each a message
            await bus.subscribe(keys.metric(name), on_metric)

        def on_tick(sample) -> None:
            if sample.sender != "sim":
                return  # before decoding: only the sim's ticks count
            try:
                t = tick_number(sample.payload)  # only the number (the monitor and the agents validate the rest)
            except ValueError:
                return
            if self.gate.admit(sample.sender, t, self.progress.t):
                self.progress.update("tick", t, float("nan"))
                self.on_tick(t)

        await bus.subscribe(keys.tick, on_tick)
