"""The Grafana dashboard and the README's Prometheus names against a live run's ``/metrics``: a short ``morph-sim up
--prometheus-port`` on a free loopback port, scraped while it runs, under the default fault time (virtual) and under
``--fault-time wall``. Every series a query selects must be there with the labels it filters and groups by."""

from __future__ import annotations

import re
import time
import urllib.request

import pytest
from _dashboard import dashboard_queries, is_query, parse, readme_spans, selectors, unanswered

from services.metrics.catalogue import CATALOGUE

from _procs import LiveRun

#: the shared air's series: only a run under a rate-limited network profile has them
AIR_SERIES = {m.prometheus + ("_total" if m.kind == "counter" else "") for m in CATALOGUE if m.source == "air"}
STEPS = 150
FIRST_TICK = 20  # by then every row metric, the W blocks and the link meter's first report (every 10 ticks) are in
# a small fleet with two robots of each role: every W block (AGV–AGV, AGV–picker, picker–picker) has a pair to average
FLEET = ("--agvs", "2", "--pickers", "2")


def _scrape(port: int) -> str | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
            return resp.read().decode()
    except OSError:
        return None


def _tick(text: str, run: str) -> float:
    m = re.search(rf'^morph_tick{{run="{run}"}} (\S+)$', text, re.M)
    return float(m.group(1)) if m else -1


@pytest.fixture(scope="module", params=["virtual", "wall"])
def scrape(request, tmp_path_factory):
    """(fault time, run id, the last scrape taken while the run was between FIRST_TICK and its last tick) of one
    live run per fault time."""
    from services.bus.zenoh_bus import free_port

    fault_time = request.param
    run_id, port = f"dash-{fault_time}", free_port()
    # the virtual-time run under a rate-limited profile: its air's per access point series are the dashboard's too
    # (a wall-time run has no network profile, and its panels are the others)
    flags = ("--network", "congested") if fault_time == "virtual" else ("--fault-time", "wall")
    # no grace after the run: the scrapes that count are taken while it runs
    run = LiveRun(tmp_path_factory.mktemp(run_id), run_id, "--steps", str(STEPS), "--prometheus-port", str(port),
                  "--prometheus-grace", "0", *FLEET, *flags)
    try:
        run.start()
        mid = None
        deadline = time.monotonic() + 120
        while run.running() and time.monotonic() < deadline:
            text = _scrape(port)
            if text is not None and FIRST_TICK <= _tick(text, run_id) < STEPS - 1:
                mid = text
            time.sleep(0.05)
        assert run.wait(timeout=60) == 0, run.stderr()[-3000:]
    finally:
        run.kill()
    assert mid is not None, f"no scrape between tick {FIRST_TICK} and {STEPS - 1}\n{run.stderr()[-2000:]}"
    return fault_time, run_id, mid


def test_every_dashboard_query_selects_live_series(scrape):
    fault_time, run_id, text = scrape
    _, samples = parse(text)
    problems = [f"{where}: {p}" for where, expr in dashboard_queries()
                if fault_time == "virtual" or not AIR_SERIES & {name for name, _ in selectors(expr)}
                for p in unanswered(expr, samples, {"run": run_id})]
    assert not problems, f"--fault-time {fault_time}:\n" + "\n".join(problems)


def test_every_metric_the_readme_names_is_served_with_its_labels(scrape):
    fault_time, run_id, text = scrape
    types, samples = parse(text)
    names = {name for name, _, _ in samples} | set(types)
    problems = []
    for span in readme_spans():
        if is_query(span):
            problems += [f"`{span}`: {p}" for p in unanswered(span, samples, {"run": run_id})]
            continue
        for name, labels in re.findall(r"\b(morph_(?!sim\b)[a-z0-9_]+)(?:\{([^}]*)\})?", span):
            if fault_time == "wall" and name in AIR_SERIES:
                continue  # a wall-time run has no network profile, hence no air
            if name not in names:
                problems.append(f"`{span}`: {name} is not served")
                continue
            wanted = {"run", *(x.strip() for x in labels.split(",") if x.strip())}
            served = [lab for s, lab, _ in samples if s == name or s.rsplit("_", 1)[0] == name]
            if not any(wanted <= set(lab) for lab in served):
                problems.append(f"`{span}`: no {name} series has the labels {sorted(wanted)}")
    assert not problems, f"--fault-time {fault_time}:\n" + "\n".join(problems)


def test_the_bus_latency_panel_has_data_in_the_runs_clock(scrape):
    fault_time, run_id, text = scrape
    _, samples = parse(text)
    clock = {"virtual": "sim", "wall": "wall"}[fault_time]
    counts = [(labels, value) for name, labels, value in samples if name == "morph_bus_latency_seconds_count"]
    assert [labels for labels, _ in counts] == [{"run": run_id, "clock": clock}], counts
    assert counts[0][1] > 0
    panel = [expr for where, expr in dashboard_queries() if "morph_bus_latency_seconds_bucket" in expr]
    assert panel and all(not unanswered(expr, samples, {"run": run_id}) for expr in panel)


def test_quantiles_follow_the_prometheus_conventions(scrape):
    """Quantiles are a summary's ``quantile`` label or a histogram's ``le`` buckets, never a gauge's own label."""
    _, run_id, text = scrape
    types, samples = parse(text)
    for name, labels, _ in samples:
        family = next(f for f in (name, re.sub(r"_(bucket|sum|count|total)$", "", name)) if f in types)
        kind = types[family]
        assert ("quantile" in labels) == (kind == "summary" and name == family), (name, labels)
        assert ("le" in labels) == (kind == "histogram" and name.endswith("_bucket")), (name, labels)
        assert not {"stat", "p", "percentile"} & set(labels), (name, labels)
    assert types["morph_link_latency_seconds"] == "summary"
    quantiles = {lab["quantile"] for name, lab, _ in samples if name == "morph_link_latency_seconds"}
    assert quantiles == {"0.5", "0.9", "0.99"}
