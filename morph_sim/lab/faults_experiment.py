"""The degradation study: deliveries, links and dispatch delay against latency and loss on the protocol's
messages, for MORPH (both presets), Full-Graph, TSG and Proximity, over scales and seeds.

Each episode is the lab's episode (:func:`morph_sim.lab.runner.run_episode`, the one tick loop) with network faults
on its discrete-event network: messages are delayed by the fault layer's per-link draw and delivered at send time
plus delay, never dropped for being late (docs/faults.md, "Late, not lost"). A fault acts on the dispatch messages
(request, reply, commitment, refusal), on the fleet broadcast (then every agent learns and gates from its own view),
or on both (``target``).

Measured per episode: deliveries, mean undirected links, mean dispatch delay (ticks an AGV waits from first needing
a picker until one is committed), the protocol's outcome counters, and dispatch messages per delivery.
"""

from __future__ import annotations

import json
import math
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from morph_sim.lab.network import dispatch_faults, fleet_faults
from morph_sim.lab.runner import REFERENCE_SEEDS, EpisodeSpec, run_episode
from schemas.faults import FaultSpec, Latency, Loss

DT = 1.0

#: condition label -> (lab condition, MORPH preset)
CONDITIONS: dict[str, tuple[str, str]] = {
    "MORPH (reference)": ("morph", "reference"),
    "MORPH (paper)": ("morph", "paper"),
    "Full-Graph": ("full", "reference"),
    "TSG": ("tsg", "reference"),
    "Proximity": ("proximity", "reference"),
}
LOSS_PCT = (0, 10, 20, 30, 40, 50)
LATENCY_TICKS = (0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0)
TARGETS = ("dispatch", "fleet", "both")
BURST = 4.0  # Gilbert–Elliott mean burst length, messages
PROXIMITY_RADIUS = 4  # RunConfig's default


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


def run_fault_episode(condition: str, kind: str, level: float, seed: int, *, scale: str = "tiny",
                      steps: int = 500, target: str = "dispatch") -> FaultEpisode:
    lab_condition, preset = CONDITIONS[condition]
    spec = EpisodeSpec(scale=scale, condition=lab_condition, preset=preset, seed=seed, steps=steps,
                       radius=PROXIMITY_RADIUS if lab_condition == "proximity" else None, fiedler_every=10**9,
                       faults=scoped(fault_spec(kind, level, seed), target))
    ep = run_episode(spec)
    s = ep.summary
    outcomes = {k.removeprefix("protocol_"): v for k, v in s.items() if k.startswith("protocol_")}
    d = s["deliveries"]
    return FaultEpisode(condition, kind, float(level), seed, int(d), float(s["mean_links"]),
                        float(s.get("dispatch_delay", float("nan"))), outcomes.get("requests", 0),
                        outcomes.get("expired", 0), ep.wall_s, target, scale, outcomes,
                        s["messages_sent"] / d if d else float("nan"),
                        s["bytes_sent"] / d if d else float("nan"))


def _run_point(args) -> FaultEpisode:
    return run_fault_episode(*args[:4], **args[4])


def sweep(*, seeds=REFERENCE_SEEDS, conditions=tuple(CONDITIONS), loss=LOSS_PCT, latency=LATENCY_TICKS,
          scales=("tiny",), targets=("dispatch",), steps: int = 800, jobs: int = 1, progress=None,
          scale: str | None = None) -> list[FaultEpisode]:
    if scale is not None:
        scales = (scale,)
    points = [("bernoulli", x) for x in loss] + [("bursty", x) for x in loss if x > 0] + \
             [("latency", x) for x in latency if x > 0]
    work = []
    for sc in scales:
        for target in targets:
            for condition in conditions:
                for kind, level in points:
                    if level == 0 and target != targets[0]:
                        continue  # the fault-free point is the same for every target
                    for seed in seeds:
                        work.append((condition, kind, level, seed, {"scale": sc, "steps": steps, "target": target}))
    out = []
    if jobs <= 1:
        for item in work:
            out.append(_run_point(item))
            if progress is not None:
                progress(out[-1], len(out), len(work))
        return out
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        for ep in pool.map(_run_point, work, chunksize=4):
            out.append(ep)
            if progress is not None:
                progress(ep, len(out), len(work))
    return out


def summarize(episodes: list[FaultEpisode]) -> list[dict]:
    """Mean and standard deviation over seeds per (scale, target, condition, kind, level); the fault-free level 0
    is shared by every kind and target."""
    groups: dict[tuple, list[FaultEpisode]] = {}
    targets = sorted({e.target for e in episodes}, key=TARGETS.index)
    for ep in episodes:
        kinds = ("bernoulli", "bursty", "latency") if ep.level == 0 else (ep.kind,)
        for kind in kinds:
            for target in (targets if ep.level == 0 else (ep.target,)):
                groups.setdefault((ep.scale, target, ep.condition, kind, ep.level), []).append(ep)
    rows = []
    for (scale, target, condition, kind, level), eps in sorted(groups.items(), key=lambda kv: (
            kv[0][0], TARGETS.index(kv[0][1]), list(CONDITIONS).index(kv[0][2]), kv[0][3], kv[0][4])):
        row = {"scale": scale, "target": target, "condition": condition, "kind": kind, "level": level,
               "seeds": len(eps)}
        for name in ("deliveries", "mean_links", "dispatch_delay", "messages_per_delivery", "bytes_per_delivery"):
            vals = np.array([getattr(e, name) for e in eps], dtype=float)
            row[name] = float(np.nanmean(vals)) if np.isfinite(vals).any() else float("nan")
            row[name + "_sd"] = float(np.nanstd(vals)) if np.isfinite(vals).any() else float("nan")
        row["lost_share"] = float(sum(e.lost_attempts for e in eps) / max(1, sum(e.attempts for e in eps)))
        for k in ("on_time", "late_applied", "refused_stale", "expired", "duplicates"):
            row[k] = float(np.mean([e.outcomes.get(k, 0) for e in eps]))
        rows.append({k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()})  # JSON
    return rows


