"""``morph-sim bench policies``: the policy board — any set of policies on one standard board of warehouses,
networks, a fault level and fixed seeds, in the lab, with a leaderboard.

The board is versioned (:data:`BOARDS`): a board's cells and seeds never change under its version, so two
leaderboards of one version compare. Every policy runs every cell with the same seeds; per seed, its deliveries
are averaged over the cells, and the leaderboard ranks those means (95 % t interval over the seeds), with Welch's p
of each entry against the best and a Bonferroni threshold over the comparisons. Beside deliveries it reports what a
policy pays for them (dispatch and policy messages and bytes per delivery, the dispatch delay) and its robustness
(deliveries under each network profile relative to the ideal ``lan``). The record is resumable (the same
``--run-id`` skips the episodes done) and runs on local workers or a Dask cluster like every study.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

NAME = "policies"
HELP = "the policy board: policies on a standard board of warehouses × networks × loss × seeds, with a leaderboard"

#: the boards by version; a version's cells never change (a new board is a new version)
BOARDS: dict[str, dict[str, Any]] = {
    "1": {"scales": ["small", "medium"], "profiles": ["lan", "wifi-fast-roaming", "wifi-legacy-roaming", "congested"],
          "loss_percent": [0.0, 10.0], "seeds": [1, 2, 3, 4, 5], "steps": 300},
    # a board for a quick look and for the tests: one cell per profile, two seeds
    "quick": {"scales": ["tiny"], "profiles": ["lan", "congested"], "loss_percent": [0.0], "seeds": [1, 2],
              "steps": 120},
}
DEFAULT_POLICIES = ("morph", "full", "full-broadcast", "tsg", "proximity", "none")
ALPHA = 0.05


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policies", default=",".join(DEFAULT_POLICIES), metavar="P1,P2,…",
                        help="policies to enter: shipped names, installed ones, package.module:Class "
                             f"(default {','.join(DEFAULT_POLICIES)})")
    parser.add_argument("--board", default="1", choices=tuple(BOARDS), help="the board's version (default 1)")
    parser.add_argument("--out", default="runs", help="parent directory of the board's record (default runs)")
    parser.add_argument("--run-id", default=None, help="the record's id; the same id resumes (default: generated)")
    parser.add_argument("--executor", choices=("local", "dask"), default="local", help="where episodes run")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://HOST:8786")
    parser.add_argument("--jobs", type=int, default=2, help="local worker processes (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


@dataclass(frozen=True)
class BoardTask:
    policy: str
    scale: str
    profile: str
    loss_percent: float
    seed: int
    steps: int

    @property
    def key(self) -> str:
        return f"{self.policy}|{self.scale}|{self.profile}|loss={self.loss_percent:g}|seed={self.seed}"


def run_board_task(task: BoardTask) -> dict:
    """One episode -> its record line (module level: pickled to the workers)."""
    from morph_sim.lab.runner import EpisodeSpec, run_episode
    from services.policies.loading import resolve

    options = {"episode_steps": task.steps} if "episode_steps" in resolve(task.policy).Params.model_fields else {}
    t0, c0 = time.perf_counter(), time.process_time()
    res = run_episode(EpisodeSpec(scale=task.scale, condition=task.policy, policy_name=task.policy,
                                  policy_options=options, seed=task.seed, steps=task.steps, network=task.profile,
                                  loss_percent=task.loss_percent, fiedler_every=10**9))
    s = res.summary
    d = s["deliveries"]
    episode = {"policy": task.policy, "scale": task.scale, "profile": task.profile, "loss_percent": task.loss_percent,
               "seed": task.seed, "deliveries": int(d),
               "messages_per_delivery": s["messages_sent"] / d if d else None,
               "bytes_per_delivery": s["bytes_sent"] / d if d else None,
               "dispatch_delay": _finite(s.get("dispatch_delay")),
               # every profile here gives each robot its own view: one fleet brain where the policy has one
               # (CoordinationPolicy.fleet_brains), else a brain per robot (the same numbers, slower)
               "brains": s["brains"]}
    return {"key": task.key, "episode": episode, "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0}


def _finite(v):
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else v


def board_tasks(policies: list[str], board: dict[str, Any]) -> list[tuple[str, BoardTask]]:
    tasks = [BoardTask(p, scale, profile, float(loss), int(seed), int(board["steps"]))
             for p in policies for scale in board["scales"] for profile in board["profiles"]
             for loss in board["loss_percent"] for seed in board["seeds"]]
    return [(t.key, t) for t in tasks]


def leaderboard(episodes: list[dict], policies: list[str], board: dict[str, Any]) -> list[dict]:
    """One row per policy, best first: deliveries (mean over seeds of the per-seed mean over cells, 95 % t interval),
    messages and bytes per delivery, dispatch delay, robustness per profile, Welch p against the best."""
    import numpy as np
    from scipy import stats

    from morph_sim.lab.grid import bonferroni, welch

    rows = []
    for p in policies:
        mine = [e for e in episodes if e["policy"] == p]
        per_seed = [float(np.mean([e["deliveries"] for e in mine if e["seed"] == s])) for s in board["seeds"]]
        n = len(per_seed)
        mean = float(np.mean(per_seed))
        half = (float(stats.t.ppf(0.975, n - 1) * np.std(per_seed, ddof=1) / math.sqrt(n)) if n > 1 else None)

        def avg(key, mine=mine):
            vals = [e[key] for e in mine if e.get(key) is not None]
            return float(np.mean(vals)) if vals else None

        lan = [e["deliveries"] for e in mine if e["profile"] == "lan"]
        robust = {}
        for profile in board["profiles"]:
            if profile == "lan":
                continue
            under = [e["deliveries"] for e in mine if e["profile"] == profile]
            robust[profile] = float(np.mean(under) / np.mean(lan)) if lan and np.mean(lan) > 0 else None
        rows.append({"policy": p, "deliveries": mean, "ci95": half, "per_seed": per_seed,
                     "messages_per_delivery": avg("messages_per_delivery"),
                     "bytes_per_delivery": avg("bytes_per_delivery"), "dispatch_delay": avg("dispatch_delay"),
                     "robustness": robust, "brains": mine[0]["brains"] if mine else None})
    rows.sort(key=lambda r: -r["deliveries"])
    best = rows[0]
    for r in rows:
        r["p_vs_best"] = None if r is best else welch(r["per_seed"], best["per_seed"])
    _, threshold = bonferroni([r["p_vs_best"] for r in rows], ALPHA)
    for r in rows:
        r["significant"] = r["p_vs_best"] is not None and r["p_vs_best"] < threshold
    for r in rows:
        r["bonferroni_threshold"] = threshold
    return rows


def _fmt(v, spec: str = ".1f") -> str:
    return "–" if v is None else format(v, spec)


def write_board(run_dir: Path, rows: list[dict], board: dict[str, Any], version: str) -> list[Path]:
    from morph_sim.lab.grid import p_text

    profiles = [p for p in board["profiles"] if p != "lan"]
    threshold = rows[0]["bonferroni_threshold"]
    md = [f"# Policy board v{version}", "",
          f"Cells: scales {', '.join(board['scales'])} × profiles {', '.join(board['profiles'])} × dispatch loss "
          f"{', '.join(f'{x:g} %' for x in board['loss_percent'])}; seeds {', '.join(map(str, board['seeds']))}; "
          f"{board['steps']} steps; the lab, every robot learning from its own view (brains: one for the fleet, or "
          f"one per robot where the policy has no fleet brain). Deliveries: mean over seeds of each seed's mean "
          f"over the cells, ± the 95 % t interval; Welch p against the best entry, **bold** below the Bonferroni "
          f"threshold {threshold:.3g}. Robustness: deliveries under a profile / under lan.", "",
          "| rank | policy | deliveries | p vs best | messages/delivery | bytes/delivery | dispatch delay (s) | "
          + " | ".join(f"{p} / lan" for p in profiles) + " | brains |",
          "|---|---|---|---|---|---|---|" + "---|" * len(profiles) + "---|"]
    for i, r in enumerate(rows, 1):
        p = "best" if r["p_vs_best"] is None and i == 1 else p_text(r["p_vs_best"], threshold)
        md.append(f"| {i} | {r['policy']} | {r['deliveries']:.1f} ± {_fmt(r['ci95'])} | {p} | "
                  f"{_fmt(r['messages_per_delivery'])} | {_fmt(r['bytes_per_delivery'], '.0f')} | "
                  f"{_fmt(r['dispatch_delay'], '.2f')} | "
                  + " | ".join(_fmt(r["robustness"].get(q), ".2f") for q in profiles) + f" | {r['brains']} |")
    paths = [run_dir / "leaderboard.md", run_dir / "leaderboard.csv"]
    paths[0].write_text("\n".join(md) + "\n", encoding="utf-8")
    with open(paths[1], "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["rank", "policy", "deliveries", "ci95", "p_vs_best", "significant", "messages_per_delivery",
                    "bytes_per_delivery", "dispatch_delay", *[f"robustness_{q}" for q in profiles], "brains"])
        for i, r in enumerate(rows, 1):
            w.writerow([i, r["policy"], r["deliveries"], r["ci95"], r["p_vs_best"], r["significant"],
                        r["messages_per_delivery"], r["bytes_per_delivery"], r["dispatch_delay"],
                        *[r["robustness"].get(q) for q in profiles], r["brains"]])
    try:
        paths.append(_figure(run_dir, rows, profiles))
    except ImportError:  # matplotlib is the [lab] extra: the tables stand without it
        pass
    return paths


def _figure(run_dir: Path, rows: list[dict], profiles: list[str]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    names = [r["policy"] for r in rows]
    a.barh(names[::-1], [r["deliveries"] for r in rows][::-1],
           xerr=[r["ci95"] or 0 for r in rows][::-1], color="#4c72b0")
    a.set_xlabel("deliveries (mean over seeds, 95 % CI)")
    for i, q in enumerate(profiles):
        b.bar([x + i * 0.8 / len(profiles) for x in range(len(rows))],
              [r["robustness"].get(q) or 0 for r in rows], width=0.8 / len(profiles), label=q)
    b.set_xticks(range(len(rows)), names, rotation=30, ha="right")
    b.axhline(1.0, color="grey", lw=0.8)
    b.set_ylabel("deliveries / deliveries on lan")
    b.legend(fontsize=8)
    fig.tight_layout()
    path = run_dir / "leaderboard.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> int:
    from morph_sim.lab.grid import run_grid
    from services.policies.loading import make_policy

    policies = [p.strip() for p in args.policies.split(",") if p.strip()]
    if not policies or len(set(policies)) != len(policies):
        raise ValueError("policies: give each policy once, comma-separated")
    for p in policies:
        make_policy(p)  # a bad name: one line, exit 2, before anything runs
    if not 1 <= args.jobs <= 256:
        raise ValueError(f"jobs: {args.jobs} outside 1..256")
    board = BOARDS[args.board]
    run_id = args.run_id or time.strftime("board-%Y%m%d-%H%M%S", time.gmtime())
    run_dir = Path(args.out) / run_id
    plan = {"board": args.board, **board, "policies": policies}
    done = run_grid(run_dir, kind="policy-board", plan=plan, tasks=board_tasks(policies, board), fn=run_board_task,
                    executor=args.executor, jobs=args.jobs, scheduler=args.scheduler,
                    progress=not args.no_progress)
    episodes = [r["episode"] for r in done.done.values()]
    rows = leaderboard(episodes, policies, board)
    paths = write_board(run_dir, rows, board, args.board)
    cpu = sum(r.get("cpu_s", 0.0) for r in done.done.values())
    print((run_dir / "leaderboard.md").read_text(encoding="utf-8"))
    print(f"board v{args.board}: {len(episodes)} episodes ({done.ran} run now, {done.skipped} from the record), "
          f"{done.wall_s:.0f} s wall, {cpu:.0f} CPU-s in the episodes; {', '.join(str(p) for p in paths)}")
    (run_dir / "leaderboard.json").write_text(json.dumps(rows, indent=2), encoding="utf-8")
    return 0
