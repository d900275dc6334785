"""The compose profile "monitoring" (Prometheus + Grafana) without an engine: the files parse, every dashboard query
names a metric (and labels) the monitor's collector exports — read from the collector itself — and the pieces point
at each other (scrape target, datasource, provisioned dashboard path)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml
from _dashboard import dashboard_queries, grouping, selectors

from services.bus.local import LocalNetwork
from services.monitor.prometheus import MonitorCollector
from services.monitor.service import MonitorService
from services.runconfig import RunConfig

ROOT = Path(__file__).resolve().parent.parent
MON = ROOT / "deploy" / "monitoring"
DASHBOARD = MON / "grafana" / "dashboards" / "morph-sim.json"
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _exported() -> dict[str, set[str]]:
    """Sample name -> label names, for every family the monitor's collector yields."""
    monitor = MonitorService(RunConfig(run_id="names", steps=5), LocalNetwork().session("monitor"), record=False)
    out: dict[str, set[str]] = {}
    for fam in MonitorCollector(monitor).collect():
        labels = set(getattr(fam, "_labelnames", ()))
        names = {"counter": [fam.name + "_total"], "histogram": [fam.name + s for s in ("_bucket", "_sum", "_count")],
                 "summary": [fam.name + s for s in ("", "_sum", "_count")], "gauge": [fam.name]}[fam.type]
        for n in names:
            out[n] = labels | ({"le"} if n.endswith("_bucket") else {"quantile"} if n == fam.name and
                               fam.type == "summary" else set())
    return out


def _queries() -> list[str]:
    dash = json.loads(DASHBOARD.read_text())
    exprs = [t["expr"] for p in dash["panels"] for t in p["targets"]]
    exprs += [a["expr"] for a in dash["annotations"]["list"] if "expr" in a]
    exprs += [v["definition"] for v in dash["templating"]["list"]]
    return exprs


def test_the_dashboard_is_valid_json_with_unique_panels():
    dash = json.loads(DASHBOARD.read_text())
    assert dash["uid"] == "morph-sim" and dash["panels"]
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids))
    for p in dash["panels"]:
        assert p["targets"] and all(t["expr"].strip() for t in p["targets"]), p["title"]
        g = p["gridPos"]
        assert 0 <= g["x"] and g["x"] + g["w"] <= 24, p["title"]


def test_every_query_names_a_metric_and_labels_the_monitor_exports():
    exported = _exported()
    used = set()
    for expr in _queries():
        names = re.findall(r"\bmorph_[a-z0-9_]+", expr)
        assert names, f"query names no morph metric: {expr}"
        for name in names:
            assert name in exported, f"{name} (in {expr!r}) is not exported by the monitor"
            used.add(name)
        for name, selector in re.findall(r"\b(morph_[a-z0-9_]+)\{([^}]*)\}", expr):
            for label in re.findall(r"(\w+)\s*(?:=~|!=|!~|=)", selector):
                assert label in exported[name], f"{name} has no label {label!r} (in {expr!r})"
        for label in re.findall(r"\bby \(([^)]*)\)", expr):
            for lab in (x.strip() for x in label.split(",")):
                assert any(lab in exported[n] for n in names), f"no metric of {expr!r} has label {lab!r}"
    # what the dashboard is for: deliveries, delivery rate, links, λ₂, η, agents alive, dispatch outcomes and delay,
    # drops and latency by key, fault windows
    assert {"morph_deliveries_total", "morph_delivery_rate_per_second", "morph_links", "morph_lambda2", "morph_eta",
            "morph_agents_alive", "morph_messages_total", "morph_dispatch_delay_seconds_bucket",
            "morph_link_messages_total", "morph_link_latency_seconds", "morph_faults_active"} <= used


def test_fault_windows_are_annotations_from_the_faults_in_force():
    dash = json.loads(DASHBOARD.read_text())
    faults = [a for a in dash["annotations"]["list"] if a.get("name") == "Fault windows"]
    assert len(faults) == 1 and faults[0]["enable"]
    assert faults[0]["expr"].startswith("morph_faults_active{") and faults[0]["expr"].endswith("> 0")


