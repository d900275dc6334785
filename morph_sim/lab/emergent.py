"""The paper's emergent-structure analysis (paper section "Emergent allocation structure"; docs/morph.md).

Long Medium MORPH episodes (T = 1500, several seeds, each preset): W snapshots at fixed ticks, Spearman of the final
W against the episode's mean Manhattan distance (directed AGV→picker pairs with a permutation p; the reference's
153 unordered pairs), link events and lifetimes with the stable core (lifetime ≥ ⌊T/2⌋) vs the periphery, η over
time and λ₂ over time under both definitions (the reference's normalised-Laplacian value with isolated vertices,
and the textbook algebraic connectivity). Writes figures, ``emergent.json`` and ``emergent.md``.
"""

from __future__ import annotations

import json
import sys
import time
from concurrent.futures import as_completed
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from morph_sim.lab.executors import episode_pool
from morph_sim.lab.runner import EpisodeSpec, check_nonempty, run_episode
from morph_sim.lab.suite import _git_revision, _jsonable, _versions
from services.metrics import catalogue, measures

SNAPSHOT_TICKS = (0, 100, 200, 400, 600, 800, 1500)
#: ticks at which λ₂ is quoted (the reference's list, plus the end)
LAMBDA_TICKS = (1, 50, 100, 200, 400, 800, 1500)


class EmergentConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scale: str = "medium"
    seeds: tuple[int, ...] = (42, 7, 123, 999, 2024)
    steps: int = Field(default=1500, ge=10)
    presets: tuple[str, ...] = ("reference", "paper")
    snapshot_ticks: tuple[int, ...] = SNAPSHOT_TICKS
    n_permutations: int = Field(default=10_000, ge=0)
    loss_percent: float = Field(default=0.0, ge=0.0, lt=100.0)
    jobs: int = Field(default=2, ge=1)

    @field_validator("seeds", "presets")
    @classmethod
    def _nonempty(cls, v):
        return check_nonempty(v, "value")

    @field_validator("presets")
    @classmethod
    def _known(cls, v):
        from services.policies.presets import load_preset

        for p in v:
            load_preset(p)
        return v

    def spec(self, preset: str, seed: int) -> EpisodeSpec:
        return EpisodeSpec(scale=self.scale, condition="morph", seed=seed, steps=self.steps, preset=preset,
                           fiedler_every=1, loss_percent=self.loss_percent)

    def ticks(self) -> tuple[int, ...]:
        return tuple(t for t in self.snapshot_ticks if t <= self.steps)


