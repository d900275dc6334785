"""``morph-sim bench distributed``: the distributed run's tick rate against the raw Zenoh barrier, same process count.

Measured in one invocation, back to back on the same machine:

1. a zero-fault ``morph-sim up`` run (sim + one OS process per agent + monitor, over Zenoh) of the chosen scale and
   policy; its rate is the sim's tick loop (``run.finished``: steps / wall seconds between tick 0 and the end, process
   start-up excluded);
2. the raw lock-step barrier (``morph_sim.services.bus.barrier_bench``, plain zenoh-python callbacks, recommended
   settings) with the same number of agent processes.

The ratio says how much of the transport's ceiling the protocol, the warehouse and the agents' plasticity leave.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from pathlib import Path

NAME = "distributed"
HELP = "distributed tick rate (up, one process per agent) vs the raw Zenoh barrier for the same process count"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scale", default="medium", help="warehouse size (default medium: 12 AGVs + 6 pickers)")
    parser.add_argument("--policy", default="morph", help="coordination policy (default morph)")
    parser.add_argument("--preset", default="reference", help="MORPH preset (default reference)")
    parser.add_argument("--agvs", type=int, default=None, help="AGV count (default: the scale's)")
    parser.add_argument("--pickers", type=int, default=None, help="picker count (default: the scale's)")
    parser.add_argument("--steps", type=int, default=800, help="ticks of the distributed run (default 800)")
    parser.add_argument("--barrier-ticks", type=int, default=2000, help="ticks of the barrier run (default 2000)")
    parser.add_argument("--seed", type=int, default=42)
    parser.add_argument("--output-dir", default=None, help="keep the run record here (default: a temporary dir)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def distributed_rate(config) -> dict:
    """Run ``config`` with the supervisor; the sim's tick-loop rate from the record's run.finished event."""
    from morph_sim.services.supervisor.launcher import Supervisor

    started = time.monotonic()
    code = asyncio.run(Supervisor(config).run())
    if code != 0:
        raise RuntimeError(f"the distributed run ended with status {code}")
    finished = None
    for line in (config.record_dir / "events.jsonl").read_text().splitlines():
        event = json.loads(line)
        if event.get("kind") == "run.finished":
            finished = event["details"]
    if not finished or not finished.get("wall_seconds"):
        raise RuntimeError(f"no run.finished event in {config.record_dir}")
    return {"ticks": finished["steps"], "seconds": finished["wall_seconds"],
            "ticks_per_s": finished["steps"] / finished["wall_seconds"], "deliveries": finished["deliveries"],
            "total_wall_s": time.monotonic() - started}


def run(args: argparse.Namespace) -> int:
    from morph_sim.services.bus.barrier_bench import run_barrier
    from morph_sim.services.runconfig import RunConfig

    with tempfile.TemporaryDirectory(prefix="morph-bench-") as tmp:
        out = Path(args.output_dir) if args.output_dir else Path(tmp)
        config = RunConfig.coerce(dict(
            run_id=f"bench-{args.scale}-{args.policy}", scale=args.scale, policy=args.policy, preset=args.preset,
            agvs=args.agvs, pickers=args.pickers, steps=args.steps, seed=args.seed, output_dir=out,
            state_every=max(10, args.steps // 8), snapshot_every=max(10, args.steps // 8) * 4))
        dist = distributed_rate(config)
    n = config.n_agents
    barrier = run_barrier(n, args.barrier_ticks, 100, mode="raw")
    ratio = dist["ticks_per_s"] / barrier.ticks_per_s if barrier.ticks_per_s else float("nan")
    result = {"scale": args.scale, "policy": args.policy, "preset": args.preset, "agents": n,
              "distributed_ticks_per_s": round(dist["ticks_per_s"], 1), "distributed_ticks": dist["ticks"],
              "barrier_ticks_per_s": round(barrier.ticks_per_s, 1), "barrier_ticks": barrier.ticks,
              "ratio": round(ratio, 3)}
    if args.json:
        print(json.dumps(result))
    else:
        label = args.policy + (f"/{args.preset}" if args.policy == "morph" else "")
        print(f"distributed {args.scale} ({n} agent processes, {label}): {dist['ticks_per_s']:.0f} ticks/s "
              f"over {dist['ticks']} ticks")
        print(f"raw Zenoh barrier, {n} agent processes: {barrier.ticks_per_s:.0f} ticks/s "
              f"(p50 {barrier.p50_ms:.2f} ms, p99 {barrier.p99_ms:.2f} ms)")
        print(f"ratio distributed / barrier: {ratio:.0%}")
    return 0