def test_provisioning_points_at_the_scraped_monitor():
    prom = yaml.safe_load((MON / "prometheus.yml").read_text())
    targets = [t for job in prom["scrape_configs"] for sc in job["static_configs"] for t in sc["targets"]]
    monitor_cmd = COMPOSE["services"]["monitor"]["command"]
    port = re.search(r":-(\d+)\}", monitor_cmd[monitor_cmd.index("--prometheus-port") + 1]).group(1)
    assert targets == [f"monitor:{port}"]
    assert monitor_cmd[monitor_cmd.index("--prometheus-host") + 1] == "0.0.0.0"

    ds = yaml.safe_load((MON / "grafana" / "provisioning" / "datasources" / "prometheus.yml").read_text())
    (source,) = ds["datasources"]
    assert source["type"] == "prometheus" and source["url"] == "http://prometheus:9090"
    dash = json.loads(DASHBOARD.read_text())
    uids = {p["datasource"]["uid"] for p in dash["panels"]} | {t["datasource"]["uid"] for p in dash["panels"]
                                                                 for t in p["targets"]}
    assert uids == {source["uid"]}

    prov = yaml.safe_load((MON / "grafana" / "provisioning" / "dashboards" / "morph-sim.yml").read_text())
    (provider,) = prov["providers"]
    grafana = COMPOSE["services"]["grafana"]
    mounts = dict(v.rsplit(":", 2)[:2] if v.endswith(":ro") else v.split(":", 1) for v in grafana["volumes"])
    assert mounts["./deploy/monitoring/grafana/dashboards"] == provider["options"]["path"]
    assert mounts["./deploy/monitoring/grafana/provisioning"] == "/etc/grafana/provisioning"
    assert grafana["environment"]["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"] == \
        provider["options"]["path"] + "/" + DASHBOARD.name
    prometheus = COMPOSE["services"]["prometheus"]
    assert "./deploy/monitoring/prometheus.yml:/etc/prometheus/prometheus.yml:ro" in prometheus["volumes"]
    for name in ("prometheus", "grafana"):
        assert COMPOSE["services"][name]["profiles"] == ["monitoring"]
        for src in COMPOSE["services"][name]["volumes"]:
            if src.startswith("./"):
                assert (ROOT / src.split(":")[0]).exists(), src


@pytest.mark.parametrize("path", sorted(p for p in MON.rglob("*") if p.suffix in (".yml", ".yaml")))
def test_every_monitoring_yaml_parses(path):
    assert isinstance(yaml.safe_load(path.read_text()), dict)


def test_every_metric_of_the_catalogue_is_charted():
    """Each metric the catalogue exports to Prometheus has a panel: the seven dispatch outcomes and the fleet view's
    age included (a histogram through its buckets)."""
    from services.metrics import catalogue

    charted = {name for _, expr in dashboard_queries() for name, _ in selectors(expr)}
    missing = []
    for metric in catalogue.CATALOGUE:
        if metric.prometheus:
            name = metric.prometheus + {"counter": "_total", "histogram": "_bucket"}.get(metric.kind, "")
            if name not in charted:
                missing.append(name)
    assert not missing, f"exported but not charted: {missing}"


def test_multi_run_selections_aggregate_by_run():
    """The run variable selects several runs at once: every aggregation keeps them apart (``by (run, …)``), and a
    panel's legend names the run of each series."""
    problems = []
    for where, expr in dashboard_queries():
        for kind, labels in grouping(expr):
            if kind != "by" or "run" not in labels:
                problems.append(f"{where}: {kind} ({', '.join(labels)}) mixes runs in {expr!r}")
    dash = json.loads(DASHBOARD.read_text())
    for panel in dash["panels"]:
        for target in panel["targets"]:
            if "run" in target["expr"] and "{{run}}" not in target["legendFormat"]:
                problems.append(f"panel {panel['title']!r}: legend {target['legendFormat']!r} does not name the run")
    assert not problems, "\n".join(problems)
