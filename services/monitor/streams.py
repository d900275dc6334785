"""The monitor's metric streams: the per-message statistics, their publication, and subscriber helpers.

Every stream is published on ``morph/<run>/metrics/<name>`` as a :class:`~schemas.MetricSample` (a
versioned wire message carrying the tick ``t`` and the sim time), at most ``--max-rate`` updates per second per stream
(the monitor's publish path), and answered from the latest value on ``get morph/<run>/state/metrics/<name>``.

Names, units and meanings are in :mod:`services.metrics.catalogue`. The row streams come from the monitor's per-tick
rows (``metrics.csv``); :class:`MessageStats` adds the statistics that come from the messages themselves (counts,
drops by sequence gaps, latency, dispatch delay); :class:`StreamPublisher` decimates and publishes them all.
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
from services.metrics.catalogue import CATALOGUE, RATE_WINDOW, ROW, sample
from services.protocol.claims import SeqWindow

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


# Streams (sender, key) tracked; each one's sequence numbers may jump at most SEQ_WINDOW (services/protocol/claims.py).
# The monitor refuses a header sender under a robot's key that is not that robot's before it gets here, so the
# streams are the authenticated authors' own.
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
        #: refusals per robot (services.protocol.claims.FloodWatch.refused, bounded by the fleet)
        self.refused_by_robot: dict[int, int] = {}
        self.clock = "wall"  # clock of the latencies: "wall" seconds or "sim" seconds (virtual time)
        self._seq: dict[tuple[str, str], SeqWindow] = {}
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
            stream = self._seq.get((sender, key))
            if stream is None and len(self._seq) < MAX_STREAMS:
                stream = self._seq[(sender, key)] = SeqWindow()
            if stream is not None:
                try:
                    self.gaps += stream.take(seq)
                except ValueError:
                    return False
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
            sample("refused_by_robot", t, sim_time, value=float(sum(self.refused_by_robot.values())),
                   labels={str(robot): str(n) for robot, n in sorted(self.refused_by_robot.items())}),
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


def _stream(s: MetricSample) -> tuple:
    return (s.name, s.labels.get("ap", "")) if s.labels else (s.name, "")


NET_STREAMS = tuple(m.name.split("/", 1)[1] for m in CATALOGUE if m.source == "network")
AIR_STREAMS = tuple(m.name for m in CATALOGUE if m.source == "air")
HEARTBEAT = 0.5  # seconds: no stream goes longer than about this plus its decimation without a sample
PUBLISH_BURST, PUBLISH_PAUSE = 256, 0.005  # metric samples published back to back at most, then a pause (s)


class StreamPublisher:
    """The monitor's metric streams going out on ``bus``: the rows' values, the message statistics ``stats``, the
    link statistics of ``link_meter`` every ``state_every`` ticks and the ``network`` model's counters (if any),
    decimated to ``max_rate`` publications per second (0: every row), and the latest sample of each stream
    (``latest_metric``, ``latest_links``) for late joiners and Prometheus."""

    def __init__(self, bus, keys, stats: MessageStats, link_meter, network, *, dt: float, state_every: int,
                 max_rate: float):
        self.bus = bus
        self.keys = keys
        self.stats = stats
        self.link_meter = link_meter
        self.network = network
        self.dt = dt
        self.state_every = state_every
        self.max_rate = max_rate
        self.latest_metric: dict[str, MetricSample] = {}
        self.latest_links: list[MetricSample] = []
        self.last_values: dict = {}  # the newest row's values
        self._last_publish = 0.0
        self._pending: list[MetricSample] = []
        self.published_lossless = 0  # samples published without loss (the run's end)
        self._publishing = False  # a publication of metric samples is under way
        self._lossless = False  # the run has ended: every sample from now on goes out without loss
        self._fresh: dict[str, tuple[int, float, float]] = {}  # stream -> newest (t, sim time, value) unpublished
        self._unbuilt = False  # rows noted since the metric samples were last built
        self._links_due = False
        # the shared air's per access point samples (label ap), newest first kept, published like the link samples
        self.latest_air: list[MetricSample] = []
        self._air_due = False
        self._air_before: tuple[float, list[int]] | None = None

    def row(self, values: dict) -> None:
        """Note the row's stream values; build and publish MetricSamples only when a publication is due.

        Streams are decimated to ``max_rate`` updates per second, so building ~15 samples (and the latency quantiles)
        for every row would be work nobody reads: per stream the newest value since the last publication is kept
        (a sparse stream, e.g. the W block means every k ticks, is not lost) and turned into a sample when due.
        ``latest_metric`` (late joiners, Prometheus) is refreshed then, and at the end of the run.
        """
        self.last_values = values
        t = values["t"]
        sim_time = values["sim_time"] or t * self.dt
        for name in ROW:
            v = values.get(name)
            if v is not None and not (isinstance(v, float) and not math.isfinite(v)):
                self._fresh[name] = (t, sim_time, float(v))
        if self.network is not None:
            net = self.network.counters(sim_time)
            for name in NET_STREAMS:
                self._fresh[f"net/{name}"] = (t, sim_time, net[name])
        self.stats.row(values)
        self._unbuilt = True
        if t % self.state_every == 0:
            # one sample per (counter, key class): kept apart from latest_metric (one value per name), and carried
            # to the next decimated publish so a k-tick snapshot is never skipped
            self.latest_links = self.link_meter.metrics(t, sim_time, self.bus.identity)
            self._links_due = True
        now = time.monotonic()
        due = self.max_rate <= 0 or now - self._last_publish >= 1.0 / self.max_rate  # 0: every row
        if due:
            self._build(values)
            self._last_publish = now
            self.bus.spawn(self.publish_pending(), "metrics")

    def air(self, stats) -> None:
        """The air's counters as of the start of tick ``stats.t`` (schemas.messages.AirStats): one sample per access
        point and stream, published with the next publication."""
        load = [0.0] * len(stats.ap_bytes)
        if self._air_before is not None and stats.sim_time > self._air_before[0]:
            span = stats.sim_time - self._air_before[0]
            load = [(b - a) / span for a, b in zip(self._air_before[1], stats.ap_bytes)]
        self._air_before = (stats.sim_time, list(stats.ap_bytes))
        out = []
        for ap, (rate, queued, dropped) in enumerate(zip(load, stats.ap_queue, stats.ap_drops)):
            labels = {"ap": str(ap)}
            out += [sample("net/ap_load", stats.t, stats.sim_time, value=float(rate), labels=labels),
                    sample("net/ap_queue", stats.t, stats.sim_time, value=float(queued), labels=labels),
                    sample("net/ap_drops", stats.t, stats.sim_time, value=float(dropped), labels=labels)]
        self.latest_air = out
        self._air_due = True

    def finish(self) -> None:
        """The last rows' samples: ``latest_metric`` ends on the run's final values. Each stream's final sample goes
        out (again, if it went out during the run): the run's end publishes without loss, and a subscriber that lost
        the run's last rows to congestion still ends on the run's totals, never on a stale value."""
        if self._unbuilt:
            self._build(self.last_values)
        queued = {(_stream(x), x.t) for x in self._pending}
        self._pending += [x for x in self.latest_metric.values() if (_stream(x), x.t) not in queued]

    def _build(self, values: dict) -> None:
        """The pending MetricSamples of the rows noted since the last build; ``values`` is the newest row."""
        self._unbuilt = False
        samples = [sample(name, t, sim_time, value=v) for name, (t, sim_time, v) in self._fresh.items()]
        self._fresh = {}
        samples += self.stats.samples(values)
        for s in samples:
            self.latest_metric[s.name] = s
        if self._links_due:
            samples += self.latest_links
            self._links_due = False
        if self._air_due:
            samples += self.latest_air
            self._air_due = False
        if self.max_rate <= 0:  # every row's samples, in order
            self._pending += samples
            return
        # per stream the newest sample since the last publication: a sparse stream (dispatch_delay) is not lost. The
        # air's access points are a stream each. The link meter's key classes share one stream per name here (the
        # newest key class's sample): publishing every key class made the shared default run's streams cost its
        # observers ~70 % more CPU; Prometheus serves every key class (latest_links)
        pending = {_stream(s): s for s in self._pending}
        pending.update((_stream(s), s) for s in samples)
        self._pending = list(pending.values())

    async def heartbeat(self, done: Callable[[], bool]) -> None:
        """Every stream gets a sample at least once a second, even while the run makes no new row (a loaded machine,
        a phase waiting for a late agent): the newest values, or the latest ones again. A live view never goes
        silent while the run is alive (until ``done()``)."""
        while True:
            await asyncio.sleep(HEARTBEAT)
            now = time.monotonic()
            if done() or now - self._last_publish < HEARTBEAT:
                continue
            if self._unbuilt:
                self._build(self.last_values)  # rows noted since the last publication
            elif not self._pending:  # (else a publication is on its way)
                self._pending = list(self.latest_metric.values()) + list(self.latest_links)
            self._last_publish = now
            await self.publish_pending()

    async def publish_pending(self, force: bool = False, *, lossless: bool = False) -> None:
        """Publish the pending samples. One publication at a time, which takes whatever is queued meanwhile too, so
        each stream's samples go out in tick order; ``force`` (the end of the run) waits for the one under way.

        ``lossless`` (the end of the run): blocking congestion control instead of dropping. While the run goes on, a
        slow subscriber must never hold up the monitor (and through its window the fleet), so samples are dropped
        rather than queued. Once the run has ended its last rows come out at once, often a backlog of a hundred
        rows or more: a subscriber that is not scheduled for that tenth of a second lost every one of them, the
        run's final values among them (seen on a loaded machine). Now it only makes the monitor's exit wait.
        A publication under way when the run ends goes on without loss too: it takes whatever is queued meanwhile,
        the run's final samples among them, and sending those as droppable lost them for a client (seen once in five
        runs of the suite: a client's streams ended 13 rows short of the run's last)."""
        if lossless:
            self._lossless = True
        while self._publishing:
            if not force:
                return  # the publication under way takes these too
            await asyncio.sleep(0.01)
        self._publishing = True
        try:
            while self._pending:
                samples, self._pending = self._pending, []
                for i, s in enumerate(samples, 1):
                    kept = self._lossless  # read per sample: the run may end while a batch goes out
                    self.published_lossless += kept
                    await self.bus.publish(self.keys.metric(s.name), s, droppable=not kept)
                    if i % PUBLISH_BURST == 0 and i < len(samples):
                        # a backlog (every row of a monitor that fell behind, --max-rate 0) goes out in bursts the
                        # transport can queue: droppable samples beyond its queue would be lost for every subscriber
                        await asyncio.sleep(PUBLISH_PAUSE)
        finally:
            self._publishing = False


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
