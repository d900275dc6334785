"""Measured, not assumed: per-key sent / delivered / dropped / duplicated / late counts and the observed
latency distribution, computed by a receiver from the samples themselves.

Every sample carries its publisher, a per-(publisher, key) sequence number starting at 0, and the publisher's send
time (bus.base). So a receiver knows, per (publisher, key):

* sent       = highest sequence number seen + 1 (messages lost after the last one that arrived are invisible until a
               later one arrives; a restarted publisher starts again at 0 and is counted from its new numbers on);
* delivered  = deliveries, duplicates included; unique = distinct sequence numbers; duplicated = delivered − unique;
* dropped    = sent − unique;
* late       = deliveries the caller flagged as after their deadline (virtual time: :meth:`VirtualTime.is_late`);
* latency    = receive time − send time, in the unit of the clocks (sim seconds in virtual time): mean and max
               since the start, quantiles over the last LATENCY_WINDOW messages of the key class.

:class:`LinkMeter` is pure (no I/O, no clock): the caller passes the receive time. Counts are grouped by key class:
the key relative to ``morph/<run>/`` with robot ids replaced by ``*`` (``agent/*/ack``), so a report has a handful
of rows whatever the fleet size. :meth:`LinkMeter.metrics` turns the report into ``MetricSample``\\ s
(``link/<counter>`` with label ``key``) for the monitor to publish.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from schemas.messages import MetricSample

QUANTILES = (0.5, 0.9, 0.99)


def key_class(rel_chunks: list[str]) -> str:
    """``['agent', '3', 'request', '7']`` → ``'agent/*/request/*'``."""
    return "/".join("*" if c.isdigit() else c for c in rel_chunks)


#: sequence numbers remembered per stream below the highest one (duplicate detection), and latencies kept per key
#: class for the quantiles: a meter's memory stays bounded over any run length.
SEQ_WINDOW = 1024
LATENCY_WINDOW = 4096


@dataclass
class _Stream:
    """One (publisher, key) stream. ``seen`` holds the sequence numbers within SEQ_WINDOW of the highest: a number
    below that window is counted as a new message (a duplicate or reordering that far back is not told apart)."""

    max_seq: int = -1
    seen: set[int] = field(default_factory=set)
    unique: int = 0
    delivered: int = 0
    late: int = 0

    def add(self, seq: int) -> None:
        self.delivered += 1
        if seq in self.seen:
            return
        self.unique += 1
        if seq > self.max_seq:
            self.max_seq = seq
        if seq > self.max_seq - SEQ_WINDOW:
            self.seen.add(seq)
            if len(self.seen) > 2 * SEQ_WINDOW:
                floor = self.max_seq - SEQ_WINDOW
                self.seen = {x for x in self.seen if x > floor}


@dataclass
class _Latency:
    """Latencies of one key class: count, mean and max since the start; the last LATENCY_WINDOW for quantiles."""

    recent: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    count: int = 0
    total: float = 0.0
    max: float = -math.inf

    def add(self, value: float) -> None:
        self.recent.append(value)
        self.count += 1
        self.total += value
        if value > self.max:
            self.max = value


@dataclass(frozen=True)
class KeyReport:
    key: str
    sent: int
    delivered: int
    unique: int
    dropped: int
    duplicated: int
    late: int
    latency: dict[str, float]  # mean, p50, p90, p99, max (empty when nothing arrived)

    @property
    def loss_rate(self) -> float:
        return self.dropped / self.sent if self.sent else 0.0


class LinkMeter:
    """Accumulates what one receiver observed. ``record`` per delivery, ``report`` / ``metrics`` whenever.

    ``receiver``: the identity of the session it meters. Its own publications handed back to it (the monitor
    subscribes to the whole run, its own metric streams too) crossed no link and are not counted: they would only add
    a key class per stream."""

    def __init__(self, run_prefix: str = "", receiver: str = ""):
        self._prefix = run_prefix.rstrip("/") + "/" if run_prefix else ""
        self._receiver = receiver
        self._streams: dict[tuple[str, str], _Stream] = {}
        self._latency: dict[str, _Latency] = {}
        self._classes: dict[str, str] = {}  # key -> key class (a run has a bounded set of keys)

    def _class(self, key: str) -> str:
        cls = self._classes.get(key)
        if cls is None:
            rel = key[len(self._prefix):] if self._prefix and key.startswith(self._prefix) else key
            cls = self._classes[key] = key_class(rel.split("/"))
        return cls

    def record(self, key: str, sender: str, seq: int, sent_at: float, received_at: float, *,
               late: bool = False) -> None:
        if self._receiver and sender == self._receiver:
            return
        stream = self._streams.get((key, sender))
        if stream is None:
            stream = self._streams[(key, sender)] = _Stream()
        stream.add(seq)
        if late:
            stream.late += 1
        cls = self._class(key)
        lat = self._latency.get(cls)
        if lat is None:
            lat = self._latency[cls] = _Latency()
        lat.add(received_at - sent_at)

    def report(self) -> dict[str, KeyReport]:
        """Per key class, sorted by key."""
        acc: dict[str, list[int]] = {}
        for (key, _sender), s in self._streams.items():
            row = acc.setdefault(self._class(key), [0, 0, 0, 0])
            row[0] += s.max_seq + 1
            row[1] += s.delivered
            row[2] += s.unique
            row[3] += s.late
        out: dict[str, KeyReport] = {}
        for cls in sorted(acc):
            sent, delivered, unique, late = acc[cls]
            lat = self._latency.get(cls)
            stats: dict[str, float] = {}
            if lat is not None and lat.count:
                stats = {"mean": lat.total / lat.count, "max": float(lat.max)}
                qs = np.quantile(np.fromiter(lat.recent, dtype=float, count=len(lat.recent)), QUANTILES)
                for q, v in zip(QUANTILES, qs):
                    stats[f"p{round(q * 100)}"] = float(v)
            out[cls] = KeyReport(cls, sent, delivered, unique, sent - unique, delivered - unique, late, stats)
        return out

    def metrics(self, t: int, sim_time: float, receiver: str = "") -> list[MetricSample]:
        """The report as metric samples ``link/<counter>`` labelled by key class (and receiver)."""
        out: list[MetricSample] = []
        for cls, r in self.report().items():
            labels = {"key": cls, **({"receiver": receiver} if receiver else {})}
            for name in ("sent", "delivered", "dropped", "duplicated", "late"):
                out.append(MetricSample(name=f"link/{name}", t=t, sim_time=sim_time, value=float(getattr(r, name)),
                                        labels=labels, unit="messages"))
            for stat, value in r.latency.items():
                out.append(MetricSample(name=f"link/latency/{stat}", t=t, sim_time=sim_time, value=value,
                                        labels=labels, unit="s"))
        return out
