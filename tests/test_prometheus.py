"""Prometheus /metrics of the monitor (containers' C4): scraped on 127.0.0.1 during and after a run."""

from __future__ import annotations

import asyncio
import re
import urllib.request

from morph_sim.environment import command_variables
from services.bus.local import LocalNetwork
from services.bus.zenoh_bus import free_port
from services.monitor.prometheus import PrometheusExporter
from services.monitor.service import MonitorService
from services.runconfig import RunConfig

from _procs import FEW_ROBOTS


def _scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        assert resp.headers["Content-Type"].startswith("text/plain")
        return resp.read().decode()


def _value(text: str, name: str, labels: str = 'run="prom"') -> float:
    m = re.search(rf"^{re.escape(name)}{{{re.escape(labels)}}} (\S+)$", text, re.M)
    assert m, f"{name}{{{labels}}} not exposed"
    return float(m.group(1))


async def test_scrape_during_and_after_a_run(tmp_path):
    from services.agent.roles import make_agent
    from services.sim.service import SimService

    config = RunConfig(run_id="prom", scale="tiny", steps=120, policy="morph", output_dir=tmp_path)
    net = LocalNetwork()
    monitor = MonitorService(config, net.session("monitor"))
    exporter = PrometheusExporter(monitor, free_port())
    try:
        agents = [make_agent(config, net.session(f"agent-{i}"), i) for i in range(config.n_agents)]
        tasks = [asyncio.create_task(monitor.run())] + [asyncio.create_task(a.run()) for a in agents]
        sim = asyncio.create_task(SimService(config, net.session("sim")).run())
        mid = None
        while not sim.done():
            await asyncio.sleep(0.05)
            if mid is None and monitor.latest_metric.get("deliveries_total"):
                mid = await asyncio.to_thread(_scrape, exporter.port)
        await sim
        await asyncio.wait_for(asyncio.gather(*tasks), 10)
        text = await asyncio.to_thread(_scrape, exporter.port)
    finally:
        exporter.close()
    assert mid is not None and "morph_tick" in mid
    assert "# TYPE morph_deliveries_total counter" in text
    assert "# TYPE morph_links gauge" in text
    assert _value(text, "morph_deliveries_total") == monitor.result.deliveries_total > 0
    assert _value(text, "morph_links") == monitor.result.rows[-1]["links"]
    assert _value(text, "morph_tick") == config.steps - 1
    assert "# TYPE morph_bus_latency_seconds histogram" in text
    # wall stamps here (LocalBus services stamp wall time): a real, non-zero wall latency, labelled with its clock
    wall = 'clock="wall",run="prom"'
    assert _value(text, "morph_bus_latency_seconds_bucket", 'clock="wall",le="0.005",run="prom"') >= 0
    inf = _value(text, "morph_bus_latency_seconds_bucket", 'clock="wall",le="+Inf",run="prom"')
    assert inf == _value(text, "morph_bus_latency_seconds_count", wall) > 0
    assert _value(text, "morph_bus_latency_seconds_sum", wall) > 0
    # per key class, as the link meter reports every k ticks: what the dashboard's drop and latency panels query
    assert _value(text, "morph_faults_active") == 0
    sent = dict(re.findall(r'^morph_link_messages_total\{key="([^"]+)",outcome="sent",receiver="monitor",run="prom"\} '
                           r'(\S+)$', text, re.M))
    assert 0 < float(sent["agent/*/ack"]) <= monitor.stats.by_kind["ack"]  # reported every k ticks
    # the link latency is a summary: quantiles of the last messages, and a count that is the delivered counter
    ack = 'key="agent/*/ack",receiver="monitor",run="prom"'
    assert "# TYPE morph_link_latency_seconds summary" in text
    assert _value(text, "morph_link_latency_seconds", ack.replace('receiver=', 'quantile="0.99",receiver=')) >= 0
    assert _value(text, "morph_link_latency_seconds_count", ack) == \
        _value(text, "morph_link_messages_total", ack.replace('receiver=', 'outcome="delivered",receiver='))
    assert _value(text, "morph_link_latency_max_seconds", ack) >= 0
    assert _value(text, "morph_dispatch_delay_seconds_count") > 0
    assert _value(text, "morph_messages_total", 'kind="ack",run="prom"') >= config.n_agents * config.steps
    assert _value(text, "morph_dropped_messages_total", 'reason="sequence_gap",run="prom"') == 0
    # the dispatch outcomes: counters that end on the run's totals (the record's last row)
    outcomes = sim.result().protocol
    assert outcomes["on_time"] > 0
    for name in ("on_time", "late_applied", "expired", "commitment_expired", "refused_stale", "duplicates", "declined"):
        assert f"# TYPE morph_dispatch_{name}_total counter" in text
        assert _value(text, f"morph_dispatch_{name}_total") == outcomes[name] == monitor.result.rows[-1][
            f"dispatch_{name}"], name


