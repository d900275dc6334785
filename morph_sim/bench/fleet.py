"""``morph-sim bench fleet``: what a distributed fleet costs as it grows, and the shortest real-time period it holds.

For each fleet size (three AGVs to a picker, in the extralarge warehouse) this runs, in one invocation on this
machine:

1. a lockstep ``up`` at full speed: its tick rate (the fleet's capacity), the CPU milliseconds per tick of each
   process role (:class:`~morph_sim.bench.distributed.CpuMeter`) and the largest private memory (USS) of an agent
   process;
2. a paced ``up`` at the requested ``--period`` (default 0.1 s, a real fleet's 10 Hz), then at shorter periods if it
   held (down to what the capacity allows) or longer ones if it did not, until the verdict changes: the shortest
   period held. A period is held when the mean tick interval is within 5 % of it, no interval is over twice it once
   the fleet has settled (after its first ticks), and the sim was never more than a period behind
   (``rescheduled``).

The knee is the smallest fleet that does not hold the requested period. Wall-clock figures move with what else runs
on the cores; CPU per tick much less (the load average is printed with them).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import time
from pathlib import Path

from morph_sim.bench.distributed import CpuMeter, Sampler, load_average, tick_points, tick_time
from services.sim.result import SETTLE_TICKS

NAME = "fleet"
HELP = ("fleets of 8, 32, 64 and 128 robot processes: CPU per tick by role, agent memory, the shortest period a "
        "paced run holds, and the knee")

DEFAULT_SIZES = (8, 32, 64, 128)
PERIODS = (0.025, 0.05, 0.1, 0.2, 0.4, 0.8, 1.6)  # candidate periods, wall seconds per tick
MAX_TRIES = 3  # paced runs per fleet size at most (the requested period is one of them)
MEAN_SLACK = 1.05  # a held period: mean interval within 5 % of it ...
MAX_FACTOR = 2.0  # ... and no settled interval over twice it
MAX_ROBOTS = 256
SAMPLE_S = 0.01  # seconds between the CPU samples of a run's processes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", default=",".join(map(str, DEFAULT_SIZES)),
                        help=f"comma-separated fleet sizes, robots (default {','.join(map(str, DEFAULT_SIZES))}); "
                             "three AGVs to a picker, at least 4")
    parser.add_argument("--ticks", type=int, default=200, help="ticks of each run (default 200)")
    parser.add_argument("--period", type=float, default=0.1,
                        help="the period every size is tried at, wall seconds (default 0.1: 10 Hz)")
    parser.add_argument("--policy", default="morph", help="coordination policy (default morph)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per size, then the knee")


def fleet_of(robots: int) -> tuple[int, int]:
    """(AGVs, pickers) of a fleet of ``robots``: three AGVs to a picker, as the scale study's fleets."""
    pickers = max(1, robots // 4)
    return robots - pickers, pickers


def schedule(requested: float, capacity: float, was_held: bool) -> list[float]:
    """The periods to try after the requested one, in order: shorter ones, longest first, down to what the lockstep
    capacity (ticks/s) leaves room for, if the requested period held; longer ones, shortest first, if it did not.
    Trying stops at the first change of verdict (:data:`MAX_TRIES` runs at most in all)."""
    if was_held:
        floor = 1.0 / capacity if capacity > 0 else requested
        return sorted((p for p in PERIODS if floor <= p < requested), reverse=True)[:MAX_TRIES - 1]
    return sorted(p for p in PERIODS if p > requested)[:MAX_TRIES - 1]


def held(pace: dict, period: float) -> bool:
    """Whether a paced run held ``period`` (its ``run.finished`` pace summary)."""
    return (pace["interval_mean"] <= MEAN_SLACK * period and pace["interval_max_settled"] <= MAX_FACTOR * period
            and pace["rescheduled"] == 0)


def knee(rows: list[dict]) -> int | None:
    """The smallest fleet size that does not hold the requested period (None: every size held it)."""
    missed = [r["robots"] for r in rows if not r["holds_requested"]]
    return min(missed) if missed else None


def _parse_sizes(text: str) -> list[int]:
    try:
        sizes = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"sizes: comma-separated whole numbers, got {text!r}") from None
    if not sizes or any(n < 4 or n > MAX_ROBOTS for n in sizes):
        raise ValueError(f"sizes: each from 4 to {MAX_ROBOTS} robots, got {text!r}")
    return sorted(set(sizes))


