"""The paper's spatial demand-shift experiment (paper Table 4; docs/morph.md).

Medium warehouse, six phases alternating left/right demand (L–R–L–R–L–R), each ``phase_steps`` long. Demand
shift = replacement requests drawn from the active half of the shelves (:meth:`Warehouse.set_demand_side`); the
reference's assignment filter is ``demand_mode="assignment"``. Per episode: deliveries per phase P1…P6, Δ6−3 and
the recovery times r3…r6 of :func:`measures.shift_recoveries` (censored at the phase length). Episodes run in
parallel processes; each gets a run record like the scale suite's.
"""

from __future__ import annotations

import csv
import json
import sys
import time
from concurrent.futures import as_completed
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from morph_sim.lab.executors import episode_pool
from morph_sim.lab.runner import (
    REFERENCE_SEEDS,
    EpisodeResult,
    EpisodeSpec,
    check_nonempty,
    run_episode,
)
from morph_sim.lab.suite import _git_revision, _jsonable, _num, _versions
from services.metrics import measures
from services.policies.conditions import SHIFT_STUDY, select, study_condition

#: the shift study's conditions: MORPH and MORPH-reset at both presets, Proximity and TSG
SHIFT_CONDITIONS = select(SHIFT_STUDY)
#: 20 seeds: the reference's five, then 1…15 (the paper does not list its seeds)
SHIFT_SEEDS = REFERENCE_SEEDS + tuple(range(1, 16))
#: the paper's Table 4 (Medium, 20 seeds): P1…P6, Δ6−3, r3…r6
PAPER_TABLE4 = {
    "proximity": (51.1, 48.2, 45.7, 41.8, 37.9, 34.1, -11.6, 45.0, 57.9, 96.0, 83.5),
    "tsg": (49.9, 46.0, 44.6, 41.4, 38.8, 38.1, -6.5, 40.8, 54.6, 39.8, 50.0),
    "morph": (50.0, 49.1, 47.5, 46.1, 45.2, 44.0, -3.5, 36.9, 23.1, 35.7, 17.7),
    "reset": (50.0, 48.9, 48.2, 46.5, 43.9, 40.8, -7.5, 31.4, 17.1, 49.5, 18.1),
}


class ShiftConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scale: str = "medium"
    seeds: tuple[int, ...] = SHIFT_SEEDS
    phases: tuple[Literal["left", "right"], ...] = ("left", "right") * 3
    phase_steps: int = Field(default=400, ge=60, description="steps per phase (≥ 60: the 50-step window must fit)")
    conditions: tuple[str, ...] = tuple(SHIFT_CONDITIONS)
    demand_mode: Literal["requests", "assignment", "none"] = "requests"
    radius: int = Field(default=6, ge=0, description="Proximity radius (shift.py uses r = 6 at Medium)")
    window: int = Field(default=50, ge=1)
    fraction: float = Field(default=0.9, gt=0)
    jobs: int = Field(default=2, ge=1)
    loss_percent: float = Field(default=0.0, ge=0.0, lt=100.0, description="bursty dispatch-message loss, %")

    @field_validator("conditions")
    @classmethod
    def _conditions(cls, v):
        for key in v:  # the study's own, or a policy from outside by the name --policy takes
            study_condition(key, SHIFT_CONDITIONS)
        return check_nonempty(v, "condition")

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v):
        return check_nonempty(v, "seed")

    @field_validator("phases")
    @classmethod
    def _phases(cls, v):
        if len(v) < 3:
            raise ValueError("at least three phases (recovery needs a same-side predecessor)")
        return v

    def spec(self, key: str, seed: int) -> EpisodeSpec:
        return EpisodeSpec(
            scale=self.scale, seed=seed, **study_condition(key, SHIFT_CONDITIONS).episode_fields(radius=self.radius),
            steps=len(self.phases) * self.phase_steps,
            demand_phases=self.phases, phase_steps=self.phase_steps, demand_mode=self.demand_mode,
            loss_percent=self.loss_percent,
            fiedler_every=self.phase_steps,  # λ₂ plays no part here; keep the eigen-solves out of the budget
        )


