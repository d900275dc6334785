"""The degradation study: deliveries, links and dispatch delay against latency and loss on the protocol's
messages, for MORPH (both presets), Full-Graph, TSG and Proximity, over scales and seeds.

Each episode is the lab's episode (:func:`morph_sim.lab.runner.run_episode`, the one tick loop) with network faults
on its discrete-event network: messages are delayed by the fault layer's per-link draw and delivered at send time
plus delay, never dropped for being late (docs/faults.md, "Late, not lost"). A fault acts on the dispatch messages
(request, reply, commitment, refusal), on the fleet broadcast (then every agent learns and gates from its own view),
or on both (``target``).

Measured per episode: deliveries, mean undirected links, mean dispatch delay (ticks an AGV waits from first needing
a picker until one is committed), the protocol's outcome counters, dispatch messages and bytes per delivery and the
fleet view's mean age. The grid is one resumable run record (morph_sim/lab/grid.py); the tables compare each policy
at each fault point with itself without faults (Welch, Bonferroni over the table).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from morph_sim.lab.network import dispatch_faults, fleet_faults
from morph_sim.lab.runner import EpisodeSpec, run_episode
from schemas.faults import FaultSpec, Latency, Loss
from services.metrics import catalogue
from services.policies.conditions import DEFAULT_RADIUS, FAULT_STUDY, by_label, command_line_keys, study_condition

DT = 1.0

#: the study's conditions by label (its records name a condition by its label)
CONDITIONS = by_label(FAULT_STUDY)
#: short names of the conditions on the command line
CONDITION_KEYS = {k: c.label for k, c in command_line_keys(FAULT_STUDY).items()}
LOSS_PCT = (0, 10, 20, 30, 40, 50)
LATENCY_TICKS = (0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0)
TARGETS = ("dispatch", "fleet", "both")
BURST = 4.0  # Gilbert–Elliott mean burst length, messages


def fault_spec(kind: str, level: float, seed: int) -> FaultSpec | None:
    """The network fault of one sweep point: ``bernoulli``/``bursty`` loss in percent, or ``latency`` in ticks
    (normal, jitter a quarter of the delay)."""
    if level == 0:
        return None
    if kind == "bernoulli":
        return FaultSpec(loss=Loss(percent=level), seed=seed)
    if kind == "bursty":
        return FaultSpec(loss=Loss(model="gilbert_elliott", percent=level, burst_length=BURST), seed=seed)
    if kind == "latency":
        return FaultSpec(latency=Latency(delay=level * DT, jitter=0.25 * level * DT, distribution="normal"),
                         seed=seed)
    raise ValueError(f"kind: unknown {kind!r} (bernoulli, bursty, latency)")


def scoped(spec: FaultSpec | None, target: str) -> tuple[FaultSpec, ...]:
    """``spec`` on the dispatch messages, the fleet broadcast, or both."""
    if target not in TARGETS:
        raise ValueError(f"target: unknown {target!r} ({', '.join(TARGETS)})")
    if spec is None:
        return ()
    out = []
    if target in ("dispatch", "both"):
        out += dispatch_faults(spec)
    if target in ("fleet", "both"):
        out += fleet_faults(spec)
    return tuple(out)


@dataclass
class FaultEpisode:
    condition: str
    kind: str
    level: float
    seed: int
    deliveries: int
    mean_links: float
    dispatch_delay: float
    attempts: int  # requests sent
    lost_attempts: int  # requests that expired unanswered (their request, reply or commitment lost)
    wall_s: float
    target: str = "dispatch"
    scale: str = "tiny"
    outcomes: dict = field(default_factory=dict)
    messages_per_delivery: float = float("nan")
    bytes_per_delivery: float = float("nan")
    view_age_mean: float = float("nan")  # mean age of the agents' fleet views, sim seconds (fleet/both targets)


def condition_order(conditions) -> list[str]:
    """The study's conditions in its table's order, then policies from outside in the order first seen."""
    seen = list(dict.fromkeys(conditions))
    return [c for c in CONDITIONS if c in seen] + [c for c in seen if c not in CONDITIONS]


def run_fault_episode(condition: str, kind: str, level: float, seed: int, *, scale: str = "tiny",
                      steps: int = 500, target: str = "dispatch") -> FaultEpisode:
    spec = EpisodeSpec(scale=scale, seed=seed, steps=steps,
                       **study_condition(condition, CONDITIONS).episode_fields(radius=DEFAULT_RADIUS),
                       fiedler_every=10**9,
                       faults=scoped(fault_spec(kind, level, seed), target))
    ep = run_episode(spec)
    s = ep.summary
    outcomes = {k.removeprefix("protocol_"): v for k, v in s.items() if k.startswith("protocol_")}
    d = s["deliveries"]
    return FaultEpisode(condition, kind, float(level), seed, int(d), float(s["mean_links"]),
                        float(s.get("dispatch_delay", float("nan"))), outcomes.get("requests", 0),
                        outcomes.get("expired", 0), ep.wall_s, target, scale, outcomes,
                        s["messages_sent"] / d if d else float("nan"),
                        s["bytes_sent"] / d if d else float("nan"), float(s.get("view_age_mean", float("nan"))))


@dataclass(frozen=True)
class FaultTask:
    """One episode of the grid: a policy at one fault point (``level`` 0: fault-free, shared by every target)."""

    scale: str
    target: str
    condition: str
    kind: str
    level: float
    seed: int
    steps: int

    @property
    def key(self) -> str:
        return f"{self.scale}|{self.target}|{self.condition}|{self.kind}={self.level:g}|seed={self.seed}|T={self.steps}"


def fault_tasks(*, scales, targets, conditions, loss, latency, seeds, steps: int) -> list[FaultTask]:
    """Every episode of a grid, in table order. The fault-free point is run once per (scale, policy, seed): it is
    the baseline of every fault kind and target."""
    points = [("bernoulli", float(x)) for x in loss if x > 0] + [("bursty", float(x)) for x in loss if x > 0] + \
             [("latency", float(x)) for x in latency if x > 0]
    work = []
    for sc in scales:
        for condition in conditions:
            for seed in seeds:
                work.append(FaultTask(sc, "none", condition, "none", 0.0, seed, steps))
        for target in targets:
            for condition in conditions:
                for kind, level in points:
                    for seed in seeds:
                        work.append(FaultTask(sc, target, condition, kind, level, seed, steps))
    return work


def run_fault_task(task: FaultTask) -> dict:
    """One grid episode -> its run-record line (module level: pickled to the worker processes)."""
    c0 = time.process_time()
    target = "dispatch" if task.target == "none" else task.target
    kind = "bernoulli" if task.kind == "none" else task.kind
    ep = run_fault_episode(task.condition, kind, task.level, task.seed, scale=task.scale, steps=task.steps,
                           target=target)
    ep.target, ep.kind = task.target, task.kind
    return {"key": task.key, "episode": {k: None if isinstance(v, float) and math.isnan(v) else v
                                         for k, v in ep.__dict__.items()}, "wall_s": ep.wall_s,
            # CPU seconds say what the grid costs on idle cores; the wall time depends on what else the machine runs
            "cpu_s": time.process_time() - c0}


#: fault-kind labels of the tables
KIND_LABEL = {"bernoulli": "Bernoulli loss, %", "bursty": f"Gilbert–Elliott loss (mean burst {BURST:g}), %",
              "latency": "latency, ticks (normal, jitter ¼ of the mean)"}
METRICS = catalogue.COST_METRICS


def summarize(episodes: list[FaultEpisode]) -> list[dict]:
    """Per (scale, target, condition, kind, level): mean and sample sd over seeds of each metric, the protocol's
    outcome counts, and Welch's p of deliveries against the same policy without faults. The fault-free point
    (level 0) heads every (target, kind) series."""
    from morph_sim.lab.grid import mean_sd, welch

    clean: dict[tuple, list[FaultEpisode]] = {}
    groups: dict[tuple, list[FaultEpisode]] = {}
    for ep in episodes:
        if ep.level == 0:
            clean.setdefault((ep.scale, ep.condition), []).append(ep)
        else:
            groups.setdefault((ep.scale, ep.target, ep.condition, ep.kind, ep.level), []).append(ep)
    series = {(sc, tg, c, k) for (sc, tg, c, k, _) in groups}
    if not groups:  # only fault-free points were run
        series = {(sc, "dispatch", c, "bernoulli") for (sc, c) in clean}
    for (sc, tg, c, k) in series:
        if (sc, c) in clean:
            groups[(sc, tg, c, k, 0.0)] = clean[(sc, c)]
    scales = list(dict.fromkeys(e.scale for e in episodes))
    kinds = ("bernoulli", "bursty", "latency")
    order = condition_order(k[2] for k in groups)
    rows = []
    for (scale, target, condition, kind, level), eps in sorted(groups.items(), key=lambda kv: (
            scales.index(kv[0][0]), TARGETS.index(kv[0][1]), kinds.index(kv[0][3]), order.index(kv[0][2]),
            kv[0][4])):
        row = {"scale": scale, "target": target, "condition": condition, "kind": kind, "level": level,
               "seeds": len(eps)}
        for name in METRICS:
            row[name], row[name + "_sd"] = mean_sd(getattr(e, name, None) for e in eps)
        base = clean.get((scale, condition), [])
        row["p_vs_clean"] = welch([e.deliveries for e in base], [e.deliveries for e in eps]) if level > 0 else None
        row["lost_share"] = float(sum(e.lost_attempts for e in eps) / max(1, sum(e.attempts for e in eps)))
        for k in ("on_time", "late_applied", "refused_stale", "expired", "duplicates"):
            row[k] = float(np.mean([e.outcomes.get(k, 0) for e in eps]))
        rows.append(row)
    return rows


def plot(rows: list[dict], path: str | Path, scale: str | None = None) -> Path:
    """One figure: rows = metrics, columns = fault kinds, one line per (policy, target); mean ± sd over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if scale is not None:
        rows = [r for r in rows if r["scale"] == scale]
    metrics = [("deliveries", "deliveries"), ("dispatch_delay", "dispatch delay, ticks"),
               ("messages_per_delivery", "dispatch messages per delivery"),
               ("bytes_per_delivery", "dispatch bytes per delivery"), ("mean_links", "mean links")]
    if any(r.get("view_age_mean") is not None for r in rows):
        metrics.append(("view_age_mean", "fleet view age, s"))
    kinds = [k for k in KIND_LABEL if any(r["kind"] == k for r in rows)]
    styles = {"dispatch": "-", "fleet": "--", "both": ":"}
    fig, axes = plt.subplots(len(metrics), len(kinds), figsize=(5.5 * len(kinds), 2.8 * len(metrics)),
                             squeeze=False)
    nan = float("nan")
    for i, (metric, mlabel) in enumerate(metrics):
        for j, kind in enumerate(kinds):
            ax = axes[i][j]
            for ci, condition in enumerate(condition_order(r["condition"] for r in rows)):
                for target in TARGETS:
                    pts = [r for r in rows if r["condition"] == condition and r["kind"] == kind
                           and r["target"] == target]
                    if not pts:
                        continue
                    ax.errorbar([r["level"] for r in pts], [nan if r[metric] is None else r[metric] for r in pts],
                                yerr=[nan if r[metric + "_sd"] is None else r[metric + "_sd"] for r in pts],
                                marker="o", markersize=3, capsize=2, color=f"C{ci}", linestyle=styles[target],
                                label=f"{condition}, {target}")
            ax.set_xlabel(KIND_LABEL[kind])
            ax.set_ylabel(mlabel)
            if kind == "latency":
                levels = sorted({r["level"] for r in rows if r["kind"] == kind})
                ax.set_xscale("symlog", linthresh=1.0)
                ax.set_xticks(levels, [f"{x:g}" for x in levels])
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=6, ncol=2)
    seeds = max((r["seeds"] for r in rows), default=0)
    fig.suptitle(f"MORPH and baselines under message faults{f' — {scale}' if scale else ''} (mean ± sd over {seeds} "
                 "seeds; line style: faults on dispatch —, fleet broadcast --, both ··)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _f(v, fmt="{:.1f}") -> str:
    return "–" if v is None else fmt.format(v)


def markdown(rows: list[dict]) -> str:
    """The study's tables: per scale and target, deliveries (mean ± sd, Welch p against the same policy without
    faults, bold below the Bonferroni threshold) and, beside them, what each delivery cost (dispatch delay in
    ticks, dispatch messages and bytes per delivery, the fleet view's mean age)."""
    from morph_sim.lab.grid import bonferroni, p_text

    m, thr = bonferroni([r["p_vs_clean"] for r in rows])
    out = [f"{m} comparisons (each policy at each fault point against itself without faults, Welch, two-sided); "
           f"Bonferroni threshold for a family-wise 5 %: p < {thr:.3g} (**bold**). Cells: mean ± sample sd over "
           "seeds."]
    scales = list(dict.fromkeys(r["scale"] for r in rows))
    for scale in scales:
        for target in TARGETS:
            block = [r for r in rows if r["scale"] == scale and r["target"] == target]
            if not block:
                continue
            seeds = max(r["seeds"] for r in block)
            out.append(f"\n### {scale}: faults on {_TARGET_TEXT[target]} ({seeds} seeds)")
            for kind in KIND_LABEL:
                kb = [r for r in block if r["kind"] == kind]
                if not kb or all(r["level"] == 0 for r in kb):
                    continue
                levels = sorted({r["level"] for r in kb})
                head = f"| {KIND_LABEL[kind]} | " + " | ".join(f"{x:g}" for x in levels) + " |"
                lines = ["", f"Deliveries — {KIND_LABEL[kind]}:", "", head, "|" + "---|" * (len(levels) + 1)]
                cost = ["", "Cost — dispatch delay (ticks) · dispatch messages / delivery · bytes / delivery"
                        + (" · fleet view age (s)" if target != "dispatch" else "") + ":", "", head,
                        "|" + "---|" * (len(levels) + 1)]
                for condition in condition_order(r["condition"] for r in kb):
                    by = {r["level"]: r for r in kb if r["condition"] == condition}
                    if not by:
                        continue
                    cells, costs = [], []
                    for x in levels:
                        r = by.get(x)
                        if r is None:
                            cells.append("")
                            costs.append("")
                            continue
                        c = f"{_f(r['deliveries'])} ± {_f(r['deliveries_sd'])}"
                        if x > 0:
                            c += ", " + p_text(r["p_vs_clean"], thr)
                        cells.append(c)
                        k = (f"{_f(r['dispatch_delay'])} · {_f(r['messages_per_delivery'])} · "
                             f"{_f(r['bytes_per_delivery'], '{:.0f}')}")
                        if target != "dispatch":
                            k += f" · {_f(r['view_age_mean'], '{:.2f}')}"
                        costs.append(k)
                    lines.append(f"| {condition} | " + " | ".join(cells) + " |")
                    cost.append(f"| {condition} | " + " | ".join(costs) + " |")
                out += lines + cost
    return "\n".join(out)


_TARGET_TEXT = {"dispatch": "the dispatch messages (request, reply, commitment, refusal)",
                "fleet": "the fleet broadcast (each agent learns and gates from its own view)",
                "both": "the dispatch messages and the fleet broadcast"}


def write_csv(rows: list[dict], path: Path) -> Path:
    import csv

    cols = list(rows[0]) if rows else []
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r[c] is None else r[c] for c in cols])
    return path


