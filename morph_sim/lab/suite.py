"""Experiment suites: conditions × scales × seeds in parallel processes, with run records and tables.

``scale`` is the reference's scale study (nine conditions, four scales, five seeds, T = 800,
Proximity radius calibrated first; docs/morph.md); ``ablation`` runs MORPH and its ablations of one preset.
Every episode gets a record under ``runs/<run-id>/episodes/<key>/`` (``manifest.json``, ``ticks.csv``,
``summary.json``); the suite writes ``manifest.json``, ``summary.csv``, ``summary.md`` and plots.
Any table can be recomputed from the episode summaries alone (:func:`summarise`).
"""

from __future__ import annotations

import csv
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from morph_sim.lab.executors import episode_pool
from morph_sim.lab.runner import (
    REFERENCE_SEEDS,
    SCALES,
    EpisodeResult,
    EpisodeSpec,
    check_choices,
    check_nonempty,
    run_episode,
)
from services.metrics import measures
from services.policies.conditions import CONDITIONS, SCALE_STUDY, study_condition
from services.policies.coordinators import PROXIMITY_RADII


class SuiteConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: Literal["scale", "ablation"] = "scale"
    preset: str = "reference"
    scales: tuple[str, ...] = SCALES
    seeds: tuple[int, ...] = REFERENCE_SEEDS
    steps: int = Field(default=800, ge=1)
    conditions: tuple[str, ...] = SCALE_STUDY
    dispatch: Literal["concurrent", "sequential"] = "concurrent"
    shared_stream: bool = False
    radii: dict[str, int] | None = None
    calibration_seed: int | None = None  # default: the first seed (42 in the reference)
    jobs: int = Field(default=2, ge=1)
    fiedler_every: int = Field(default=10, ge=1, description="λ₂ every this many ticks (eigen-solves are the lab's main cost)")

    @field_validator("scales")
    @classmethod
    def _scales(cls, v):
        from services.world.layout import named_sizes

        check_choices(v, named_sizes(), "scale")
        return check_nonempty(v, "scale")

    @field_validator("conditions")
    @classmethod
    def _conditions(cls, v):
        for c in v:  # the study's table, or a policy from outside by the name --policy takes
            study_condition(c, CONDITIONS)
        return check_nonempty(v, "condition")

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v):
        return check_nonempty(v, "seed")

    def spec(self, scale: str, condition: str, seed: int, radius: int | None = None, steps: int | None = None):
        outside = {} if condition in CONDITIONS else {"policy_name": condition}
        return EpisodeSpec(
            scale=scale, condition=condition, seed=seed, steps=steps or self.steps, preset=self.preset,
            radius=radius, dispatch=self.dispatch, shared_stream=self.shared_stream,
            fiedler_every=self.fiedler_every, **outside,
        )


@dataclass
class SuiteResult:
    config: SuiteConfig
    episodes: list[dict]  # episode summaries
    radii: dict[str, int]
    calibration: dict[str, dict]
    wall_s: float
    run_dir: Path | None
    series: dict[tuple[str, str], dict[str, np.ndarray]]  # (scale, condition) -> mean tick series


def _work(spec: EpisodeSpec) -> EpisodeResult:
    return run_episode(spec)


class _Scheduler:
    """This machine's processes (:func:`episode_pool`) fed one episode at a time; ``results()`` waits for at least
    one finished episode (the interface :class:`_DaskScheduler` shares)."""

    def __init__(self, jobs: int) -> None:
        self.jobs = jobs
        self.pending = 0
        self._running: set[Future] = set()

    def __enter__(self) -> _Scheduler:
        self._context = episode_pool(self.jobs)
        self._pool = self._context.__enter__()
        return self

    def __exit__(self, *exc) -> bool | None:
        return self._context.__exit__(*exc)

    def submit(self, spec: EpisodeSpec) -> None:
        self.pending += 1
        self._running.add(self._pool.submit(_work, spec))

    def results(self) -> list[EpisodeResult]:
        finished, self._running = wait(self._running, return_when=FIRST_COMPLETED)
        self.pending -= len(finished)
        return [future.result() for future in finished]