def episode_shift_metrics(cumulative: np.ndarray, cfg: ShiftConfig) -> dict:
    """P1…Pk, Δ(k)−3 and r3…rk (with censoring) of one episode from its cumulative delivery series."""
    per_step = np.diff(np.asarray(cumulative, dtype=float), prepend=0.0)
    bounds = [p * cfg.phase_steps for p in range(len(cfg.phases))]
    phases = measures.phase_deliveries(per_step, bounds)
    rec = measures.shift_recoveries(per_step, bounds, window=cfg.window, fraction=cfg.fraction)
    out = {f"P{p + 1}": int(v) for p, v in enumerate(phases)}
    last = len(phases)
    out[f"delta_{last}_3"] = int(phases[-1] - phases[2])
    for r in rec:
        out[f"r{r.phase + 1}"] = r.time
        out[f"r{r.phase + 1}_censored"] = r.censored
        out[f"r{r.phase + 1}_baseline"] = r.baseline
    return out


def table_columns(cfg: ShiftConfig) -> list[str]:
    k = len(cfg.phases)
    return [f"P{p}" for p in range(1, k + 1)] + [f"delta_{k}_3"] + [f"r{p}" for p in range(3, k + 1)]


def summarise_shift(cfg: ShiftConfig, episodes: list[dict]) -> list[dict]:
    """One row per condition: mean, std (population, as the reference) and, for r, the censored count."""
    rows = []
    for key in cfg.conditions:
        eps = [e for e in episodes if e["shift_condition"] == key]
        row = {"condition": key, "label": study_condition(key, SHIFT_CONDITIONS).label, "n": len(eps)}
        for col in table_columns(cfg):
            ms = measures.mean_std([e[col] for e in eps])
            row[col] = ms.mean
            row[f"{col}_std"] = ms.std
            if col.startswith("r"):
                row[f"{col}_censored"] = int(sum(bool(e[f"{col}_censored"]) for e in eps))
        rows.append(row)
    return rows


def markdown_shift(cfg: ShiftConfig, rows: list[dict], wall_s: float | None = None) -> str:
    cols = table_columns(cfg)
    head = "| condition | " + " | ".join(c.replace("delta_", "Δ").replace("_", "−") for c in cols) + " |"
    lines = [head, "|---|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            cell = f"{r[c]:.1f} ± {r[c + '_std']:.1f}"
            if c.startswith("r") and r[f"{c}_censored"]:
                cell += f" ({r[f'{c}_censored']}/{r['n']} cens.)"
            cells.append(cell)
        lines.append(f"| {r['label']} | " + " | ".join(cells) + " |")
    loss = f", bursty dispatch-message loss {cfg.loss_percent:g}%" if cfg.loss_percent else ""
    mode = {"requests": "new requests drawn from the active half", "assignment": "assignment filter (shift.py)",
            "none": "no shift (control: uniform requests, same phase boundaries and resets)"}[cfg.demand_mode]
    lines += [
        "",
        f"{cfg.scale}, {len(cfg.phases)} phases × {cfg.phase_steps} steps ({'–'.join(p[0].upper() for p in cfg.phases)}),"
        f" demand: {mode}{loss}, {len(cfg.seeds)} seeds, Proximity r = {cfg.radius}. mean ± population std over seeds."
        f" r = steps until the trailing {cfg.window}-step delivery rate reaches {cfg.fraction:.0%} of the same side's"
        " previous-phase rate; a censored r (never reached) counts as the phase length in the mean.",
    ]
    if wall_s is not None:
        lines.append(f"Wall time: {wall_s:.1f} s.")
    return "\n".join(lines) + "\n"


@dataclass
class ShiftResult:
    config: ShiftConfig
    episodes: list[dict]
    rows: list[dict]
    rates: dict[str, np.ndarray]  # condition -> mean rolling delivery rate over seeds
    wall_s: float
    run_dir: Path | None


def run_shift(cfg: ShiftConfig, out_root: Path | None = Path("runs"), run_id: str | None = None,
              show_progress: bool = True, argv: list[str] | None = None) -> ShiftResult:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    t0 = time.perf_counter()
    specs = {(key, seed): cfg.spec(key, seed) for key in cfg.conditions for seed in cfg.seeds}
    by_spec = {sp.model_dump_json(): k for k, sp in specs.items()}
    heavy = sorted(specs.values(), key=lambda sp: (sp.condition == "proximity", sp.condition == "tsg",
                                                   sp.preset == "paper"))  # slowest first
    done: dict[tuple[str, int], EpisodeResult] = {}
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        disable=not show_progress)
    with progress, episode_pool(cfg.jobs) as pool:
        task = progress.add_task("shift experiment", total=len(specs))
        for future in as_completed([pool.submit(run_episode, sp) for sp in heavy]):
            res = future.result()
            done[by_spec[res.spec.model_dump_json()]] = res
            progress.advance(task)
    wall = time.perf_counter() - t0
    episodes = []
    rates: dict[str, np.ndarray] = {}
    for key in cfg.conditions:
        per = []
        for seed in cfg.seeds:
            res = done[(key, seed)]
            m = episode_shift_metrics(res.ticks["deliveries_total"], cfg)
            episodes.append({"shift_condition": key, "seed": seed, "deliveries": res.summary["deliveries"],
                             "mean_links": res.summary["mean_links"], "wall_s": res.wall_s, **m})
            per.append(measures.rolling_rate(res.ticks["deliveries"], cfg.window))
        rates[key] = np.mean(per, axis=0)
    rows = summarise_shift(cfg, episodes)
    result = ShiftResult(cfg, episodes, rows, rates, wall, None)
    if out_root is not None:
        result.run_dir = _write_records(result, done, Path(out_root), run_id, argv)
    return result


