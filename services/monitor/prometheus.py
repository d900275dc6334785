"""Prometheus ``/metrics`` of the monitor (ecosystem.md §E1): one endpoint for the whole run.

A custom collector reads the monitor's latest metric samples and message statistics at scrape time, in its own
``CollectorRegistry`` (no process-global state, so tests and several monitors in one process do not collide).
Names follow the conventions: base units in the name, counters end in ``_total``, histograms expose ``_bucket``,
``_sum`` and ``_count`` (latency with prometheus_client's default buckets, dispatch delay in sim seconds).
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

#: stream name -> (Prometheus name without suffix, type, help). Counters get ``_total`` from the client.
EXPORTED = {
    "deliveries_total": ("morph_deliveries", "counter", "Shelves delivered since the start of the run"),
    "links": ("morph_links", "gauge", "Undirected coordination links"),
    "lambda2": ("morph_lambda2", "gauge", "Algebraic connectivity of the link graph"),
    "eta": ("morph_eta", "gauge", "Mean neuromodulation signal"),
    "delivery_rate": ("morph_delivery_rate_per_second", "gauge", "Deliveries per sim second (sliding window)"),
    "w_agv_agv": ("morph_w_agv_agv", "gauge", "Mean W between AGVs"),
    "w_agv_picker": ("morph_w_agv_picker", "gauge", "Mean W between AGVs and pickers"),
    "w_picker_picker": ("morph_w_picker_picker", "gauge", "Mean W between pickers"),
    "agents_alive": ("morph_agents_alive", "gauge", "Agents that acknowledged the last tick"),
}


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
        for stream, (name, kind, doc) in EXPORTED.items():
            sample = latest.get(stream)
            family = (CounterMetricFamily if kind == "counter" else GaugeMetricFamily)(name, doc, labels=["run"])
            if sample is not None and sample.value is not None:
                family.add_metric([run], sample.value)
            yield family
        stats = mon.stats
        messages = CounterMetricFamily("morph_messages", "Messages received by the monitor", labels=["run", "kind"])
        for kind, count in sorted(dict(stats.by_kind).items()):
            messages.add_metric([run, kind], count)
        yield messages
        drops = CounterMetricFamily("morph_dropped_messages", "Messages lost (sequence gaps) or rejected",
                                    labels=["run", "reason"])
        drops.add_metric([run, "sequence_gap"], stats.gaps)
        drops.add_metric([run, "rejected"], stats.rejected)
        yield drops
        faults = GaugeMetricFamily("morph_faults_active", "Faults in force (set and not yet healed or reset)",
                                   labels=["run"])
        faults.add_metric([run], mon.fault_windows.active)
        yield faults
        # per key class (request, ack, tick, …) and receiver, as the monitor's link meter reports every k ticks
        links = CounterMetricFamily("morph_link_messages", "Messages per key class by outcome (sent, delivered, "
                                    "dropped, duplicated, late)", labels=["run", "key", "receiver", "outcome"])
        latency = GaugeMetricFamily("morph_link_latency_seconds", "Observed latency per key class since the start",
                                    labels=["run", "key", "receiver", "stat"])
        for s in list(mon.latest_links):
            key, receiver = s.labels.get("key", ""), s.labels.get("receiver", "")
            if s.name.startswith("link/latency/"):
                latency.add_metric([run, key, receiver, s.name.rsplit("/", 1)[1]], s.value)
            else:
                links.add_metric([run, key, receiver, s.name.split("/", 1)[1]], s.value)
        yield links
        yield latency
        for hist, name, doc in ((stats.latency, "morph_bus_latency_seconds", "Publish to monitor latency"),
                                (stats.dispatch, "morph_dispatch_delay_seconds",
                                 "Sim seconds from an AGV's first help request to a picker's commit")):
            family = HistogramMetricFamily(name, doc, labels=["run"])
            family.add_metric([run], hist.cumulative(), sum_value=hist.sum)
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