def analyse_episode(args: tuple[EmergentConfig, str, int]) -> dict:
    """One episode and everything the analysis needs from it (plain arrays, picklable)."""
    cfg, preset, seed = args
    spec = cfg.spec(preset, seed)
    res = run_episode(spec, snapshot_ticks=cfg.ticks())
    W, D = res.final_weights, res.mean_distance
    n = W.shape[0]
    n_agv = _n_agvs(spec)
    is_agv = np.arange(n) < n_agv
    perms = cfg.n_permutations
    sp_ap = measures.spearman_agv_picker(W, D, is_agv, n_permutations=perms, rng=seed)
    sp_both = measures.spearman_agv_picker(W, D, is_agv, n_permutations=perms, rng=seed, direction="both")
    sp_ref = measures.spearman_reference_pairs(W, D, n_permutations=perms, rng=seed)
    life, cens = res.tracker.lifetimes()
    T = spec.steps
    core, periphery = res.tracker.core_periphery(T // 2)
    blocks = measures.mean_w_by_block(W, is_agv)
    lam_ref, lam_alg = res.ticks["fiedler_ref"], res.ticks["lambda2"]
    at = [min(t, T) - 1 for t in LAMBDA_TICKS if t <= T]
    return {
        "preset": preset, "seed": seed, "steps": T, "n_agvs": n_agv, "n_agents": n,
        "deliveries": res.summary["deliveries"],
        "spearman_agv_to_picker": _sp(sp_ap), "spearman_directed_both": _sp(sp_both),
        "spearman_reference_153": _sp(sp_ref),
        "link_events": int(life.size), "censored_events": int(cens.sum()),
        "median_lifetime": float(np.median(life)) if life.size else float("nan"),
        "core_events": core, "periphery_events": periphery,
        "core_share": core / life.size if life.size else float("nan"),
        "events_ge_400": int(np.count_nonzero(life >= 400)),  # the paper's "≥ 400 consecutive steps"
        "lifetimes": life.tolist(),
        **catalogue.w_block_values(blocks),
        "w_asymmetry": float(np.abs(W - W.T).max()),
        "eta_mean": float(res.ticks["eta"].mean()), "eta_positive_share": float((res.ticks["eta"] > 0).mean()),
        "links_mean": float(res.ticks["links"].mean()),
        "links_mean_after_200": float(res.ticks["links"][200:].mean()) if T > 200 else float("nan"),
        "lambda_ref_at": {str(t): float(lam_ref[i]) for t, i in zip(LAMBDA_TICKS, at)},
        "lambda_alg_at": {str(t): float(lam_alg[i]) for t, i in zip(LAMBDA_TICKS, at)},
        "lambda_ref_max": float(lam_ref.max()),
        # "declines monotonically": the rank correlation of λ₂ with time over the second half of the episode
        "lambda_ref_trend_2nd_half": _trend(lam_ref[T // 2:]),
        "series": {k: res.ticks[k].tolist() for k in ("deliveries_total", "links", "eta", "fiedler_ref", "lambda2")},
        "snapshots": {str(t): w.tolist() for t, w in res.snapshots.items()},
        "wall_s": res.wall_s,
    }


def _trend(y: np.ndarray) -> float:
    from scipy import stats

    return float(stats.spearmanr(np.arange(y.size), y).statistic) if np.ptp(y) > 0 else float("nan")


def _n_agvs(spec: EpisodeSpec) -> int:
    from services.world.warehouse import WarehouseConfig

    return WarehouseConfig.named(spec.scale).agvs


def _sp(r: measures.SpearmanResult) -> dict:
    return {"rho": r.rho, "p": r.p_value, "p_permutation": r.p_permutation, "pairs": r.n_pairs}


@dataclass
class EmergentResult:
    config: EmergentConfig
    episodes: list[dict]
    summary: dict
    wall_s: float
    run_dir: Path | None


_SUMMARY_KEYS = ("deliveries", "link_events", "median_lifetime", "core_events", "core_share", "events_ge_400", "eta_mean",
                 "eta_positive_share", "links_mean", "links_mean_after_200", *catalogue.W_BLOCKS, "lambda_ref_max",
                 "lambda_ref_trend_2nd_half")


def summarise_emergent(cfg: EmergentConfig, episodes: list[dict]) -> dict:
    out = {}
    for preset in cfg.presets:
        eps = [e for e in episodes if e["preset"] == preset]
        row: dict = {}
        for k in _SUMMARY_KEYS:
            v = np.array([e[k] for e in eps], dtype=float)
            row[k] = {"mean": measures.nan_mean(v), "std": measures.nan_std(v), "values": v.tolist()}
        for k in ("spearman_agv_to_picker", "spearman_directed_both", "spearman_reference_153"):
            row[k] = {
                "rho": [e[k]["rho"] for e in eps], "p_permutation": [e[k]["p_permutation"] for e in eps],
                "p": [e[k]["p"] for e in eps], "pairs": eps[0][k]["pairs"],
                "rho_mean": measures.nan_mean(e[k]["rho"] for e in eps),
                "significant_5pct": int(sum(1 for e in eps if (e[k]["p_permutation"] or 1.0) < 0.05)),
            }
        for k in ("lambda_ref_at", "lambda_alg_at"):
            row[k] = {t: float(np.mean([e[k][t] for e in eps])) for t in eps[0][k]}
        out[preset] = row
    return out


def markdown_emergent(res: EmergentResult) -> str:
    cfg = res.config
    lines = [f"Emergent analysis: {cfg.scale}, T = {cfg.steps}, seeds {list(cfg.seeds)}"
             + (f", bursty dispatch-message loss {cfg.loss_percent:g}%" if cfg.loss_percent else "")
             + f"; wall {res.wall_s:.1f} s.", "",
             "| metric | " + " | ".join(cfg.presets) + " |", "|---|" + "---|" * len(cfg.presets)]

    def ms(preset, k, d=2):
        r = res.summary[preset][k]
        return f"{r['mean']:.{d}f} ± {r['std']:.{d}f}"

    def sp(preset, k):
        r = res.summary[preset][k]
        rhos = ", ".join(f"{x:+.2f}" for x in r["rho"])
        return (f"ρ̄ = {r['rho_mean']:+.3f} [{rhos}]; {r['significant_5pct']}/{len(r['rho'])} seeds perm. p < 0.05"
                f" ({r['pairs']} pairs)")

    rows = [("deliveries", lambda p: ms(p, "deliveries", 1)),
            ("Spearman final W vs mean distance, AGV→picker", lambda p: sp(p, "spearman_agv_to_picker")),
            ("Spearman, both directions AGV↔picker", lambda p: sp(p, "spearman_directed_both")),
            ("Spearman, reference's 153 unordered pairs", lambda p: sp(p, "spearman_reference_153")),
            ("link events", lambda p: ms(p, "link_events", 0)),
            ("median lifetime (steps)", lambda p: ms(p, "median_lifetime", 1)),
            (f"stable-core events (≥ {cfg.steps // 2} steps)", lambda p: ms(p, "core_events", 1)),
            ("core share of events", lambda p: ms(p, "core_share", 3)),
            ("events ≥ 400 steps (the paper's core at T = 800)", lambda p: ms(p, "events_ge_400", 1)),
            ("mean W AGV–AGV / AGV–picker / picker–picker", lambda p: " / ".join(
                ms(p, k, 3) for k in catalogue.W_BLOCKS)),
            ("mean links (all / after t = 200)", lambda p: ms(p, "links_mean", 1) + " / " + ms(
                p, "links_mean_after_200", 1)),
            ("mean η; share of ticks with η > 0", lambda p: ms(p, "eta_mean", 3) + "; " + ms(
                p, "eta_positive_share", 2)),
            ("λ₂ (reference def.) at t = " + "/".join(str(t) for t in LAMBDA_TICKS if t <= cfg.steps),
             lambda p: " / ".join(f"{v:.3f}" for v in res.summary[p]["lambda_ref_at"].values())),
            ("λ₂ (algebraic connectivity) at the same t",
             lambda p: " / ".join(f"{v:.3f}" for v in res.summary[p]["lambda_alg_at"].values())),
            ("λ₂ (ref.) max; Spearman(λ₂, t) over 2nd half", lambda p: ms(p, "lambda_ref_max", 3) + "; " + ms(
                p, "lambda_ref_trend_2nd_half", 2))]
    for name, f in rows:
        lines.append(f"| {name} | " + " | ".join(f(p) for p in cfg.presets) + " |")
    lines.append("")
    lines.append("mean ± population std over seeds; λ₂ values are means over seeds; permutation p from "
                 f"{cfg.n_permutations} permutations (two-sided).")
    return "\n".join(lines) + "\n"


def run_emergent(cfg: EmergentConfig, out_root: Path | None = Path("runs"), run_id: str | None = None,
                 show_progress: bool = True, argv: list[str] | None = None) -> EmergentResult:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    t0 = time.perf_counter()
    work = [(cfg, preset, seed) for preset in cfg.presets for seed in cfg.seeds]
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        disable=not show_progress)
    episodes = []
    with progress:
        task = progress.add_task("emergent analysis", total=len(work))
        with episode_pool(cfg.jobs) as pool:
            for future in as_completed([pool.submit(analyse_episode, w) for w in work]):
                episodes.append(future.result())
                progress.advance(task)
    order = {(p, s): k for k, (_, p, s) in enumerate(work)}
    episodes.sort(key=lambda e: order[(e["preset"], e["seed"])])
    res = EmergentResult(cfg, episodes, summarise_emergent(cfg, episodes), time.perf_counter() - t0, None)
    if out_root is not None:
        run_id = run_id or f"{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}-emergent"
        d = Path(out_root) / run_id
        d.mkdir(parents=True, exist_ok=True)
        common = {"git_revision": _git_revision(), "versions": _versions(),
                  "command_line": list(argv) if argv is not None else sys.argv}
        (d / "manifest.json").write_text(json.dumps(_jsonable({"run_id": run_id, "kind": "emergent",
                                                                "config": cfg.model_dump(), "wall_s": res.wall_s,
                                                                **common}), indent=2))
        (d / "emergent.json").write_text(json.dumps(_jsonable({"summary": res.summary, "episodes": [
            {k: v for k, v in e.items() if k not in ("series", "snapshots", "lifetimes")} for e in episodes]}),
            indent=2))
        ep_dir = d / "episodes"
        ep_dir.mkdir(exist_ok=True)
        for e in episodes:
            (ep_dir / f"{e['preset']}_s{e['seed']}.json").write_text(json.dumps(_jsonable(e)))
        (d / "emergent.md").write_text(markdown_emergent(res))
        plot_emergent(res, d / "plots")
        res.run_dir = d
    return res


def plot_emergent(res: EmergentResult, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = res.config
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for preset in cfg.presets:
        ep = next(e for e in res.episodes if e["preset"] == preset)
        ticks = sorted(int(t) for t in ep["snapshots"])
        fig, axes = plt.subplots(1, len(ticks), figsize=(2.6 * len(ticks), 3.0), squeeze=False)
        vmax = max(1e-9, max(np.max(ep["snapshots"][str(t)]) for t in ticks))
        na, n = ep["n_agvs"], ep["n_agents"]
        for ax, t in zip(axes[0], ticks):
            im = ax.imshow(np.array(ep["snapshots"][str(t)]), vmin=0, vmax=vmax, cmap="viridis")
            for v in (na - 0.5,):
                ax.axhline(v, color="w", lw=0.8)
                ax.axvline(v, color="w", lw=0.8)
            ax.set_title(f"t = {t}", fontsize=9)
            ax.set_xticks([na / 2 - 0.5, na + (n - na) / 2 - 0.5], ["AGV", "picker"], fontsize=7)
            if t == ticks[0]:
                ax.set_yticks([na / 2 - 0.5, na + (n - na) / 2 - 0.5], ["AGV", "picker"], fontsize=7)
            else:
                ax.set_yticks([])
        fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="W")
        fig.suptitle(f"W evolution, preset {preset}, {cfg.scale} seed {ep['seed']} (rows: from, cols: to)",
                     fontsize=10)
        p = out_dir / f"w_snapshots_{preset}.png"
        fig.savefig(p, dpi=100, bbox_inches="tight")
        plt.close(fig)
        paths.append(p)

    fig, axes = plt.subplots(4, len(cfg.presets), figsize=(6.5 * len(cfg.presets), 10), squeeze=False, sharex=True)
    for j, preset in enumerate(cfg.presets):
        eps = [e for e in res.episodes if e["preset"] == preset]
        for i, (k, label) in enumerate((("links", "active links"), ("eta", "η (neuromodulation)"),
                                        ("fiedler_ref", "λ₂ reference (normalised L)"),
                                        ("lambda2", "λ₂ algebraic connectivity"))):
            ax = axes[i][j]
            ys = np.array([e["series"][k] for e in eps])
            for y in ys:
                ax.plot(y, lw=0.4, alpha=0.4, color="#888")
            if k == "eta":
                kern = np.ones(25) / 25
                ax.plot(np.convolve(ys.mean(axis=0), kern, mode="same"), lw=1.4, color="#2a7ab9")
                ax.axhline(0, color="k", lw=0.6)
                label = "η (neuromodulation);\nblue: mean, 25-step smoothed"
            else:
                ax.plot(ys.mean(axis=0), lw=1.4, color="#2a7ab9")
            ax.set_ylabel(label, fontsize=8)
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(f"preset {preset} ({len(eps)} seed{'s' if len(eps) != 1 else ''}: grey each, blue "
                             "mean)", fontsize=9)
        axes[-1][j].set_xlabel("step")
    fig.tight_layout()
    p = out_dir / "dynamics.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)

    fig, axes = plt.subplots(1, 2 * len(cfg.presets), figsize=(5 * len(cfg.presets) * 2, 3.6), squeeze=False)
    for j, preset in enumerate(cfg.presets):
        eps = [e for e in res.episodes if e["preset"] == preset]
        life = np.concatenate([np.array(e["lifetimes"]) for e in eps]) if eps else np.array([])
        ax = axes[0][2 * j]
        ax.hist(life, bins=np.arange(0, cfg.steps + 25, 25), color="#2a7ab9")
        ax.axvline(cfg.steps // 2, color="r", lw=1, ls="--", label=f"core ≥ {cfg.steps // 2}")
        ax.set_yscale("log")
        ax.set_xlabel("link lifetime (steps)")
        ax.set_ylabel("events (all seeds)")
        ax.set_title(f"{preset}: {life.size} events, median {np.median(life) if life.size else 0:.0f}",
                     fontsize=9)
        ax.legend(fontsize=7)
        ax = axes[0][2 * j + 1]
        ax.set_title(f"{preset}: ρ(AGV→picker) per seed", fontsize=9)
        rhos = [x["spearman_agv_to_picker"]["rho"] for x in eps]
        pp = [x["spearman_agv_to_picker"]["p_permutation"] for x in eps]
        ax.bar(range(len(eps)), rhos, color=["#c0392b" if (q or 1) < 0.05 else "#7f7f7f" for q in pp])
        ax.set_xticks(range(len(eps)), [str(x["seed"]) for x in eps], fontsize=7)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_ylabel("Spearman ρ(final W, mean distance)")
        ax.set_xlabel("seed")
    from matplotlib.patches import Patch

    fig.legend(handles=[Patch(color="#c0392b", label="ρ: permutation p < 0.05"),
                        Patch(color="#7f7f7f", label="ρ: not significant")], loc="upper right", fontsize=7,
               bbox_to_anchor=(1.0, 1.0), ncol=2)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    p = out_dir / "lifetimes_spearman.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    return paths