def test_the_monitor_command_has_the_flag_and_its_variable():
    variables = {v.flag: v for v in command_variables("monitor")}
    assert variables["--prometheus-port"].env == "MORPH_PROMETHEUS_PORT"


def test_up_serves_prometheus_through_the_run_and_a_grace_after_it(tmp_path):
    import json
    import socket
    import subprocess
    import sys
    import time

    port = free_port()
    argv = [sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny", "--steps", "150",
            "--run-id", "prom", "--output-dir", str(tmp_path), "--prometheus-port", str(port),
            "--prometheus-grace", "3", *FEW_ROBOTS]
    # a busy port is named in one line before anything starts
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", port))
        taken.listen()
        busy = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert busy.returncode == 2 and busy.stderr.strip().splitlines() == [
        f"morph-sim up: error: prometheus_port: 127.0.0.1:{port} is not available (Address already in use)"]
    assert not (tmp_path / "prom").exists()

    up = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        summary = tmp_path / "prom" / "summary.json"
        deadline = time.monotonic() + 120
        while not summary.exists():  # the run is over, its record written
            assert up.poll() is None and time.monotonic() < deadline, up.communicate(timeout=10)
            time.sleep(0.05)
        time.sleep(1.0)  # well inside the grace: a scrape after the run still gets its final values
        text = _scrape(port)
        out, err = up.communicate(timeout=60)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate(timeout=10)
    assert up.returncode == 0, err[-2000:]
    assert _value(text, "morph_deliveries_total") == json.loads(summary.read_text())["deliveries_total"]
    assert _value(text, "morph_tick") == 149


def test_faults_in_force_follow_the_events():
    """morph_faults_active counts the faults set and not yet healed or reset (every process reports a scheduled
    fault; one window per fault id), which the Grafana dashboard shades as fault windows."""
    from prometheus_client import generate_latest

    from schemas.messages import Event

    config = RunConfig(run_id="prom", scale="tiny", steps=10)
    monitor = MonitorService(config, LocalNetwork().session("monitor"), record=False)
    from prometheus_client import CollectorRegistry

    from services.monitor.prometheus import MonitorCollector

    registry = CollectorRegistry(auto_describe=False)
    registry.register(MonitorCollector(monitor))
    active = lambda: _value(generate_latest(registry).decode(), "morph_faults_active")  # noqa: E731
    assert active() == 0
    for source in ("sim", "agent-0", "agent-1"):
        monitor._on_event(Event(kind="fault.set", source=source, t=5, details={"fault_id": "burst"}))
    monitor._on_event(Event(kind="fault.set", source="sim", t=8, details={"fault_id": "slow"}))
    assert active() == 2
    monitor._on_event(Event(kind="fault.healed", source="sim", t=20, details={"fault_id": "burst"}))
    assert active() == 1
    monitor._on_event(Event(kind="fault.reset", source="sim", t=30, details={}))
    assert active() == 0
    assert monitor.fault_windows.closed == [(5.0, 20.0, "burst"), (8.0, 30.0, "slow")]
