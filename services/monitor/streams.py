"""The monitor's metric streams: the per-message statistics, and subscriber helpers.

Every stream is published on ``morph/<run>/metrics/<name>`` as a :class:`~schemas.MetricSample` (a
versioned wire message carrying the tick ``t`` and the sim time), at most ``--max-rate`` updates per second per stream
(the monitor's publish path), and answered from the latest value on ``get morph/<run>/state/metrics/<name>``.

Names, units and meanings are in :mod:`services.metrics.catalogue`. The row streams come from the monitor's per-tick
rows (``metrics.csv``); :class:`MessageStats` adds the statistics that come from the messages themselves (counts,
drops by sequence gaps, latency, dispatch delay).
"""

from __future__ import annotations

import asyncio
import bisect
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable

import numpy as np

from schemas import MetricSample
from services.metrics.catalogue import RATE_WINDOW, sample

#: Histogram bucket boundaries (seconds): prometheus_client's defaults, also OTel's for messaging durations.
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.25, 0.5, 0.75, 1.0, 2.5, 5.0, 7.5, 10.0)
#: Dispatch delay is in sim seconds (one step = Δ, 1 s by default): buckets of a few steps up to minutes.
DISPATCH_BUCKETS = (0.0, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0)


class Histogram:
    """Cumulative bucket counts, sum and count (Prometheus semantics; no I/O)."""

    def __init__(self, bounds: tuple[float, ...]):
        self.bounds = tuple(bounds)
        self.counts = [0] * (len(self.bounds) + 1)  # last = +Inf
        self.sum = 0.0
        self.count = 0

    def observe(self, value: float) -> None:
        i = bisect.bisect_left(self.bounds, value)  # np.searchsorted(side="left") without numpy: once per message
        self.counts[i] += 1
        self.sum += value
        self.count += 1

    def cumulative(self) -> list[tuple[str, int]]:
        out, acc = [], 0
        for bound, c in zip([*map(str, self.bounds), "+Inf"], self.counts):
            acc += c
            out.append((bound, acc))
        return out


# A stream (sender, key) whose sequence number jumps further than this is refused: no run loses that many messages
# of one stream between two that arrive. Streams are tracked up to MAX_STREAMS (senders are named by the header).
MAX_SEQ_JUMP = 10_000
MAX_STREAMS = 65_536