def grid_plan(*, quick: bool = False, scales=("tiny",), seeds=None, steps: int | None = None, conditions=None,
              targets=None, loss=None, latency=None) -> dict:
    """The grid as plain data (the run record's identity): the full study, or ``quick``, the reduced CI version."""
    if quick:
        plan = {"scales": list(scales), "seeds": list(seeds or (1,)),
                "conditions": list(conditions or ("MORPH (reference)", "Full-Graph")),
                "targets": list(targets or ("dispatch",)), "loss": list(loss or (0, 30)),
                "latency": list(latency or (0.0, 1.0)), "steps": steps or 150}
    else:
        plan = {"scales": list(scales), "seeds": list(seeds or range(1, 11)),
                "conditions": list(conditions or CONDITIONS), "targets": list(targets or TARGETS),
                "loss": list(LOSS_PCT if loss is None else loss),
                "latency": list(LATENCY_TICKS if latency is None else latency), "steps": steps or 800}
    plan["conditions"] = [CONDITION_KEYS.get(c, c) for c in plan["conditions"]]
    for c in plan["conditions"]:
        study_condition(c, CONDITIONS)  # the study's own, or a policy from outside by name; else one line
    for t in plan["targets"]:
        if t not in TARGETS:
            raise ValueError(f"targets: unknown {t!r}; choose from {', '.join(TARGETS)}")
    for x in plan["loss"]:
        if not 0 <= x < 100:
            raise ValueError(f"loss-levels: {x:g} is not a loss in percent in [0, 100)")
    for x in plan["latency"]:
        if not 0 <= x <= 1000:
            raise ValueError(f"latency-levels: {x:g} is not a latency in ticks in [0, 1000]")
    if plan["steps"] < 1:
        raise ValueError("steps: must be >= 1")
    return plan