class _DaskScheduler:
    """The same interface on a Dask cluster (``scheduler``: tcp://HOST:8786, a Client or a LocalCluster): each episode
    is one task; episodes are deterministic in their spec, so the study equals the local one episode for episode."""

    def __init__(self, scheduler) -> None:
        from morph_sim.lab.executors import DaskExecutor

        self._executor = DaskExecutor(scheduler)
        self.pending = 0
        self._done = None
        self._futures: list = []

    def __enter__(self) -> _DaskScheduler:
        from distributed import as_completed

        self._done = as_completed([], loop=self._executor.client.loop)
        return self

    def __exit__(self, *exc) -> None:
        self._executor.client.cancel([f for f in self._futures if not f.done()])
        self._executor.close()

    def submit(self, spec: EpisodeSpec) -> None:
        self.pending += 1
        future = self._executor.client.submit(_work, spec, pure=False)
        self._futures.append(future)
        self._done.add(future)

    def results(self) -> list[EpisodeResult]:
        out = [next(self._done).result()]
        self.pending -= 1
        return out


def _scheduler(jobs: int, executor: str, scheduler) -> _Scheduler | _DaskScheduler:
    if executor == "local":
        return _Scheduler(jobs)
    if executor == "dask":
        return _DaskScheduler(scheduler)
    raise ValueError(f"executor: unknown {executor!r} (local, dask)")


def _cost(spec: EpisodeSpec) -> float:
    size = {"tiny": 1.0, "small": 1.4, "medium": 2.0, "large": 2.8}.get(spec.scale, 2.0)
    plastic = 1.6 if study_condition(spec.condition, CONDITIONS).plastic else 1.0
    return size * plastic * spec.steps


