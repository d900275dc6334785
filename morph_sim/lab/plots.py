"""Figures of a suite: cumulative deliveries, link usage, grouped bars (the paper's Fig. 3/4 layout)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from morph_sim.lab.runner import CONDITIONS  # noqa: E402

_COLOURS = {
    "morph": "#2a7ab9", "full": "#7f7f7f", "tsg": "#e08a2c", "proximity": "#3a9a4a", "none": "#c0392b",
    "v1": "#8e6bbf", "no_threshold": "#b5597e", "no_reward": "#9a7b4f", "no_neuromod": "#4fb0b5",
    "constant": "#bbbb33", "reset_at_boundary": "#555599",
}


def plot_suite(result, rows: list[dict], out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = result.config
    paths = []
    for what, ylabel, fname in (("deliveries", "cumulative deliveries", "cumulative_deliveries.png"),
                                ("links", "active links", "link_usage.png")):
        fig, axes = plt.subplots(1, len(cfg.scales), figsize=(4.2 * len(cfg.scales), 3.4), squeeze=False)
        for ax, s in zip(axes[0], cfg.scales):
            for c in cfg.conditions:
                y = result.series[(s, c)][what]
                ax.plot(np.arange(len(y)), y, label=CONDITIONS[c][0], color=_COLOURS.get(c), lw=1.4)
            ax.set_title(s)
            ax.set_xlabel("step")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
        axes[0][-1].legend(fontsize=7, loc="upper left")
        fig.suptitle(f"{cfg.kind} study, preset {cfg.preset}: {ylabel} (mean over {len(cfg.seeds)} seeds)")
        fig.tight_layout()
        p = out_dir / fname
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)

    # grouped bars: deliveries (mean ± std) per scale, one bar per condition
    fig, ax = plt.subplots(figsize=(2.2 + 2.4 * len(cfg.scales), 3.8))
    k = len(cfg.conditions)
    width = 0.8 / k
    x = np.arange(len(cfg.scales))
    for m, c in enumerate(cfg.conditions):
        means = [next(r for r in rows if r["scale"] == s and r["condition"] == c)["mean"] for s in cfg.scales]
        stds = [next(r for r in rows if r["scale"] == s and r["condition"] == c)["std"] for s in cfg.scales]
        ax.bar(x - 0.4 + width * (m + 0.5), means, width, yerr=stds, capsize=2, label=CONDITIONS[c][0],
               color=_COLOURS.get(c))
    top = max((r["mean"] + r["std"]) for r in rows) if rows else 1.0
    ax.set_ylim(0, max(top, 1.0) * 1.35)  # room for the legend above the bars
    ax.set_xticks(x, [f"{s}" for s in cfg.scales])
    ax.set_ylabel(f"deliveries in {cfg.steps} steps")
    ax.legend(fontsize=7, ncol=3)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(f"{cfg.kind} study, preset {cfg.preset}")
    fig.tight_layout()
    p = out_dir / "deliveries_bars.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths
