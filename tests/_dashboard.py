"""What the Grafana dashboard and the README ask Prometheus for, and whether a scrape of ``/metrics`` answers it.

The queries are read from the shipped files; a query's series selectors (``morph_x{label="v",run=~"$run"}``) are
matched against scraped samples the way Prometheus matches them (``=~`` and ``!~`` anchored regexes), and its
grouping labels (``by (run, le)``) must be labels of what it selects.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DASHBOARD = ROOT / "deploy" / "monitoring" / "grafana" / "dashboards" / "morph-sim.json"
README = ROOT / "README.md"

#: a metric's name (``morph_sim`` is the Python package)
METRIC = re.compile(r"\bmorph_(?!sim\b)[a-z0-9_]+")
_SELECTOR = re.compile(r"\b(morph_(?!sim\b)[a-zA-Z0-9_]+)(\{[^}]*\})?")
_MATCHER = re.compile(r'(\w+)\s*(=~|!~|!=|=)\s*"((?:[^"\\]|\\.)*)"')
_GROUPING = re.compile(r"\b(by|without)\s*\(([^)]*)\)")


def dashboard_queries() -> list[tuple[str, str]]:
    """(where, PromQL) for every panel target, annotation and template variable of the dashboard."""
    dash = json.loads(DASHBOARD.read_text())
    out = [(f"panel {p['title']!r}", t["expr"]) for p in dash["panels"] for t in p["targets"]]
    out += [(f"annotation {a['name']!r}", a["expr"]) for a in dash["annotations"]["list"] if "expr" in a]
    out += [(f"variable {v['name']!r}", v["definition"]) for v in dash["templating"]["list"]]
    return out


def readme_spans() -> list[str]:
    """Every code span of the README that names a morph metric (metric names, ``name{labels}`` or PromQL)."""
    spans = re.findall(r"`([^`\n]*morph_[^`\n]*)`", README.read_text())
    return [s for s in spans if METRIC.search(s)]


def is_query(span: str) -> bool:
    """A PromQL expression, as opposed to a metric's name with the names of its labels (``morph_x{kind}``)."""
    return "(" in span or "=" in span


def selectors(expr: str) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """(metric name, [(label, op, value)]) of every series selector in ``expr``."""
    out = []
    for name, braces in _SELECTOR.findall(expr):
        out.append((name, _MATCHER.findall(braces or "")))
    return out


def grouping(expr: str) -> list[tuple[str, list[str]]]:
    """(by|without, labels) of every aggregation's grouping clause."""
    return [(kind, [x.strip() for x in labels.split(",") if x.strip()]) for kind, labels in _GROUPING.findall(expr)]


def matches(labels: dict[str, str], matchers: list[tuple[str, str, str]]) -> bool:
    for label, op, value in matchers:
        have = labels.get(label, "")
        if op == "=" and have != value or op == "!=" and have == value:
            return False
        if op == "=~" and not re.fullmatch(value, have) or op == "!~" and re.fullmatch(value, have):
            return False
    return True


def parse(text: str) -> tuple[dict[str, str], list[tuple[str, dict[str, str], float]]]:
    """A scrape as (family name -> type, [(sample name, labels, value)])."""
    from prometheus_client.parser import text_string_to_metric_families

    types, samples = {}, []
    for family in text_string_to_metric_families(text):
        types[family.name] = family.type
        samples += [(s.name, dict(s.labels), s.value) for s in family.samples]
    return types, samples


def unanswered(expr: str, samples, variables: dict[str, str]) -> list[str]:
    """What ``expr`` asks for that the scraped ``samples`` do not have: a selector no sample matches, or a grouping
    label that none of the selected samples carries."""
    for name, value in variables.items():
        expr = expr.replace(f"${name}", value)
    problems, selected = [], []
    for name, matchers in selectors(expr):
        hits = [labels for sample, labels, _ in samples if sample == name and matches(labels, matchers)]
        if not hits:
            problems.append(f"no series matches {name}{{{', '.join(''.join(m) for m in matchers)}}}")
        selected += hits
    for kind, labels in grouping(expr):
        for label in labels:
            if selected and not any(label in s for s in selected):
                problems.append(f"{kind} ({label}): no selected series has the label {label!r}")
    return problems