def plot(rows: list[dict], path: str | Path, scale: str | None = None) -> Path:
    """One figure: rows = metrics, columns = fault kinds, one line per (condition, target)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if scale is not None:
        rows = [r for r in rows if r["scale"] == scale]
    metrics = (("deliveries", "deliveries"), ("mean_links", "mean links"), ("dispatch_delay", "dispatch delay, ticks"),
               ("messages_per_delivery", "dispatch messages per delivery"))
    kinds = (("bernoulli", "Bernoulli loss, %"), ("bursty", f"Gilbert–Elliott loss (burst {BURST:g}), %"),
             ("latency", "latency, ticks (jitter 25 %)"))
    styles = {"dispatch": "-", "fleet": "--", "both": ":"}
    fig, axes = plt.subplots(len(metrics), len(kinds), figsize=(16, 14), squeeze=False)
    for i, (metric, mlabel) in enumerate(metrics):
        for j, (kind, klabel) in enumerate(kinds):
            ax = axes[i][j]
            for ci, condition in enumerate(CONDITIONS):
                for target in TARGETS:
                    pts = [r for r in rows if r["condition"] == condition and r["kind"] == kind
                           and r["target"] == target]
                    if not pts:
                        continue
                    nan = float("nan")
                    ax.errorbar([r["level"] for r in pts], [nan if r[metric] is None else r[metric] for r in pts],
                                yerr=[nan if r[metric + "_sd"] is None else r[metric + "_sd"] for r in pts],
                                marker="o", capsize=3, color=f"C{ci}", linestyle=styles[target],
                                label=f"{condition}, {target}")
            ax.set_xlabel(klabel)
            ax.set_ylabel(mlabel)
            if kind == "latency":
                levels = sorted({r["level"] for r in rows if r["kind"] == kind})
                ax.set_xscale("symlog", linthresh=1.0)
                ax.set_xticks(levels, [f"{x:g}" for x in levels])
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"MORPH and baselines under message faults{f' ({scale})' if scale else ''}: late, not lost "
                 "(mean ± sd over seeds)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def markdown(rows: list[dict]) -> str:
    head = "| scale | target | condition | fault | level | deliveries | links | delay | msgs/delivery | expired |"
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        def f(v, fmt="{:.1f}"):
            return "–" if v is None else fmt.format(v)
        lines.append(f"| {r['scale']} | {r['target']} | {r['condition']} | {r['kind']} | {r['level']:g} | "
                     f"{f(r['deliveries'])} ± {f(r['deliveries_sd'])} | {f(r['mean_links'])} | "
                     f"{f(r['dispatch_delay'], '{:.2f}')} | {f(r['messages_per_delivery'])} | {r['expired']:.1f} |")
    return "\n".join(lines)


def run_experiment(out_dir: str | Path, *, quick: bool = False, progress=None, scales=("tiny",),
                   seeds=None, steps: int | None = None, jobs: int = 1, conditions=None,
                   targets=TARGETS) -> dict:
    """Run the sweep (``quick``: the reduced CI version), write ``faults.json``, ``faults.md`` and one figure per
    scale under ``out_dir``; returns {"rows", "json", "png" (the first figure), "pngs", "wall_s"}."""
    t0 = time.perf_counter()
    if quick:
        episodes = sweep(seeds=seeds or (1,), conditions=conditions or ("MORPH (reference)", "Full-Graph"),
                         loss=(0, 30), latency=(0.0, 1.0), steps=steps or 150, scales=scales,
                         targets=("dispatch",), jobs=jobs, progress=progress)
    else:
        episodes = sweep(seeds=seeds or tuple(range(1, 11)), conditions=conditions or tuple(CONDITIONS),
                         steps=steps or 800, scales=scales, targets=targets, jobs=jobs, progress=progress)
    rows = summarize(episodes)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "faults.json").write_text(json.dumps(
        {"rows": rows, "episodes": [{k: None if isinstance(v, float) and math.isnan(v) else v
                                     for k, v in e.__dict__.items()} for e in episodes]}, indent=1))
    (out / "faults.md").write_text(markdown(rows) + "\n")
    pngs = [str(plot(rows, out / f"faults_{sc}.png", sc)) for sc in dict.fromkeys(e.scale for e in episodes)]
    return {"rows": rows, "json": str(out / "faults.json"), "png": pngs[0], "pngs": pngs,
            "wall_s": time.perf_counter() - t0}