def run_suite(cfg: SuiteConfig, out_root: Path | None = Path("runs"), run_id: str | None = None,
              show_progress: bool = True, argv: list[str] | None = None, executor: str = "local",
              scheduler=None) -> SuiteResult:
    """Run the study on ``cfg.jobs`` local processes, or on a Dask cluster (``executor="dask"``, ``scheduler``)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    t0 = time.perf_counter()
    radii = dict(cfg.radii or {})
    calib: dict[str, dict] = {}
    need_calib = "proximity" in cfg.conditions and any(s not in radii for s in cfg.scales)
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        disable=not show_progress, transient=False)
    seed0 = cfg.calibration_seed if cfg.calibration_seed is not None else cfg.seeds[0]
    from services.policies.presets import load_preset

    paper_rules = load_preset(cfg.preset).rules == "paper"
    todo = [sc for sc in cfg.scales if sc not in radii] if need_calib else []
    cal_morph = {sc: cfg.spec(sc, "morph", seed0) for sc in todo}
    cal_prox = {(sc, r): cfg.spec(sc, "proximity", seed0, radius=r) for sc in todo for r in PROXIMITY_RADII}

    def main_specs(with_radius: bool) -> list[EpisodeSpec]:
        return [
            cfg.spec(sc, c, seed, radius=radii.get(sc) if c == "proximity" else None)
            for sc in cfg.scales for c in cfg.conditions for seed in cfg.seeds
            if (c == "proximity" and sc in radii) == with_radius or (c != "proximity" and not with_radius)
        ]

    done: dict[str, EpisodeResult] = {}
    # One pool for everything: calibration first (it gates the Proximity episodes), then every episode that
    # does not need a radius, largest first; Proximity is queued as soon as its scale is calibrated. An
    # episode identical to a calibration episode (same spec) is not run twice.
    first = list(cal_morph.values()) + list(cal_prox.values())
    first += sorted((sp for sp in main_specs(False) if sp.condition != "proximity"), key=_cost, reverse=True)
    first += [sp for sp in main_specs(True) if sp.condition == "proximity"]
    with progress, _scheduler(cfg.jobs, executor, scheduler) as pool:
        task = progress.add_task(f"{cfg.kind} study", total=None)
        submitted = set()

        def submit(specs):
            for sp in specs:
                k = sp.model_dump_json()
                if k not in submitted:
                    submitted.add(k)
                    pool.submit(sp)
            progress.update(task, total=len(submitted))

        submit(first)
        while pool.pending:
            for res in pool.results():
                done[res.spec.model_dump_json()] = res
                progress.advance(task)
            for sc in [sc for sc in todo if sc not in radii]:
                keys = [cal_morph[sc]] + [cal_prox[(sc, r)] for r in PROXIMITY_RADII]
                if all(k.model_dump_json() in done for k in keys):
                    summary = done[cal_morph[sc].model_dump_json()].summary
                    # the reference calibrates to MORPH's whole-episode mean link count; the paper "to match MORPH's
                    # converged mean link count", which the paper rules follow (second half of the episode)
                    target_kind = "converged" if paper_rules else "episode"
                    target = summary["mean_links_converged" if paper_rules else "mean_links"]
                    by_r = {r: done[cal_prox[(sc, r)].model_dump_json()].summary["mean_links"]
                            for r in PROXIMITY_RADII}
                    best_r, best = PROXIMITY_RADII[0], float("inf")
                    for r in PROXIMITY_RADII:  # the reference's rule: first strictly closer radius wins
                        if abs(by_r[r] - target) < best:
                            best_r, best = r, abs(by_r[r] - target)
                    radii[sc] = best_r
                    calib[sc] = {"target_links": target, "target": target_kind, "links_by_radius": by_r,
                                 "radius": best_r, "episode_links": summary["mean_links"],
                                 "converged_links": summary["mean_links_converged"]}
                    submit([sp for sp in main_specs(True) if sp.scale == sc and sp.condition == "proximity"])
    specs = main_specs(False) + main_specs(True)
    order = {(c, sc, seed): k for k, (sc, c, seed) in enumerate(
        (sc, c, seed) for sc in cfg.scales for c in cfg.conditions for seed in cfg.seeds)}
    results = sorted((done[sp.model_dump_json()] for sp in specs),
                     key=lambda r: order[(r.spec.condition, r.spec.scale, r.spec.seed)])
    wall = time.perf_counter() - t0

    series: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for s in cfg.scales:
        for c in cfg.conditions:
            group = [r for r in results if r.spec.scale == s and r.spec.condition == c]
            series[(s, c)] = {
                k: np.mean([r.ticks[k] for r in group], axis=0) for k in ("deliveries_total", "links", "links_directed")
            }
    result = SuiteResult(cfg, [r.summary for r in results], radii, calib, wall, None, series)
    if out_root is not None:
        result.run_dir = write_records(result, results, Path(out_root), run_id, argv)
    return result


# --------------------------------------------------------------------------------------------------
# tables


def summarise(cfg: SuiteConfig, episodes: list[dict]) -> list[dict]:
    """Per (condition, scale): mean ± std deliveries, %Full, links and %max, Welch p vs MORPH."""
    rows = []
    for s in cfg.scales:
        by = {c: [e for e in episodes if e["scale"] == s and e["condition"] == c] for c in cfg.conditions}
        full = [e["deliveries"] for e in by.get("full", [])]
        morph = [e["deliveries"] for e in by.get("morph", [])]
        for c in cfg.conditions:
            eps = sorted(by[c], key=lambda e: cfg.seeds.index(e["seed"]) if e["seed"] in cfg.seeds else 0)
            d = [e["deliveries"] for e in eps]
            ms = measures.mean_std(d)
            links = float(np.mean([e["mean_links"] for e in eps]))
            max_links = eps[0]["max_links"]
            rows.append({
                "condition": c,
                "label": study_condition(c, CONDITIONS).label,
                "scale": s,
                "n_agents": eps[0]["n_agents"],
                "mean": ms.mean,
                "std": ms.std,
                "values": d,
                "pct_full": 100.0 * ms.mean / np.mean(full) if full and np.mean(full) > 0 else float("nan"),
                "links": links,
                "links_pct_max": 100.0 * links / max_links if max_links else float("nan"),
                "p_vs_morph": _welch(morph, d) if morph and c != "morph" else float("nan"),
                "mean_p_respond": measures.nan_mean(e["mean_p_respond"] for e in eps),
                "divergent_ticks": float(np.mean([e["divergent_dispatch_ticks"] for e in eps])),
                "median_lifetime": measures.nan_mean(e.get("median_lifetime", np.nan) for e in eps),
            })
    return rows


def _welch(a, b) -> float:
    import warnings

    with warnings.catch_warnings():  # near-identical samples: scipy warns, the p-value is still what it is
        warnings.simplefilter("ignore", RuntimeWarning)
        return measures.welch_p(a, b)


def _fmt_p(p: float) -> str:
    if p != p:
        return "–"
    return f"**{p:.3f}**" if p < 0.05 else f"{p:.3f}"


def markdown_table(cfg: SuiteConfig, rows: list[dict], wall_s: float | None = None, radii=None) -> str:
    scales = list(cfg.scales)
    head = "| condition | " + " | ".join(
        f"{s} (N={next(r['n_agents'] for r in rows if r['scale'] == s)})" for s in scales
    ) + " |"
    lines = [head, "|---|" + "---|" * len(scales)]
    for c in cfg.conditions:
        cells = []
        for s in scales:
            r = next(r for r in rows if r["scale"] == s and r["condition"] == c)
            cell = f"{r['mean']:.1f} ± {r['std']:.1f} [{','.join(str(v) for v in r['values'])}]"
            if r["pct_full"] == r["pct_full"] and c != "full":
                cell += f"; {r['pct_full']:.0f}% Full"
            cell += f"; {r['links']:.1f} links ({r['links_pct_max']:.0f}%)"
            if c != "morph" and r["p_vs_morph"] == r["p_vs_morph"]:
                cell += f"; p={_fmt_p(r['p_vs_morph'])}"
            cells.append(cell)
        lines.append(f"| {study_condition(c, CONDITIONS).label} | " + " | ".join(cells) + " |")
    notes = [
        "",
        f"preset `{cfg.preset}`, dispatch `{cfg.dispatch}`, gate stream "
        f"`{'shared (reference)' if cfg.shared_stream else 'per-agent'}`, {len(cfg.seeds)} seeds "
        f"{list(cfg.seeds)}, T = {cfg.steps}. Cells: mean ± population std [per seed]; %Full; mean active links "
        "(% of N(N−1)/2); Welch p vs MORPH.",
    ]
    if radii:
        notes.append("Proximity radius: " + ", ".join(f"{s} r={radii[s]}" for s in scales if s in radii) + ".")
    if wall_s is not None:
        notes.append(f"Wall time: {wall_s:.1f} s.")
    return "\n".join(lines + notes) + "\n"


# --------------------------------------------------------------------------------------------------
# run records


def _git_revision() -> str:
    try:
        here = Path(__file__).resolve().parent
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        rev = out.stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True,
                               timeout=5).stdout.strip()
        return rev + ("-dirty" if dirty else "") if rev else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _versions() -> dict:
    import scipy

    from morph_sim import __version__

    return {"morph_sim": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__}


def write_records(result: SuiteResult, episodes: list[EpisodeResult], root: Path, run_id: str | None,
                  argv: list[str] | None) -> Path:
    cfg = result.config
    run_id = run_id or f"{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}-{cfg.kind}-{cfg.preset}"
    run_dir = root / run_id
    ep_root = run_dir / "episodes"
    ep_root.mkdir(parents=True, exist_ok=True)
    common = {
        "git_revision": _git_revision(),
        "versions": _versions(),
        "command_line": list(argv) if argv is not None else sys.argv,
    }
    for ep in episodes:
        d = ep_root / ep.spec.key
        d.mkdir(exist_ok=True)
        (d / "manifest.json").write_text(json.dumps({"spec": ep.spec.model_dump(), **common}, indent=2))
        (d / "summary.json").write_text(json.dumps(_jsonable(ep.summary), indent=2))
        names = list(ep.ticks)
        with open(d / "ticks.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", *names])
            for t in range(ep.spec.steps):
                w.writerow([t, *(_num(ep.ticks[k][t]) for k in names)])
    rows = summarise(cfg, result.episodes)
    manifest = {
        "run_id": run_id,
        "kind": cfg.kind,
        "config": cfg.model_dump(),
        "seeds": list(cfg.seeds),
        "proximity_radii": result.radii,
        "calibration": result.calibration,
        "wall_s": result.wall_s,
        "cpu_count": os.cpu_count(),
        **common,
    }
    (run_dir / "manifest.json").write_text(json.dumps(_jsonable(manifest), indent=2))
    with open(run_dir / "summary.csv", "w", newline="") as f:
        fields = ["condition", "label", "scale", "n_agents", "mean", "std", "values", "pct_full", "links",
                  "links_pct_max", "p_vs_morph", "mean_p_respond", "divergent_ticks", "median_lifetime"]
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (" ".join(map(str, r[k])) if k == "values" else r[k]) for k in fields})
    (run_dir / "summary.md").write_text(markdown_table(cfg, rows, result.wall_s, result.radii))
    try:
        from morph_sim.lab.plots import plot_suite

        plot_suite(result, rows, run_dir / "plots")
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        pass
    return run_dir


def _num(v) -> str:
    f = float(v)
    return str(int(f)) if f.is_integer() else f"{f:.6g}"


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return None if f != f else f
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