class MessageStats:
    """Statistics of the monitor's incoming messages (pure bookkeeping; the monitor feeds it every sample)."""

    def __init__(self, n_agents: int, dt: float):
        self.n = n_agents
        self.dt = dt
        self.by_kind: dict[str, int] = {}
        self.total = 0
        self.gaps = 0
        self.rejected = 0
        self.clock = "wall"  # clock of the latencies: "wall" seconds or "sim" seconds (virtual time)
        self._last_seq: dict[tuple[str, str], int] = {}
        self._latency: deque[tuple[float, float]] = deque()  # (receive time, latency)
        self.latency = Histogram(LATENCY_BUCKETS)
        self.dispatch = Histogram(DISPATCH_BUCKETS)
        self._waiting: dict[int, int] = {}  # AGV -> tick of its first unanswered request
        self._dispatch_by_tick: dict[int, list[float]] = {}
        self._deliveries: deque[int] = deque(maxlen=RATE_WINDOW)
        self._dispatch_row: tuple[int, float, float] | None = None  # (t, sim time, mean delay), not yet published

    def observe(self, kind: str, key: str, sender: str, seq: int, sent_at: float, now: float | None = None,
                clock: str = "wall") -> bool:
        """Count one message; False (the caller rejects it) when its sequence number jumps further ahead of its
        stream than any real loss could (a forged header would otherwise turn into millions of "lost" messages).
        Its latency is ``now`` (default: wall time) minus ``sent_at``, both in ``clock`` ("wall" seconds, or "sim"
        seconds of a virtual-time run)."""
        self.total += 1
        self.by_kind[kind] = self.by_kind.get(kind, 0) + 1
        if sender and seq:
            last = self._last_seq.get((sender, key))
            if last is not None and seq > last + MAX_SEQ_JUMP:
                return False
            if last is not None and seq > last + 1:
                self.gaps += seq - last - 1
            if (last is None and len(self._last_seq) < MAX_STREAMS) or (last is not None and seq > last):
                self._last_seq[(sender, key)] = seq
        if sent_at > 0:
            self.clock = clock
            now = time.time() if now is None else now
            lat = max(0.0, now - sent_at)
            self.latency.observe(lat)
            self._latency.append((now, lat))
            while self._latency and self._latency[0][0] < now - 1.0:
                self._latency.popleft()
        return True

    def requested(self, t: int, agv: int) -> None:
        self._waiting.setdefault(agv, t)

    def committed(self, t: int, agv: int) -> None:
        first = self._waiting.pop(agv, None)
        if first is not None:
            delay = (t - first) * self.dt
            self.dispatch.observe(delay)
            self._dispatch_by_tick.setdefault(t, []).append(delay)

    def latency_quantiles(self) -> list[float]:
        if not self._latency:
            return [math.nan] * 3
        lat = np.array([x for _, x in self._latency], dtype=float)
        return [float(q) for q in np.quantile(lat, (0.5, 0.9, 0.99))]

    def row(self, values: dict) -> None:
        """Account the row ``values`` just finalised (t, sim_time, deliveries …): every row, in order."""
        t = values["t"]
        self._deliveries.append(int(values.get("deliveries") or 0))
        delays = [d for k in [k for k in self._dispatch_by_tick if k <= t] for d in self._dispatch_by_tick.pop(k)]
        if delays:  # the newest row with dispatches is what the (decimated) stream shows
            self._dispatch_row = (t, values.get("sim_time") or t * self.dt, float(np.mean(delays)))

    def samples(self, values: dict) -> list[MetricSample]:
        """The message streams as of the newest row ``values`` (:meth:`row` has seen it): built when published."""
        t = values["t"]
        sim_time = values.get("sim_time") or t * self.dt
        out = [
            sample("delivery_rate", t, sim_time, value=sum(self._deliveries) / (len(self._deliveries) * self.dt)),
            sample("messages_total", t, sim_time, value=float(self.total),
                   labels={k: str(v) for k, v in sorted(self.by_kind.items())}),
            sample("drops_total", t, sim_time, value=float(self.gaps + self.rejected),
                   labels={"sequence_gaps": str(self.gaps), "rejected": str(self.rejected)}),
            sample("agents_alive", t, sim_time, value=float(values.get("acks") or 0)),
        ]
        if self._dispatch_row is not None:
            at, at_time, delay = self._dispatch_row
            self._dispatch_row = None
            out.append(sample("dispatch_delay", at, at_time, value=delay))
        q = self.latency_quantiles()
        if all(math.isfinite(x) for x in q):
            out.append(sample("latency_seconds", t, sim_time, values=q, labels={"quantiles": "0.5,0.9,0.99", "clock": self.clock}))
        return out


# -- subscribers --------------------------------------------------------------------------------------------------
class Decimator:
    """Per-stream rate limit for a slow subscriber: pass at most ``max_rate`` samples per second per stream name.

    The newest sample of a suppressed burst is kept (``pending``) so the subscriber can flush it: a view never ends
    on a stale value.
    """

    def __init__(self, max_rate: float, clock: Callable[[], float] = time.monotonic):
        if max_rate < 0:
            raise ValueError(f"max_rate: must be >= 0, got {max_rate}")
        self.max_rate = max_rate
        self.clock = clock
        self._last: dict[str, float] = {}
        self.pending: dict[str, MetricSample] = {}
        self.suppressed = 0

    def admit(self, sample: MetricSample) -> bool:
        if self.max_rate == 0:
            return True
        now = self.clock()
        last = self._last.get(sample.name)
        if last is not None and now - last < 1.0 / self.max_rate:
            self.pending[sample.name] = sample
            self.suppressed += 1
            return False
        self._last[sample.name] = now
        self.pending.pop(sample.name, None)
        return True


async def subscribe_metrics(bus, run_id: str, handler: Callable[[MetricSample], Awaitable[None] | None], *,
                            names: str = "**", max_rate: float = 0.0):
    """Subscribe ``handler`` to the run's metric streams, decimated to ``max_rate`` per stream (0 = all)."""
    from schemas.keys import RunKeys

    keys = RunKeys(run_id)
    dec = Decimator(max_rate)

    async def on_sample(sample) -> None:
        try:
            metric = sample.decode(MetricSample)
        except ValueError:
            return
        if dec.admit(metric):
            result = handler(metric)
            if asyncio.iscoroutine(result):
                await result

    expr = keys.metrics if names == "**" else keys.metric(names)
    return await bus.subscribe(expr, on_sample)