def run_experiment(run_dir: str | Path, *, quick: bool = False, progress=False, scales=("tiny",), seeds=None,
                   steps: int | None = None, jobs: int = 1, conditions=None, targets=None, loss=None, latency=None,
                   argv=None) -> dict:
    """Run (or resume) the grid into the run record ``run_dir``; write ``faults.json``, ``faults.csv``,
    ``faults.md`` and one figure per scale there. Returns {"rows", "json", "md", "png" (the first figure), "pngs",
    "wall_s", "ran", "skipped", "markdown"}."""
    from morph_sim.lab.grid import run_grid

    t0 = time.perf_counter()
    plan = grid_plan(quick=quick, scales=scales, seeds=seeds, steps=steps, conditions=conditions, targets=targets,
                     loss=loss, latency=latency)
    tasks = fault_tasks(scales=plan["scales"], targets=plan["targets"], conditions=plan["conditions"],
                        loss=plan["loss"], latency=plan["latency"], seeds=plan["seeds"], steps=plan["steps"])
    out = Path(run_dir)
    grid = run_grid(out, kind="faults", plan=plan, tasks=[(t.key, t) for t in tasks], fn=run_fault_task,
                    jobs=jobs, progress=progress, argv=argv)
    episodes = [FaultEpisode(**grid.done[t.key]["episode"]) for t in tasks]
    rows = summarize(episodes)
    (out / "faults.json").write_text(json.dumps({"plan": plan, "rows": rows,
                                                 "episodes": [grid.done[t.key]["episode"] for t in tasks]}, indent=1))
    write_csv(rows, out / "faults.csv")
    md = markdown(rows)
    (out / "faults.md").write_text(md + "\n")
    pngs = [str(plot(rows, out / f"faults_{sc}.png", sc)) for sc in plan["scales"]]
    return {"rows": rows, "json": str(out / "faults.json"), "md": str(out / "faults.md"), "png": pngs[0],
            "pngs": pngs, "wall_s": time.perf_counter() - t0, "ran": grid.ran, "skipped": grid.skipped,
            "markdown": md}
