"""The network study: MORPH (both presets), Full-Graph (unicast and broadcast), TSG and Proximity under the named
network profiles (services/faults/profiles/, docs/faults.md "Network profiles"), at every scale, over fresh seeds.

Each episode is the lab's episode (:func:`morph_sim.lab.runner.run_episode`) with ``network=<profile>``: the services'
radio model (access points, hand-overs, dead zones, rate limits and queues) judges every protocol message and every
copy of the fleet broadcast, so each agent learns and gates from its own, possibly late, view of the fleet.

Measured per episode: deliveries, dispatch delay (ticks from needing a picker to having one), dispatch messages and
bytes per delivery, the fleet view's mean age, mean links, and the radio's hand-overs, outage and losses. The tables
compare every policy with all-to-all coordination at the same scale and profile (Welch, two-sided, over seeds) —
the paper's communication claims — and the grid is one resumable run record (morph_sim/lab/grid.py).
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.metrics import catalogue
from services.policies.conditions import (
    DEFAULT_RADIUS,
    NETWORK_STUDY,
    by_label,
    command_line_keys,
    study_condition,
)

#: the study's conditions by label (its records name a condition by its label); Proximity at RunConfig's radius
CONDITIONS = by_label(NETWORK_STUDY)
#: the command line's names of the conditions
CONDITION_KEYS = {k: c.label for k, c in command_line_keys(NETWORK_STUDY).items()}
PROFILES = ("lan", "wifi-fast-roaming", "wifi-legacy-roaming", "congested", "lossy-mesh")
SCALES = ("tiny", "small", "medium", "large")
#: fresh seeds: neither the tuning seeds 1–10 nor the reference's 42, 7, 123, 999, 2024, nor the audit's 11–15
SEEDS = tuple(range(301, 311))
#: the default grid's episode length per scale, chosen so that the whole default grid runs within 15 minutes on two
#: cores (per-agent brains make MORPH's cost grow with the fleet; measured in docs/results.md)
STEPS = {"tiny": 800, "small": 800, "medium": 600, "large": 400}
METRICS = (*catalogue.COST_METRICS, *catalogue.episode_metrics(
    "network_handovers", "network_outage_seconds", "network_stops", "messages_dropped"))


def available_conditions() -> tuple[str, ...]:
    """The study's policies this lab can run (the broadcast Full-Graph needs the lab's ``full-broadcast``)."""
    return tuple(CONDITIONS)


def all_to_all() -> str:
    """The paper's all-to-all: the broadcast Full-Graph where the lab has it, else the unicast one."""
    return "Full-Graph (broadcast)" if "Full-Graph (broadcast)" in available_conditions() else "Full-Graph"


@dataclass(frozen=True)
class NetworkTask:
    scale: str
    profile: str
    condition: str
    seed: int
    steps: int

    @property
    def key(self) -> str:
        return f"{self.scale}|{self.profile}|{self.condition}|seed={self.seed}|T={self.steps}"


