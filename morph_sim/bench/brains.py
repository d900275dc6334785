"""``morph-sim bench brains``: what robots that learn from their own views cost in the lab, one brain for the fleet
against a brain per robot.

Under a network profile or faults on the fleet broadcast every robot learns from the view it holds, which may be
late or lost. The lab runs such a fleet in one brain where the policy offers one (``CoordinationPolicy.fleet_brains``:
every robot's state in one array, stepped from its own view) and otherwise in a brain per robot. This bench runs each
cell both ways in this process, after a warm-up episode (imports, caches), alternating the order, and prints the CPU
of each, their ratio, and each policy's cost against Proximity's of the same cell: the figures are ratios measured in
one sitting. It also checks that both ways give the same episode, tick for tick.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

NAME = "brains"
HELP = "per-episode CPU of robots with views of their own: one fleet brain vs a brain per robot, against Proximity"

# conditions (services/policies/conditions.py): morph is MORPH at the reference preset, morph_paper at the paper's
DEFAULT_POLICIES = ("morph", "morph_paper", "proximity", "tsg")
DEFAULT_PROFILES = ("wifi-fast-roaming", "congested")
RADIUS = 4  # Proximity's link radius (RunConfig's default)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scale", default="large", help="warehouse size (default large)")
    parser.add_argument("--steps", type=int, default=400, help="episode length (default 400)")
    parser.add_argument("--seeds", default="1,2,3", help="seeds: 1,2,5 or a range 1-3 (default 1,2,3)")
    parser.add_argument("--profiles", default=",".join(DEFAULT_PROFILES),
                        help=f"comma-separated network profiles (default {','.join(DEFAULT_PROFILES)})")
    parser.add_argument("--policies", default=",".join(DEFAULT_POLICIES),
                        help=f"comma-separated conditions (morph: MORPH's reference preset, morph_paper: its paper "
                             f"preset); proximity is the baseline (default {','.join(DEFAULT_POLICIES)})")


def _spec(policy: str, profile: str, seed: int, scale: str, steps: int, fleet_brain: bool):
    from morph_sim.lab.runner import EpisodeSpec

    return EpisodeSpec(scale=scale, condition=policy, seed=seed, steps=steps, network=profile,
                       radius=RADIUS if policy == "proximity" else None, fleet_brain=fleet_brain)


def _episode(spec) -> tuple[float, dict]:
    from morph_sim.lab.runner import run_episode

    cpu = time.process_time()
    result = run_episode(spec)
    return time.process_time() - cpu, result.ticks


def _same(a: dict, b: dict) -> bool:
    import numpy as np

    return a.keys() == b.keys() and all(np.array_equal(np.asarray(a[k]), np.asarray(b[k]), equal_nan=True)
                                        for k in a)


def measure(policies, profiles, seeds, scale: str, steps: int) -> list[dict]:
    """One row per (policy, profile): median CPU seconds per episode over ``seeds`` each way, and whether every
    episode was the same both ways."""
    from services.policies.interface import Fleet
    from services.world.warehouse import WarehouseConfig

    cfg = WarehouseConfig.named(scale)
    fleet = Fleet(cfg.agvs, cfg.pickers, scale)
    _episode(_spec(policies[0], profiles[0], seeds[0], scale, min(steps, 50), True))  # warm-up
    rows = []
    for profile in profiles:
        for policy in policies:
            # whether the policy has a fleet brain; without one both ways run a brain per robot
            batched = _spec(policy, profile, 0, scale, 1, True).policy().fleet_brains(fleet, 0) is not None
            fleet_cpu, robot_cpu, same = [], [], True
            for k, seed in enumerate(seeds):
                order = (True, False) if k % 2 == 0 else (False, True)
                runs = {}
                for fleet_brain in order:
                    runs[fleet_brain] = _episode(_spec(policy, profile, seed, scale, steps, fleet_brain))
                fleet_cpu.append(runs[True][0])
                robot_cpu.append(runs[False][0])
                same = same and _same(runs[True][1], runs[False][1])
            rows.append({"policy": policy, "profile": profile, "batched": batched,
                         "fleet_brain_s": statistics.median(fleet_cpu), "per_robot_s": statistics.median(robot_cpu),
                         "same": same})
    return rows


def update_in_use() -> str:
    """Which update MORPH's fleet brain runs here: compiled (with numba's version) or numpy, and why."""
    import os

    from services.policies.plasticity import compiled_kernels

    if compiled_kernels() is not None:
        from importlib.metadata import version

        return f"compiled update (numba {version('numba')}; the numpy update's bits)"
    if os.environ.get("MORPH_SIM_KERNEL", "") == "numpy":
        return "numpy update (MORPH_SIM_KERNEL=numpy)"
    return "numpy update (numba is not installed: pip install 'morph-sim[lab]' compiles it)"


def run(args: argparse.Namespace) -> int:
    from schemas.errors import one_line
    from services.inputs import at_most

    policies = [p for p in args.policies.split(",") if p]
    profiles = [p for p in args.profiles.split(",") if p]
    from morph_sim.lab.sweep import parse_seeds

    try:
        seeds = list(parse_seeds(args.seeds))  # ranges too ("1-5"), bounded before they are spelled out
        if not (policies and profiles and seeds) or args.steps < 1:
            raise ValueError("policies, profiles, seeds: at least one each, and steps >= 1")
        at_most(len(policies) * len(profiles) * len(seeds), 1000, "cells", "policy × profile × seed cells")
        rows = measure(policies, profiles, seeds, args.scale, args.steps)
    except ValueError as exc:
        print(f"morph-sim bench brains: error: {one_line(exc)}", file=sys.stderr)
        return 2
    print(f"{args.scale}, {args.steps} steps, seeds {','.join(map(str, seeds))}: CPU s per episode (median); "
          "one fleet brain vs a brain per robot, and against Proximity's episode of the same profile, same way")
    print(f"MORPH's fleet brain: {update_in_use()}")
    print(f"{'profile':<22}{'policy':<12}{'fleet brain':>12}{'per robot':>11}{'speed-up':>10}"
          f"{'fleet/Prox':>12}{'robot/Prox':>12}  same")
    base = {(r["profile"]): r for r in rows if r["policy"] == "proximity"}
    for r in rows:
        prox = base.get(r["profile"])
        vs_fleet = f"{r['fleet_brain_s'] / prox['fleet_brain_s']:.2f}×" if prox else "–"
        vs_robot = f"{r['per_robot_s'] / prox['per_robot_s']:.2f}×" if prox else "–"
        fleet = f"{r['fleet_brain_s']:.3f}" if r["batched"] else "(per robot)"
        print(f"{r['profile']:<22}{r['policy']:<12}{fleet:>12}{r['per_robot_s']:>11.3f}"
              f"{r['per_robot_s'] / r['fleet_brain_s']:>9.2f}×{vs_fleet:>12}{vs_robot:>12}  "
              f"{'yes' if r['same'] else 'NO'}")
    return 0 if all(r["same"] for r in rows) else 1