def _write_records(result: ShiftResult, done: dict, root: Path, run_id: str | None, argv) -> Path:
    cfg = result.config
    run_id = run_id or f"{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}-shift-{cfg.demand_mode}{f'-loss{cfg.loss_percent:g}' if cfg.loss_percent else ''}"
    run_dir = root / run_id
    ep_root = run_dir / "episodes"
    ep_root.mkdir(parents=True, exist_ok=True)
    common = {"git_revision": _git_revision(), "versions": _versions(),
              "command_line": list(argv) if argv is not None else sys.argv}
    by_key = {(e["shift_condition"], e["seed"]): e for e in result.episodes}
    for (key, seed), ep in done.items():
        d = ep_root / f"{key}_s{seed}"
        d.mkdir(exist_ok=True)
        (d / "manifest.json").write_text(json.dumps({"spec": ep.spec.model_dump(), **common}, indent=2))
        (d / "summary.json").write_text(json.dumps(_jsonable({**ep.summary, **by_key[(key, seed)]}), indent=2))
        names = ["deliveries", "deliveries_total", "links"]
        with open(d / "ticks.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", *names])
            for t in range(ep.spec.steps):
                w.writerow([t, *(_num(ep.ticks[k][t]) for k in names)])
    manifest = {"run_id": run_id, "kind": "shift", "config": cfg.model_dump(), "wall_s": result.wall_s, **common}
    (run_dir / "manifest.json").write_text(json.dumps(_jsonable(manifest), indent=2))
    cols = table_columns(cfg)
    with open(run_dir / "shift.csv", "w", newline="") as f:
        fields = ["condition", "label", "n"] + [x for c in cols for x in (
            [c, f"{c}_std"] + ([f"{c}_censored"] if c.startswith("r") else []))]
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in result.rows:
            w.writerow({k: r[k] for k in fields})
    with open(run_dir / "episodes.csv", "w", newline="") as f:
        fields = list(result.episodes[0])
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(result.episodes)
    (run_dir / "shift.md").write_text(markdown_shift(cfg, result.rows, result.wall_s))
    plot_shift(result, run_dir / "plots")
    return run_dir


