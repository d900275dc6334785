"""The paper-preset audit (docs/morph.md §4a): each departure of the ``paper`` preset from the paper, measured.

Every variant is the ``paper`` preset with a few parameters changed back to what the preset did before the audit (or
to what the paper says, for a departure we keep with a reason); each runs as an ablation study (conditions × scales ×
seeds) through :func:`morph_sim.lab.suite.run_suite`, and the table compares each variant's MORPH with the paper
preset's (Welch's two-sided t-test over seeds). The paper preset's own run also holds Full-Graph, TSG, v1 (the
reference's) and v1 as the paper states it, and Proximity calibrated to the converged link count, so the same table
answers "how high is the paper preset's gate, and does the gate level matter here?".
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.metrics import measures
from services.policies.conditions import AUDIT_STUDY, select
from services.policies.presets import load_preset

#: variant -> (departure, what it changes, overrides of the paper preset's params)
VARIANTS: dict[str, tuple[str, str, dict]] = {
    "paper": ("—", "the paper preset as it is now", {}),
    "before": ("d, f", "the paper preset before the audit: θ_form over 100 updates, θ_adj floor 0.36, h ≤ 1, "
               "d_exp per scale", {"theta_form_anneal": 100, "theta_form_anneal_over": "updates",
                                   "theta_adj_floor": 0.8, "h_max": 1.0,
                                   "expected_delivery_rate": {"tiny": 0.07, "small": 0.09, "medium": 0.12,
                                                              "large": 0.14}}),
    "task_sets_per_step": ("a", "T_i = the tasks held at step t (the paper's letter), not over 40 ticks",
                           {"task_window": 1}),
    "no_alpha_r": ("b", "α_r = 0 (it only writes picker rows, which dispatch never reads)", {"reward_alpha": 0.0}),
    "anneal_100": ("d", "θ_form annealed over 100 updates (the reference) instead of the episode",
                   {"theta_form_anneal": 100, "theta_form_anneal_over": "updates"}),
    "h_clip_1": ("f", "h clipped at 1 (the reference)", {"h_max": 1.0}),
    "theta_floor": ("f", "θ_adj floored at 0.8 · θ_end = 0.36 (the reference)", {"theta_adj_floor": 0.8}),
    "d_exp_per_scale": ("f", "η's starting baseline d_exp per scale 0.07/0.09/0.12/0.14 (the reference)",
                        {"expected_delivery_rate": {"tiny": 0.07, "small": 0.09, "medium": 0.12, "large": 0.14}}),
}
#: conditions of the paper preset's own run (the other variants run MORPH only)
PAPER_CONDITIONS = tuple(select(AUDIT_STUDY))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "inf" if v == math.inf else "-inf" if v == -math.inf else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {v!r} as TOML")


def variant_toml(name: str) -> str:
    """The TOML text of a variant: the paper preset with the variant's overrides (ablations kept)."""
    preset = load_preset("paper")
    params = preset.params.model_dump()
    params.update(VARIANTS[name][2])
    lines = [f"name = {json.dumps('audit-' + name)}", f"rules = {json.dumps(preset.rules)}",
             f"description = {json.dumps(VARIANTS[name][1])}", "", "[params]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in params.items()]
    for abl, overrides in preset.ablations.items():
        lines += ["", f"[ablations.{abl}]"] + [f"{k} = {_toml_value(v)}" for k, v in overrides.items()]
    return "\n".join(lines) + "\n"


@dataclass
class AuditResult:
    rows: list[dict]
    calibration: dict
    wall_s: float
    run_dir: Path


def run_audit(out: Path, *, scales=("small", "medium"), seeds=(11, 12, 13, 14, 15), steps: int = 800,
              variants=tuple(VARIANTS), jobs: int = 2, show_progress: bool = True, argv=None) -> AuditResult:
    from morph_sim.lab.suite import SuiteConfig, run_suite

    out.mkdir(parents=True, exist_ok=True)
    (out / "presets").mkdir(exist_ok=True)
    episodes: dict[str, list[dict]] = {}
    calibration: dict = {}
    wall = 0.0
    for name in variants:
        if name not in VARIANTS:
            raise ValueError(f"variant: unknown {name!r}; choose from {', '.join(VARIANTS)}")
        path = out / "presets" / f"{name}.toml"
        path.write_text(variant_toml(name), encoding="utf-8")
        load_preset(str(path))  # validate before any episode runs
        cfg = SuiteConfig(kind="ablation", preset=str(path), scales=tuple(scales), seeds=tuple(seeds), steps=steps,
                          conditions=PAPER_CONDITIONS if name == "paper" else ("morph",), jobs=jobs)
        res = run_suite(cfg, out, name, show_progress=show_progress, argv=argv)
        episodes[name] = res.episodes
        wall += res.wall_s
        if name == "paper":
            calibration = res.calibration
    rows = summarise_audit(episodes, scales)
    (out / "audit.json").write_text(json.dumps({"rows": rows, "calibration": calibration, "wall_s": wall,
                                                "scales": list(scales), "seeds": list(seeds), "steps": steps,
                                                "argv": argv}, indent=1), encoding="utf-8")
    result = AuditResult(rows, calibration, wall, out)
    (out / "audit.md").write_text(markdown_audit(result), encoding="utf-8")
    return result


def summarise_audit(episodes: dict[str, list[dict]], scales) -> list[dict]:
    base = {sc: [e["deliveries"] for e in episodes.get("paper", []) if e["scale"] == sc and e["condition"] == "morph"]
            for sc in scales}
    rows = []
    for name, eps in episodes.items():
        conditions = sorted({e["condition"] for e in eps}, key=PAPER_CONDITIONS.index)
        for c in conditions:
            row = {"variant": name, "departure": VARIANTS[name][0], "condition": c}
            for sc in scales:
                group = [e for e in eps if e["scale"] == sc and e["condition"] == c]
                d = np.array([e["deliveries"] for e in group], dtype=float)
                p = float("nan")
                same = (name, c) != ("paper", "morph") and d.tolist() == [float(x) for x in base[sc]]
                if same:
                    p = 1.0
                elif (name, c) != ("paper", "morph") and len(base[sc]) > 1 and len(d) > 1:
                    from scipy import stats  # here: scipy.stats costs half a CPU-second to import

                    with warnings.catch_warnings():  # near-constant groups: scipy warns, the p-value stands
                        warnings.simplefilter("ignore", RuntimeWarning)
                        p = float(stats.ttest_ind(d, base[sc], equal_var=False).pvalue)
                row[sc] = {"mean": float(d.mean()), "std": float(d.std()), "per_seed": d.astype(int).tolist(),
                           "gate": measures.nan_mean(e["mean_p_respond"] for e in group),
                           "links": float(np.mean([e["mean_links"] for e in group])),
                           "links_converged": float(np.mean([e["mean_links_converged"] for e in group])),
                           "p_vs_paper": p,
                           "same_as_paper": same}
            rows.append(row)
    return rows


def markdown_audit(result: AuditResult) -> str:
    scales = [k for k in result.rows[0] if k not in ("variant", "departure", "condition")] if result.rows else []
    head = "| variant | departure | condition | " + " | ".join(
        f"{sc}: deliveries (p vs paper) | {sc}: gate | {sc}: links (converged)" for sc in scales) + " |"
    lines = [head, "|" + "---|" * (3 + 3 * len(scales))]
    for r in result.rows:
        cells = []
        for sc in scales:
            v = r[sc]
            p = "" if math.isnan(v["p_vs_paper"]) else (" (identical)" if v["same_as_paper"]
                                                        else f" (p = {v['p_vs_paper']:.2f})")
            cells += [f"{v['mean']:.1f} ± {v['std']:.1f}{p}", f"{v['gate']:.3f}",
                      f"{v['links']:.1f} ({v['links_converged']:.1f})"]
        lines.append(f"| {r['variant']} | {r['departure']} | {r['condition']} | " + " | ".join(cells) + " |")
    if result.calibration:
        lines.append("")
        for sc, c in result.calibration.items():
            lines.append(f"Proximity at {sc}: MORPH links over the episode {c['episode_links']:.1f}, converged "
                         f"(second half) {c['converged_links']:.1f}; calibrated to the {c['target']} count → "
                         f"radius {c['radius']}")
    lines.append("")
    lines.append(f"wall time {result.wall_s:.0f} s")
    return "\n".join(lines)
