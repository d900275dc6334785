"""Prometheus ``/metrics`` of the monitor: one endpoint for the whole run, named by the catalogue of metrics.

A custom collector reads the monitor's latest metric samples and message statistics at scrape time, in its own
``CollectorRegistry`` (no process-global state, so tests and several monitors in one process do not collide).
Names follow the conventions: base units in the name, counters end in ``_total``, histograms expose ``_bucket``,
``_sum`` and ``_count`` (latency with prometheus_client's default buckets, dispatch delay in sim seconds), and
quantiles are a summary's ``quantile`` label. One name per quantity whatever the run's settings, so a dashboard's
query finds it in every run: the bus latency's clock (sim seconds under virtual fault time, wall seconds under wall
time) is its ``clock`` label, as on the ``latency_seconds`` stream.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, SummaryMetricFamily
from prometheus_client.samples import Sample

from services.faults.linkstats import QUANTILES
from services.metrics import catalogue

#: exported from the monitor's message statistics (labels per kind or reason, histograms), not from a stream's value
FROM_STATS = ("messages_total", "drops_total", "refused_by_robot", "latency_seconds", "dispatch_delay")
#: the streams exported as one gauge or counter each, with the catalogue's name and help
EXPORTED = tuple(m for m in catalogue.CATALOGUE if m.prometheus and m.name not in FROM_STATS and m.source != "air")
#: the shared air's per access point streams, one series per access point (label ``ap``)
AIR_EXPORTED = tuple(m for m in catalogue.CATALOGUE if m.prometheus and m.source == "air")
#: the link meter's quantile streams (``link/latency/p50`` …) as a summary's ``quantile`` label values
LINK_QUANTILES = {f"p{round(q * 100)}": str(q) for q in QUANTILES}


class MonitorCollector:
    """Collects from a :class:`~services.monitor.service.MonitorService` at scrape time."""

    def __init__(self, monitor):
        self.monitor = monitor

    def collect(self):
        mon = self.monitor
        run = mon.config.run_id
        latest = dict(mon.latest_metric)  # copy: the event loop thread writes it
        tick = GaugeMetricFamily("morph_tick", "Last finalised tick", labels=["run"])
        tick.add_metric([run], max((s.t for s in latest.values()), default=-1))
        yield tick
        sim_time = GaugeMetricFamily("morph_sim_time_seconds", "Sim time of the last finalised tick", labels=["run"])
        sim_time.add_metric([run], max((s.sim_time for s in latest.values()), default=0.0))
        yield sim_time
        for metric in EXPORTED:
            sample = latest.get(metric.name)
            family = (CounterMetricFamily if metric.kind == "counter" else GaugeMetricFamily)(
                metric.prometheus, metric.help, labels=["run"])
            if sample is not None and sample.value is not None:
                family.add_metric([run], sample.value)
            yield family
        stats = mon.stats
        by = catalogue.BY_NAME
        messages = CounterMetricFamily(by["messages_total"].prometheus, "Messages received by the monitor",
                                       labels=["run", "kind"])
        for kind, count in sorted(dict(stats.by_kind).items()):
            messages.add_metric([run, kind], count)
        yield messages
        drops = CounterMetricFamily(by["drops_total"].prometheus, "Messages lost (sequence gaps) or rejected",
                                    labels=["run", "reason"])
        drops.add_metric([run, "sequence_gap"], stats.gaps)
        drops.add_metric([run, "rejected"], stats.rejected)
        yield drops
        refused = CounterMetricFamily(by["refused_by_robot"].prometheus, "Robots' messages refused by the monitor",
                                      labels=["run", "robot"])
        by_robot = dict(stats.refused_by_robot)
        for robot in range(stats.n):  # every robot's series from the start (a counter that appears at its first count
            refused.add_metric([run, str(robot)], by_robot.get(robot, 0))  # has no rate to show for it)
        yield refused
        faults = GaugeMetricFamily("morph_faults_active", "Faults in force (set and not yet healed or reset)",
                                   labels=["run"])
        faults.add_metric([run], mon.fault_windows.active)
        yield faults
        # per key class (request, ack, tick, …) and receiver, as the monitor's link meter reports every k ticks
        links = CounterMetricFamily("morph_link_messages", "Messages per key class by outcome (sent, delivered, "
                                    "dropped, duplicated, late)", labels=["run", "key", "receiver", "outcome"])
        # a summary: quantiles over the key class's last messages, sum and count since the start (every delivered
        # message is one latency observation, so the count is the delivered counter and the sum its mean × count)
        latency = SummaryMetricFamily("morph_link_latency_seconds", "Observed latency per key class (quantiles: its "
                                      "last 4096 messages; sum and count: since the start)",
                                      labels=["run", "key", "receiver"])
        latency_max = GaugeMetricFamily("morph_link_latency_max_seconds", "Largest observed latency per key class "
                                        "since the start", labels=["run", "key", "receiver"])
        stats_of: dict[tuple[str, str], dict[str, float]] = {}
        for s in list(mon.latest_links):
            key, receiver = s.labels.get("key", ""), s.labels.get("receiver", "")
            if s.name.startswith("link/latency/"):
                stats_of.setdefault((key, receiver), {})[s.name.rsplit("/", 1)[1]] = s.value
            else:
                outcome = s.name.split("/", 1)[1]
                links.add_metric([run, key, receiver, outcome], s.value)
                if outcome == "delivered":
                    stats_of.setdefault((key, receiver), {})["count"] = s.value
        for (key, receiver), st in sorted(stats_of.items()):
            if "mean" not in st or "count" not in st:
                continue
            # the client's summary family takes count and sum; its quantile samples are added as the format has them
            for stat, quantile in LINK_QUANTILES.items():
                latency.samples.append(Sample(latency.name, {"run": run, "key": key, "receiver": receiver,
                                                             "quantile": quantile}, st[stat]))
            latency.add_metric([run, key, receiver], count_value=st["count"], sum_value=st["mean"] * st["count"])
            latency_max.add_metric([run, key, receiver], st["max"])
        yield links
        yield latency
        yield latency_max
        air = list(mon.latest_air)
        for metric in AIR_EXPORTED:
            family = (CounterMetricFamily if metric.kind == "counter" else GaugeMetricFamily)(
                metric.prometheus, metric.help, labels=["run", "ap"])
            for s in air:
                if s.name == metric.name and s.value is not None:
                    family.add_metric([run, s.labels.get("ap", "")], s.value)
            yield family
        # the bus latency is measured in the clock its messages are stamped with: before the first one arrives, the
        # clock the run's fault time stamps them with
        clock = stats.clock if stats.latency.count else ("sim" if mon.config.fault_time == "virtual" else "wall")
        for hist, stream, doc, labels, values in (
                (stats.latency, "latency_seconds", "Publish to monitor latency (clock: sim seconds under virtual "
                 "fault time, wall seconds under wall time)", ["run", "clock"], [run, clock]),
                (stats.dispatch, "dispatch_delay", "Sim seconds from an AGV's first help request to a picker's "
                 "commit", ["run"], [run])):
            family = HistogramMetricFamily(by[stream].prometheus, doc, labels=labels)
            family.add_metric(values, hist.cumulative(), sum_value=hist.sum)
            yield family


class PrometheusExporter:
    """Serves ``http://host:port/metrics`` for ``monitor`` until :meth:`close`."""

    def __init__(self, monitor, port: int, host: str = "127.0.0.1"):
        if not 0 <= port < 65536:
            raise ValueError(f"prometheus_port: {port} is not a TCP port")
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(MonitorCollector(monitor))
        self.server, self.thread = start_http_server(port, addr=host, registry=self.registry)
        self.port = self.server.server_port

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