def run_network_task(task: NetworkTask) -> dict:
    """One episode -> its run-record line (module level: pickled to the worker processes)."""
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    t0, c0 = time.perf_counter(), time.process_time()
    s = run_episode(EpisodeSpec(scale=task.scale, seed=task.seed, steps=task.steps,
                                **study_condition(task.condition, CONDITIONS).episode_fields(radius=DEFAULT_RADIUS),
                                fiedler_every=10**9, network=task.profile)).summary
    d = s["deliveries"]
    ep = {"scale": task.scale, "profile": task.profile, "condition": task.condition, "seed": task.seed,
          "steps": task.steps, "deliveries": int(d), "dispatch_delay": s.get("dispatch_delay"),
          "messages_per_delivery": s["messages_sent"] / d if d else None,
          "bytes_per_delivery": s["bytes_sent"] / d if d else None, "view_age_mean": s.get("view_age_mean"),
          "mean_links": s["mean_links"], "network_handovers": s.get("network_handovers"),
          "network_outage_seconds": s.get("network_outage_seconds"), "network_stops": s.get("network_stops"),
          "messages_dropped": s.get("messages_dropped"), "messages_sent": s.get("messages_sent"),
          "mean_p_respond": s.get("mean_p_respond"),
          **{k: v for k, v in s.items() if k.startswith("network_lost_") or k.startswith("protocol_")}}
    ep = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in ep.items()}
    # CPU seconds say what the grid costs on idle cores; the wall time depends on what else the machine runs
    return {"key": task.key, "episode": ep, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def grid_plan(*, scales=SCALES, profiles=PROFILES, conditions=None, seeds=SEEDS, steps: int | None = None) -> dict:
    """The grid as plain data (the run record's identity). ``steps``: one length for every scale (default
    :data:`STEPS`)."""
    from services.faults.network import load_profile
    from services.world.layout import named_sizes

    conditions = [CONDITION_KEYS.get(c, c) for c in (conditions or available_conditions())]
    for c in conditions:
        if c not in CONDITIONS:
            study_condition(c, CONDITION_KEYS)  # a policy from outside, by name; else one line naming it
            continue
        if c not in available_conditions():
            raise ValueError(f"conditions: {c!r} needs the lab condition {CONDITIONS[c].key!r}, which this "
                             "version does not have")
    for sc in scales:
        if sc not in named_sizes():
            raise ValueError(f"scales: unknown scale {sc!r} (choose from {', '.join(named_sizes())})")
    for p in profiles:
        try:
            load_profile(p)
        except ValueError as exc:
            raise ValueError(f"profiles: {str(exc).removeprefix('network: ')}") from None
    if steps is not None and steps < 1:
        raise ValueError("steps: must be >= 1")
    if not (scales and profiles and conditions and seeds):
        raise ValueError("scales/profiles/conditions/seeds: the grid is empty")
    return {"scales": list(scales), "profiles": list(profiles), "conditions": conditions, "seeds": list(seeds),
            "steps": {sc: steps or STEPS.get(sc, 200) for sc in scales}}


def network_tasks(plan: dict) -> list[NetworkTask]:
    return [NetworkTask(sc, p, c, s, plan["steps"][sc]) for sc in plan["scales"] for p in plan["profiles"]
            for c in plan["conditions"] for s in plan["seeds"]]


# -- tables ---------------------------------------------------------------------------------------------------------
def summarize(plan: dict, episodes: list[dict]) -> list[dict]:
    """Per (scale, profile, condition): mean and sample sd over seeds of every metric; Welch p of deliveries against
    the unicast Full-Graph and against all-to-all (:func:`all_to_all`) at the same scale and profile."""
    from morph_sim.lab.grid import mean_sd, welch

    by: dict[tuple, list[dict]] = {}
    for e in episodes:
        by.setdefault((e["scale"], e["profile"], e["condition"]), []).append(e)
    a2a = all_to_all() if all_to_all() in plan["conditions"] else "Full-Graph"
    rows = []
    for sc in plan["scales"]:
        for p in plan["profiles"]:
            for c in plan["conditions"]:
                eps = by.get((sc, p, c), [])
                if not eps:
                    continue
                row = {"scale": sc, "profile": p, "condition": c, "seeds": len(eps), "steps": eps[0]["steps"]}
                for m in METRICS:
                    row[m], row[m + "_sd"] = mean_sd(e.get(m) for e in eps)
                for ref, name in (("Full-Graph", "p_vs_full"), (a2a, "p_vs_all_to_all")):
                    other = by.get((sc, p, ref), [])
                    row[name] = (welch([e["deliveries"] for e in other], [e["deliveries"] for e in eps])
                                 if c != ref and other else None)
                rows.append(row)
    return rows


def claims(plan: dict, episodes: list[dict]) -> list[dict]:
    """The paper's claims, per scale and profile: each MORPH preset against all-to-all — the difference of mean
    deliveries (and per seed, common random numbers: the same warehouse), Welch p — and, for "the benefit compounds
    at scale", the per-seed differences at each scale against those at the smallest."""
    from morph_sim.lab.grid import mean_sd, welch

    a2a = all_to_all() if all_to_all() in plan["conditions"] else "Full-Graph"
    by = {(e["scale"], e["profile"], e["condition"], e["seed"]): e for e in episodes}
    out = []
    for morph in ("MORPH (reference)", "MORPH (paper)"):
        if morph not in plan["conditions"] or a2a not in plan["conditions"]:
            continue
        for p in plan["profiles"]:
            first = None
            for sc in plan["scales"]:
                pairs = [(by[(sc, p, morph, s)], by[(sc, p, a2a, s)]) for s in plan["seeds"]
                         if (sc, p, morph, s) in by and (sc, p, a2a, s) in by]
                if not pairs:
                    continue
                diffs = [m["deliveries"] - f["deliveries"] for m, f in pairs]
                rel = [(m["deliveries"] - f["deliveries"]) / f["deliveries"] for m, f in pairs if f["deliveries"]]
                mean, sd = mean_sd(diffs)
                row = {"morph": morph, "all_to_all": a2a, "profile": p, "scale": sc, "seeds": len(pairs),
                       "diff": mean, "diff_sd": sd,
                       "rel_diff": mean / float(np.mean([f["deliveries"] for _, f in pairs])) if mean is not None
                       and any(f["deliveries"] for _, f in pairs) else None,
                       "p": welch([f["deliveries"] for _, f in pairs], [m["deliveries"] for m, _ in pairs]),
                       "p_vs_smallest": None}
                if first is None:
                    first = rel
                else:
                    row["p_vs_smallest"] = welch(first, rel)
                out.append(row)
    return out


def _f(v, fmt="{:.1f}") -> str:
    return "–" if v is None else fmt.format(v)


def markdown(plan: dict, rows: list[dict], claim_rows: list[dict]) -> str:
    from morph_sim.lab.grid import bonferroni, p_text

    a2a = all_to_all() if all_to_all() in plan["conditions"] else "Full-Graph"
    ps = [r["p"] for r in claim_rows] + [r["p_vs_smallest"] for r in claim_rows]
    m, thr = bonferroni(ps)
    steps = ", ".join(f"{sc} {plan['steps'][sc]}" for sc in plan["scales"])
    seeds = plan["seeds"]
    out = [f"Seeds {seeds[0]}–{seeds[-1]} ({len(seeds)})" if seeds == list(range(seeds[0], seeds[-1] + 1))
           else f"Seeds {', '.join(map(str, seeds))}", f"; steps per episode: {steps}. Cells: mean ± sample sd over "
           "seeds.", "", "### The paper's claims: MORPH against all-to-all "
           f"({a2a})", "",
           f"Mean per-seed difference of deliveries, MORPH − {a2a} (relative to {a2a}'s mean), Welch p of the two "
           f"samples; 'vs {plan['scales'][0]}': Welch p of the relative per-seed differences at this scale against those at "
           f"{plan['scales'][0]} (does the benefit compound?). {m} comparisons; Bonferroni threshold for a "
           f"family-wise 5 %: p < {thr:.3g} (**bold**).", ""]
    out[0] = out[0] + out.pop(1)
    head = "| MORPH | profile | " + " | ".join(plan["scales"]) + " |"
    out += [head, "|" + "---|" * (len(plan["scales"]) + 2)]
    for morph in ("MORPH (reference)", "MORPH (paper)"):
        for p in plan["profiles"]:
            cells = []
            for sc in plan["scales"]:
                r = next((r for r in claim_rows if r["morph"] == morph and r["profile"] == p and r["scale"] == sc),
                         None)
                if r is None:
                    cells.append("")
                    continue
                c = f"{_f(r['diff'], '{:+.1f}')} ({_f(None if r['rel_diff'] is None else 100 * r['rel_diff'], '{:+.0f}')} %), {p_text(r['p'], thr)}"
                if r["p_vs_smallest"] is not None:
                    c += f"; vs {plan['scales'][0]} {p_text(r['p_vs_smallest'], thr).removeprefix('p = ')}"
                cells.append(c)
            if any(cells):
                out.append(f"| {morph} | {p} | " + " | ".join(cells) + " |")
    for sc in plan["scales"]:
        block = [r for r in rows if r["scale"] == sc]
        if not block:
            continue
        out += ["", f"### {sc} (T = {plan['steps'][sc]})", "",
                "| profile | policy | deliveries | p vs Full-Graph | dispatch delay (ticks) | messages / delivery | "
                "bytes / delivery | view age (s) | links | hand-overs | outage (robot-s) | stopped (robot-steps) |",
                "|" + "---|" * 12]
        for r in block:
            out.append(
                f"| {r['profile']} | {r['condition']} | {_f(r['deliveries'])} ± {_f(r['deliveries_sd'])} | "
                f"{'–' if r['p_vs_full'] is None else p_text(r['p_vs_full'], 0).removeprefix('p = ')} | "
                f"{_f(r['dispatch_delay'])} | {_f(r['messages_per_delivery'])} | "
                f"{_f(r['bytes_per_delivery'], '{:.0f}')} | {_f(r['view_age_mean'], '{:.2f}')} | "
                f"{_f(r['mean_links'])} | {_f(r['network_handovers'], '{:.0f}')} | "
                f"{_f(r['network_outage_seconds'], '{:.0f}')} | {_f(r['network_stops'], '{:.0f}')} |")
    return "\n".join(out)


def plot(rows: list[dict], path: str | Path, scale: str) -> Path:
    """One figure per scale: a panel per metric, policies side by side per profile (mean ± sd over seeds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["scale"] == scale]
    profiles = list(dict.fromkeys(r["profile"] for r in rows))
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    metrics = (("deliveries", "deliveries"), ("dispatch_delay", "dispatch delay, ticks"),
               ("messages_per_delivery", "dispatch messages / delivery"),
               ("bytes_per_delivery", "dispatch bytes / delivery"), ("view_age_mean", "fleet view age, s"),
               ("mean_links", "mean links"))
    fig, axes = plt.subplots(len(metrics), 1, figsize=(12, 2.6 * len(metrics)), squeeze=False)
    width = 0.8 / max(len(conditions), 1)
    x = np.arange(len(profiles))
    for i, (metric, label) in enumerate(metrics):
        ax = axes[i][0]
        for j, c in enumerate(conditions):
            vals, errs = [], []
            for p in profiles:
                r = next((r for r in rows if r["profile"] == p and r["condition"] == c), None)
                vals.append(np.nan if r is None or r[metric] is None else r[metric])
                errs.append(np.nan if r is None or r[metric + "_sd"] is None else r[metric + "_sd"])
            ax.bar(x + (j - (len(conditions) - 1) / 2) * width, vals, width, yerr=errs, capsize=2, color=f"C{j}",
                   label=c)
        ax.set_xticks(x, profiles)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    axes[0][0].legend(fontsize=7, ncol=3)
    seeds = max((r["seeds"] for r in rows), default=0)
    steps = rows[0]["steps"] if rows else 0
    fig.suptitle(f"Policies under network profiles — {scale}, T = {steps} (mean ± sd over {seeds} seeds)")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def services_check(plan: dict, episodes: list[dict], cell: tuple[str, str, str], out: Path) -> dict:
    """One cell of the grid (scale, profile, condition label) run again through the services in one process (what
    ``morph-sim run`` runs: sim, agents, monitor and, under a rate-limited profile, the air, over the in-process bus),
    seed by seed, beside the lab's episodes: the services' deliveries and mean view age must be the lab's."""
    import asyncio

    from morph_sim.local import run_local
    from services.runconfig import RunConfig

    scale, profile, label = cell
    cond = CONDITIONS[label]
    rows = []
    for seed in plan["seeds"]:
        lab = next(e for e in episodes if (e["scale"], e["profile"], e["condition"], e["seed"]) ==
                   (scale, profile, label, seed))
        cfg = RunConfig(run_id=f"check-{seed}", scale=scale, policy=cond.policy, ablation=cond.ablation,
                        preset=cond.preset or "reference", seed=seed, steps=plan["steps"][scale], network=profile,
                        output_dir=out)
        result = asyncio.run(run_local(cfg, record=False))
        ages = [r["view_age_mean"] for r in result.monitor.rows if r.get("view_age_mean") is not None]
        age = sum(ages) / len(ages) if ages else None
        same = result.sim.deliveries == lab["deliveries"] and (
            age is None and lab["view_age_mean"] is None
            or age is not None and lab["view_age_mean"] is not None and abs(age - lab["view_age_mean"]) <= 1e-9)
        rows.append({"seed": seed, "lab_deliveries": lab["deliveries"], "services_deliveries": result.sim.deliveries,
                     "lab_view_age_mean": lab["view_age_mean"], "services_view_age_mean": age, "equal": same})
    return {"scale": scale, "profile": profile, "condition": label, "seeds": rows,
            "equal": all(r["equal"] for r in rows)}


def services_check_markdown(check: dict) -> str:
    lines = [f"## Services cross-check: {check['condition']} under `{check['profile']}` at {check['scale']}", "",
             "| seed | lab deliveries | services deliveries | lab view age (s) | services view age (s) | equal |",
             "|---|---|---|---|---|---|"]
    for r in check["seeds"]:
        lines.append(f"| {r['seed']} | {r['lab_deliveries']} | {r['services_deliveries']} | "
                     f"{_f(r['lab_view_age_mean'], '{:.3f}')} | {_f(r['services_view_age_mean'], '{:.3f}')} | "
                     f"{'yes' if r['equal'] else '**no**'} |")
    return "\n".join(lines)


def parse_cell(value: str, plan: dict) -> tuple[str, str, str]:
    """``SCALE:PROFILE:CONDITION`` (a cell of ``plan``) as (scale, profile, condition label); ValueError naming the
    flag otherwise."""
    parts = value.split(":")
    if len(parts) != 3:
        raise ValueError(f"services_cell: expected SCALE:PROFILE:CONDITION, got {value!r}")
    scale, profile, condition = parts
    label = CONDITION_KEYS.get(condition, condition)
    if scale not in plan["scales"] or profile not in plan["profiles"] or label not in plan["conditions"]:
        raise ValueError(f"services_cell: {value!r} is not a cell of this grid (scales {', '.join(plan['scales'])}; "
                         f"profiles {', '.join(plan['profiles'])}; conditions {', '.join(plan['conditions'])})")
    if label not in CONDITIONS:
        raise ValueError(f"services_cell: {condition!r} is a policy from outside; the cross-check runs the study's own")
    return scale, profile, label


def run_study(run_dir: str | Path, plan: dict, *, jobs: int = 2, progress=False, argv=None,
              services_cell: tuple[str, str, str] | None = None) -> dict:
    """Run (or resume) the grid into the run record ``run_dir``; write ``network.json``, ``network.csv``,
    ``network.md`` and ``network_<scale>.png`` there."""
    from morph_sim.lab.grid import run_grid

    t0 = time.perf_counter()
    tasks = network_tasks(plan)
    out = Path(run_dir)
    grid = run_grid(out, kind="network", plan=plan, tasks=[(t.key, t) for t in tasks], fn=run_network_task,
                    jobs=jobs, progress=progress, argv=argv)
    episodes = [grid.done[t.key]["episode"] for t in tasks]
    rows = summarize(plan, episodes)
    claim_rows = claims(plan, episodes)
    md = markdown(plan, rows, claim_rows)
    check = None
    if services_cell is not None:
        check = services_check(plan, episodes, services_cell, out / "services-check")
        (out / "services_check.json").write_text(json.dumps(check, indent=1))
        md += "\n\n" + services_check_markdown(check)
    (out / "network.json").write_text(json.dumps({"plan": plan, "rows": rows, "claims": claim_rows,
                                                  "episodes": episodes}, indent=1))
    with open(out / "network.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        cols = list(rows[0]) if rows else []
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r[c] is None else r[c] for c in cols])
    (out / "network.md").write_text(md + "\n")
    pngs = [str(plot(rows, out / f"network_{sc}.png", sc)) for sc in plan["scales"]]
    return {"rows": rows, "claims": claim_rows, "markdown": md, "md": str(out / "network.md"),
            "json": str(out / "network.json"), "pngs": pngs, "ran": grid.ran, "skipped": grid.skipped,
            "wall_s": time.perf_counter() - t0, "services_check": check,
            "cpu_s": sum(grid.done[t.key].get("cpu_s", 0.0) for t in tasks)}