MEMORY_DUTY = 20  # the memory meter reads at most 1/this of its time: a round of USS readings costs ~0.3 ms an agent


class _MemoryMeter(Sampler):
    """The largest private memory (USS, MiB) of an agent process at the run's middle tick.

    A thread reads every live agent's USS in rounds, each round stamped with the host's monotonic clock and the next
    one after a pause of ``MEMORY_DUTY`` times the CPU the round took (at least ``sample_s``), so that reading costs
    the supervisor's process a bounded share. After the run, the round nearest the start of the middle tick on the
    sim's tick clock is the figure. Rounds before the first tick do not count (the agents have not run yet); rounds
    after the final tick do, if the round nearest the middle is one (a short run on a loaded machine): the agents
    have run the whole run then. Placing the reading by the sim's clock rather than by the ticks the supervisor has
    seen finds the agents alive even when a loaded machine hands the supervisor the run's ticks late, after the
    agents have left."""

    name = "agent-uss"

    def __init__(self, supervisor, sample_s: float = 0.05):
        super().__init__()
        self.sup, self.sample_s = supervisor, sample_s
        self.rounds: list[tuple[float, int]] = []  # (monotonic seconds at the round's end, largest USS in bytes)

    def _round(self) -> float:
        """One round of readings; the CPU seconds they took (unlike their wall time, not stretched by a loaded
        machine)."""
        import psutil

        began = time.thread_time()
        largest = 0
        for name, child in list(self.sup.children.items()):
            if not name.startswith("agent-") or not child.alive():
                continue
            try:
                largest = max(largest, self.process(child.pid).memory_full_info().uss)
            except psutil.Error:
                continue
        if largest:
            self.keep(self.rounds, (time.monotonic(), largest))
        return time.thread_time() - began

    def reading(self) -> float:
        return max(self.sample_s, MEMORY_DUTY * self._round())

    def uss_mib(self, tick_clock: list | None) -> float | None:
        """The figure, by the sim's ``tick_clock`` ([[tick, monotonic seconds], ...]); None without a round taken
        from the first tick on."""
        points = tick_points(tick_clock)
        if len(points) < 2:
            return None
        began, middle = points[0][1], tick_time(points, points[-1][0] / 2)
        ran = [(abs(at - middle), uss) for at, uss in self.rounds if at >= began]
        return min(ran)[1] / 2**20 if ran else None


def _run(config, *, memory: bool = False) -> tuple[dict, dict[str, float], float | None]:
    """One ``up`` of ``config`` under the supervisor in this process: its ``run.finished`` details, its CPU ms per
    tick by role, and with ``memory`` the largest agent USS (MiB) at its middle tick."""
    from services.supervisor.launcher import Supervisor

    supervisor = Supervisor(config)
    # a small fleet runs its ticks in a blink at full speed: samples close enough that its window holds several
    meters = [CpuMeter(supervisor, config.n_agvs, sample_s=SAMPLE_S)]
    if memory:
        meters.append(_MemoryMeter(supervisor, sample_s=SAMPLE_S))
    for meter in meters:
        meter.start()
    try:
        code = asyncio.run(supervisor.run())
    finally:
        for meter in meters:
            meter.stop()
    if code != 0:
        raise RuntimeError(f"bench fleet: the run of {config.n_agents} robots ended with status {code} "
                           f"(record: {config.record_dir})")
    finished = None
    for line in (config.record_dir / "events.jsonl").read_text().splitlines():
        event = json.loads(line)
        if event.get("kind") == "run.finished":
            finished = event["details"]
    if finished is None:
        raise RuntimeError(f"bench fleet: no run.finished event in {config.record_dir}")
    clock = finished.get("tick_clock")
    return finished, meters[0].per_tick_ms(clock), meters[1].uss_mib(clock) if memory else None


