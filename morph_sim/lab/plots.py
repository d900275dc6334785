"""Figures of a suite: cumulative deliveries, link usage, grouped bars (the paper's Fig. 3/4 layout)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from services.policies.conditions import CONDITIONS, study_condition  # noqa: E402

_COLOURS = {
    "morph": "#2a7ab9", "full": "#7f7f7f", "tsg": "#e08a2c", "proximity": "#3a9a4a", "none": "#c0392b",
    "v1": "#8e6bbf", "no_threshold": "#b5597e", "no_reward": "#9a7b4f", "no_neuromod": "#4fb0b5",
    "constant": "#bbbb33", "reset_at_boundary": "#555599",
}


def _seeds(cfg) -> str:
    n = len(cfg.seeds)
    return f"{n} seed{'s' if n != 1 else ''}"


def plot_suite(result, rows: list[dict], out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = result.config
    paths = []
    for what, ylabel, fname in (("deliveries_total", "cumulative deliveries", "cumulative_deliveries.png"),
                                ("links", "active links", "link_usage.png")):
        # constrained layout keeps the suptitle and the legend (outside the axes, never over a curve) in the figure,
        # whatever the number of scales
        fig, axes = plt.subplots(1, len(cfg.scales), figsize=(2.4 + 4.2 * len(cfg.scales), 3.6), squeeze=False,
                                 layout="constrained")
        for ax, s in zip(axes[0], cfg.scales):
            for c in cfg.conditions:
                y = result.series[(s, c)][what]
                ax.plot(np.arange(len(y)), y, label=study_condition(c, CONDITIONS).label, color=_COLOURS.get(c), lw=1.4)
            ax.set_title(s)
            ax.set_xlabel("step")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
        fig.legend(*axes[0][0].get_legend_handles_labels(), loc="outside right upper", fontsize=7,
                   title="condition", title_fontsize=7)
        fig.suptitle(f"{cfg.kind} study, preset {cfg.preset}: {ylabel} (mean over {_seeds(cfg)})", fontsize=10)
        p = out_dir / fname
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)

    # grouped bars: deliveries (mean ± std) per scale, one bar per condition
    fig, ax = plt.subplots(figsize=(4.2 + 2.4 * len(cfg.scales), 3.8), layout="constrained")
    k = len(cfg.conditions)
    width = 0.8 / k
    x = np.arange(len(cfg.scales))
    for m, c in enumerate(cfg.conditions):
        means = [next(r for r in rows if r["scale"] == s and r["condition"] == c)["mean"] for s in cfg.scales]
        stds = [next(r for r in rows if r["scale"] == s and r["condition"] == c)["std"] for s in cfg.scales]
        ax.bar(x - 0.4 + width * (m + 0.5), means, width, yerr=stds, capsize=2, label=study_condition(c, CONDITIONS).label,
               color=_COLOURS.get(c))
    ax.set_xticks(x, [f"{s}" for s in cfg.scales])
    ax.set_ylabel(f"deliveries in {cfg.steps} steps")
    fig.legend(loc="outside right upper", fontsize=7, title="condition (mean ± std)", title_fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(f"{cfg.kind} study, preset {cfg.preset}, {_seeds(cfg)}")
    p = out_dir / "deliveries_bars.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths
