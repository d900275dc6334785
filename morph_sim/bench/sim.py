"""``morph-sim bench sim``: whole-episode speed and memory of the warehouse simulation, per size.

Each size runs one heuristic episode (controller included, reset included) in a fresh Python process, so the peak
RSS reported is that of a process doing nothing else (interpreter + numpy + pydantic + the simulation). The original
TA-RWARE's rate on this machine is read from ``presets/bench_reference.toml`` (its source is named there); its
figures are CPU-time rates, so the ratio compares CPU-time rates too. Wall-clock rates are shown as well.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tomllib
from importlib import resources

NAME = "sim"
HELP = "whole-episode steps/s (heuristic included) and peak RSS per warehouse size, vs the original TA-RWARE"

SCALES = ("tiny", "small", "medium", "large", "extralarge")


def reference_rates() -> tuple[dict[str, float], str, dict[str, float], str]:
    """(the original's rates on this machine, their source, the same re-measured on an idle machine, its source)."""
    text = resources.files("morph_sim.bench").joinpath("reference.toml").read_text(encoding="utf-8")
    data = tomllib.loads(text)
    idle = dict(data.get("steps_per_second_idle", {}))
    idle_source = str(idle.pop("source", ""))
    return ({k: float(v) for k, v in data["steps_per_second"].items()}, data["source"],
            {k: float(v) for k, v in idle.items()}, idle_source)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scales", default=",".join(SCALES), metavar="SCALES",
                        help=f"comma-separated sizes to run, e.g. tiny,small (default: all of {','.join(SCALES)})")
    parser.add_argument("--steps", type=int, default=800, help="episode length (default 800, as the reference)")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per size instead of a table")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds allowed per episode process")


def _peak_rss_kb(resource) -> float:
    """This process's own peak resident memory in KiB. ``ru_maxrss`` is not it on Linux: a child started by fork and
    exec keeps its parent's high-water mark from the fork (a large test runner's 600 MB showed up as the episode's),
    while ``VmHWM`` belongs to the process image and starts afresh at exec."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1])
    except OSError:
        pass
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)  # elsewhere: the best figure there is


def measure(scale: str, steps: int, seed: int) -> dict:
    """Run one episode in this process and report its speed and this process's peak RSS."""
    import resource
    import time

    from services.world.heuristic import run_episode
    from services.world.warehouse import WarehouseConfig

    config = WarehouseConfig.named(scale, max_steps=steps)
    cpu0 = time.process_time()
    result = run_episode(config, seed)
    cpu = time.process_time() - cpu0
    peak_kb = _peak_rss_kb(resource)
    return {
        "scale": scale, "agvs": config.agvs, "pickers": config.pickers, "steps": result.steps, "seed": seed,
        "deliveries": result.deliveries, "wall_s": result.seconds, "cpu_s": cpu,
        "steps_per_s_wall": result.steps / result.seconds, "steps_per_s_cpu": result.steps / cpu if cpu else None,
        "peak_rss_mb": peak_kb / 1024.0,
    }


def _child(scale: str, steps: int, seed: int, timeout: float) -> dict:
    cmd = [sys.executable, "-m", "morph_sim.bench.sim", scale, str(steps), str(seed)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"bench sim: episode process for {scale} failed:\n{proc.stderr.strip()}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(args: argparse.Namespace) -> int:
    args.scales = [s.strip() for s in args.scales.split(",") if s.strip()]  # commas, as everywhere in morph-sim
    if not args.scales:
        raise ValueError("scales: give at least one size, e.g. --scales tiny,small")
    bad = [s for s in args.scales if s not in SCALES]
    if bad:
        raise ValueError(f"scales: unknown size(s) {', '.join(bad)}; choose from {', '.join(SCALES)}")
    if args.steps < 1:
        raise ValueError(f"steps: must be >= 1, got {args.steps}")
    rates, source, idle_rates, idle_source = reference_rates()
    rows = []
    for scale in args.scales:
        row = _child(scale, args.steps, args.seed, args.timeout)
        ref = rates.get(scale)
        row["original_steps_per_s"] = ref
        row["speedup_cpu"] = row["steps_per_s_cpu"] / ref if ref and row["steps_per_s_cpu"] else None
        idle = idle_rates.get(scale)
        row["original_idle_steps_per_s"] = idle
        row["speedup_cpu_vs_idle"] = row["steps_per_s_cpu"] / idle if idle and row["steps_per_s_cpu"] else None
        rows.append(row)
        if args.json:
            print(json.dumps(row), flush=True)
    if args.json:
        return 0
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"warehouse simulation, heuristic episode of {args.steps} steps, seed {args.seed}")
    for col in ("scale", "agents", "deliveries", "steps/s wall", "steps/s CPU", "original steps/s", "ratio (CPU)",
                "original idle", "ratio vs idle", "peak RSS MB"):
        table.add_column(col, justify="right")
    for r in rows:
        ref = r["original_steps_per_s"]
        table.add_row(
            r["scale"], f"{r['agvs']}+{r['pickers']}", str(r["deliveries"]), f"{r['steps_per_s_wall']:,.0f}",
            f"{r['steps_per_s_cpu']:,.0f}", f"{ref:,.0f}" if ref else "n/a",
            f"{r['speedup_cpu']:.1f}x" if r["speedup_cpu"] else "n/a",
            f"{r['original_idle_steps_per_s']:,.0f}" if r["original_idle_steps_per_s"] else "n/a",
            f"{r['speedup_cpu_vs_idle']:.1f}x" if r["speedup_cpu_vs_idle"] else "n/a", f"{r['peak_rss_mb']:.1f}",
        )
    console = Console(width=None if Console().is_terminal else 140)
    console.print(table)
    console.print(f"original steps/s: {source}.")
    console.print(f"original idle: {idle_source}.")
    console.print("Each size ran in its own process; RSS = that process's own peak (VmHWM); ratios use CPU-time rates.")
    return 0


if __name__ == "__main__":  # child process: python -m morph_sim.bench.sim SCALE STEPS SEED
    _scale, _steps, _seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    print(json.dumps(measure(_scale, _steps, _seed)), flush=True)