def measure_size(robots: int, args: argparse.Namespace, out: Path) -> dict:
    from services.runconfig import RunConfig

    agvs, pickers = fleet_of(robots)
    every = max(10, args.ticks // 4)

    def config(mode: str, period: float | None = None):
        tag = mode + (f"-{round(period * 1000)}ms" if period is not None else "")
        return RunConfig.coerce(dict(
            run_id=f"fleet-{robots}-{tag}", scale="extralarge", agvs=agvs, pickers=pickers, policy=args.policy,
            steps=args.ticks, seed=42, output_dir=out, mode=mode, state_every=every, snapshot_every=every * 4,
            **({"period": period} if period is not None else {})))

    finished, cpu, uss = _run(config("lockstep"), memory=True)
    capacity = finished["steps"] / finished["wall_seconds"] if finished.get("wall_seconds") else 0.0

    def paced(period: float) -> dict:
        pace = _run(config("paced", period))[0]["pace"]
        return {"period": period, "held": held(pace, period), "interval_mean": pace["interval_mean"],
                "interval_max_settled": pace["interval_max_settled"], "rescheduled": pace["rescheduled"]}

    at_requested = paced(args.period)
    tries = [at_requested]
    for period in schedule(args.period, capacity, at_requested["held"]):
        tries.append(paced(period))
        if tries[-1]["held"] != at_requested["held"]:
            break
    shortest = min((t["period"] for t in tries if t["held"]), default=None)
    return {"robots": robots, "agvs": agvs, "pickers": pickers, "lockstep_ticks_per_s": round(capacity, 1),
            "cpu_ms_per_tick": {k: round(v, 3) for k, v in cpu.items()},
            "cpu_ms_per_robot_tick": round(cpu["total"] / robots, 3) if cpu.get("total") else None,
            "agent_uss_mib": round(uss, 1) if uss is not None else None,
            "shortest_period_held": shortest, "holds_requested": at_requested["held"], "requested": at_requested,
            "tries": tries, "loadavg": load_average()}


def run(args: argparse.Namespace) -> int:
    sizes = _parse_sizes(args.sizes)
    if args.ticks < 30:
        raise ValueError(f"ticks: at least 30 (the first {SETTLE_TICKS} settle), got {args.ticks}")
    if not 0 < args.period <= 60:
        raise ValueError(f"period: seconds in (0, 60], got {args.period}")
    rows = []
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="morph-bench-fleet-") as tmp:
        for robots in sizes:
            row = measure_size(robots, args, Path(tmp))
            rows.append(row)
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                print(_line(row, args.period), flush=True)
    where = knee(rows)
    if args.json:
        print(json.dumps({"knee": where, "period": args.period, "cores": os.cpu_count(),
                          "wall_seconds": round(time.monotonic() - started, 1)}))
        return 0
    _table(rows, args)
    print("knee: " + (f"{where} robots is the smallest fleet that does not hold {args.period:g} s"
                       if where is not None else f"every fleet measured holds {args.period:g} s")
          + f" ({os.cpu_count()} cores; {time.monotonic() - started:.0f} s in all)")
    return 0


def _line(row: dict, period: float) -> str:
    req = row["requested"]
    return (f"{row['robots']} robots ({row['agvs']}+{row['pickers']}): lockstep {row['lockstep_ticks_per_s']:.0f} "
            f"ticks/s, {row['cpu_ms_per_tick'].get('total', float('nan')):.1f} ms CPU per tick; at {period:g} s mean "
            f"{req['interval_mean']:.3f} s, settled max {req['interval_max_settled']:.3f} s, rescheduled "
            f"{req['rescheduled']}: {'held' if req['held'] else 'not held'} (load {row['loadavg']})")


def _table(rows: list[dict], args: argparse.Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"fleets in the extralarge warehouse, {args.policy}, {args.ticks} ticks a run")
    for col in ("robots", "lockstep ticks/s", "CPU ms/tick", "sim", "monitor", "supervisor", "AGV each",
                "picker each", "per robot", "agent USS MiB", "shortest period held", f"holds {args.period:g} s"):
        table.add_column(col, justify="right")
    for r in rows:
        def ms(role: str, cpu: dict = r["cpu_ms_per_tick"]) -> str:
            return f"{cpu[role]:.2f}" if role in cpu else "–"

        table.add_row(f"{r['robots']} ({r['agvs']}+{r['pickers']})", f"{r['lockstep_ticks_per_s']:.0f}",
                      ms("total"), ms("sim"), ms("monitor"), ms("supervisor"), ms("agv"), ms("picker"),
                      f"{r['cpu_ms_per_robot_tick']:.2f}" if r["cpu_ms_per_robot_tick"] else "–",
                      f"{r['agent_uss_mib']:.1f}" if r["agent_uss_mib"] else "–",
                      f"{r['shortest_period_held']:g} s" if r["shortest_period_held"] else "none of those tried",
                      "yes" if r["holds_requested"] else "no")
    console = Console(width=None if Console().is_terminal else 160)
    console.print(table)