_COLOURS = {"morph_reference": "#2a7ab9", "reset_reference": "#8fb8de", "morph_paper": "#8e44ad",
            "reset_paper": "#c39bd3", "proximity": "#3a9a4a", "tsg": "#e08a2c"}


def plot_shift(result: ShiftResult, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = result.config
    out_dir.mkdir(parents=True, exist_ok=True)
    L = cfg.phase_steps
    fig, ax = plt.subplots(figsize=(12.5, 4), layout="constrained")
    for p, side in enumerate(cfg.phases):
        ax.axvspan(p * L, (p + 1) * L, color="#f3e9d2" if side == "left" else "#dfeaf3", alpha=0.6, lw=0)
        ax.text(p * L + L / 2, 1.0, f"P{p + 1} {side[0].upper()}", ha="center", va="bottom",
                transform=ax.get_xaxis_transform(), fontsize=8)
        if p:
            ax.axvline(p * L, color="k", lw=0.6, ls="--")
    for key in cfg.conditions:
        r = result.rates[key]
        ax.plot(np.arange(r.size), r * cfg.window, lw=1.2, color=_COLOURS.get(key), label=study_condition(key, SHIFT_CONDITIONS).label)
    ax.set_xlabel("step")
    ax.set_ylabel(f"deliveries per {cfg.window} steps (trailing window)")
    ax.set_xlim(0, len(cfg.phases) * L)
    ax.grid(alpha=0.3)
    from matplotlib.patches import Patch

    handles, _ = ax.get_legend_handles_labels()
    handles += [Patch(color="#f3e9d2", label="demand on the left half"),
                Patch(color="#dfeaf3", label="demand on the right half")]
    fig.legend(handles=handles, loc="outside right upper", fontsize=7)  # outside the axes: never over a curve
    loss = f", {cfg.loss_percent:g}% bursty dispatch loss" if cfg.loss_percent else ""
    n = len(cfg.seeds)
    ax.set_title(f"Demand shift ({cfg.demand_mode}{loss}), {cfg.scale}, mean over {n} seed{'s' if n != 1 else ''}",
                 pad=14)
    p1 = out_dir / "delivery_rate.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)

    rcols = [c for c in table_columns(cfg) if c.startswith("r")]
    pcols = [c for c in table_columns(cfg) if c.startswith("P")]
    fig, axes = plt.subplots(1, 2, figsize=(13.5, 4), layout="constrained")
    k = len(cfg.conditions)
    width = 0.8 / k
    for ax, cols, ylabel in ((axes[0], pcols, "deliveries per phase"), (axes[1], rcols, "recovery time (steps)")):
        x = np.arange(len(cols))
        for m, row in enumerate(result.rows):
            ax.bar(x - 0.4 + width * (m + 0.5), [row[c] for c in cols], width,
                   yerr=[row[c + "_std"] for c in cols], capsize=2, color=_COLOURS.get(row["condition"]),
                   label=row["label"])
            if ylabel.startswith("recovery"):
                for j, c in enumerate(cols):
                    if row[f"{c}_censored"]:
                        ax.text(x[j] - 0.4 + width * (m + 0.5), 2, str(row[f"{c}_censored"]), ha="center",
                                fontsize=6, color="white")
        ax.set_xticks(x, cols)
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    axes[1].axhline(L, color="k", lw=0.6, ls=":", label=f"phase length ({L} steps): never recovered")
    axes[1].set_title(f"recovery to {cfg.fraction:.0%} of same-side baseline (white digits: censored seeds)",
                      fontsize=9)
    axes[0].set_title("deliveries per phase", fontsize=9)
    handles, _ = axes[0].get_legend_handles_labels()
    cap = [h for h, label in zip(*axes[1].get_legend_handles_labels()) if label.startswith("phase length")]
    fig.legend(handles=handles + cap, loc="outside right upper", fontsize=7, title="mean ± std over seeds",
               title_fontsize=7)
    p2 = out_dir / "recovery_bars.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [p1, p2]
