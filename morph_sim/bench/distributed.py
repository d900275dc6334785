"""``morph-sim bench distributed``: the distributed run's tick rate against the raw Zenoh barrier, same process count.

Measured in one invocation, back to back on the same machine:

1. a zero-fault ``morph-sim up`` run (sim + one OS process per agent + monitor, over Zenoh) of the chosen scale and
   policy; its rate is the sim's tick loop (``run.finished``: steps / wall seconds between tick 0 and the end, process
   start-up excluded);
2. the raw lock-step barrier (``services.bus.barrier_bench``, plain zenoh-python callbacks, recommended
   settings) with the same number of agent processes.

The ratio says how much of the transport's ceiling the protocol, the warehouse and the agents' plasticity leave. The
run's CPU milliseconds per tick of each process role (:class:`CpuMeter`) and the load average are printed too: on a
shared machine the rates move with the load, CPU per tick much less (docs/services.md, Performance).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import threading
import time
from pathlib import Path

NAME = "distributed"
HELP = "distributed tick rate (up, one process per agent) vs the raw Zenoh barrier for the same process count"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import field_choices

    parser.add_argument("--scale", default="medium", choices=field_choices("scale"),
                        help="warehouse size (default medium: 12 AGVs + 6 pickers)")
    parser.add_argument("--policy", default="morph", choices=field_choices("policy"),
                        help="coordination policy (default morph)")
    parser.add_argument("--preset", default="reference", choices=field_choices("preset"),
                        help="MORPH preset (default reference)")
    parser.add_argument("--agvs", type=int, default=None, help="AGV count (default: the scale's)")
    parser.add_argument("--pickers", type=int, default=None, help="picker count (default: the scale's)")
    parser.add_argument("--steps", type=int, default=800, help="ticks of the distributed run (default 800)")
    parser.add_argument("--barrier-ticks", type=int, default=2000, help="ticks of the barrier run (default 2000)")
    parser.add_argument("--seed", type=int, default=42)
    parser.add_argument("--network", default=None, metavar="PROFILE",
                        help="a network profile (docs/faults.md); one with rate-limited queues (congested) adds the "
                             "air process, whose CPU per tick is its own row")
    parser.add_argument("--output-dir", default=None, help="keep the run record here (default: a temporary dir)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--code", default=None, metavar="DIR",
                        help="measure the code of this git checkout (its working tree) instead of the installed one")
    parser.add_argument("--against", default=None, metavar="DIR",
                        help="before/after: measure the code of this git checkout and the installed one "
                             "alternately, --rounds times each, and print both with their ratio")
    parser.add_argument("--rounds", type=int, default=1, help="with --against: measurements of each (default 1)")
    parser.add_argument("--insecure", action="store_true",
                        help="an open endpoint (no credentials, no access control), to measure the run without "
                             "security's cost; with --against, a checkout older than security runs as it is")


CPU_SAMPLE_S = 0.05  # seconds between CPU samples of the run's processes, at least
CPU_WARMUP_TICKS = 20  # the CPU window opens at this tick (start-up and the first ticks excluded)
CPU_DUTY = 50  # the CPU meter reads at most 1/this of its time: a round reads every process (~30 µs each)
READINGS_MAX = 4096  # readings a meter keeps per series: beyond, every other one goes (the series keeps its span)


class Sampler:
    """A thread that takes a reading (:meth:`reading`, which returns the seconds to wait before the next) from
    :meth:`start` until :meth:`stop`, of the run's processes through ``psutil`` handles it keeps."""

    name = "sampler"

    def __init__(self) -> None:
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._processes: dict[int, object] = {}  # pid -> psutil.Process

    def reading(self) -> float:
        raise NotImplementedError

    def process(self, pid: int):
        """The ``psutil`` handle of ``pid``, one per process: making one reads the process's start time, a cost the
        supervisor's own figure would carry on every reading (psutil.Error where there is no such process)."""
        import psutil

        handle = self._processes.get(pid)
        if handle is None:
            handle = self._processes[pid] = psutil.Process(pid)
        return handle

    @staticmethod
    def keep(series: list, reading) -> None:
        """Append ``reading`` to ``series``, keeping at most ``READINGS_MAX`` of them over the whole span."""
        series.append(reading)
        if len(series) > READINGS_MAX:
            series[:] = [*series[:-1:2], series[-1]]

    def start(self) -> None:
        import psutil  # noqa: F401  (imported here, not in the first reading: its import is no reading's cost)

        def read() -> None:
            while not self._done.wait(self.reading()):
                pass

        self._thread = threading.Thread(target=read, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()


def tick_points(tick_clock: list | None) -> list[tuple[int, float]]:
    """The sim's run.finished ``tick_clock`` ([[tick, monotonic seconds], ...]) as (tick, seconds) in tick order."""
    return sorted((int(t), float(at)) for t, at in tick_clock or ())


def tick_time(points: list[tuple[int, float]], tick: float) -> float:
    """When tick ``tick`` started (monotonic seconds), interpolated between the tick clock's ``points``."""
    import numpy as np

    return float(np.interp(tick, [t for t, _ in points], [at for _, at in points]))


class CpuMeter(Sampler):
    """CPU seconds per tick of every process of a distributed run, by role (sim, monitor, agv, picker, supervisor).

    A thread of its own (:meth:`start`, :meth:`stop`) samples each process's CPU time (user + system, from
    ``psutil``) every ``sample_s`` seconds, or less often where a round of readings costs more than a
    ``CPU_DUTY``-th of that (at 128 robots the meter would otherwise take a quarter of a core from the machine it
    measures), each reading stamped with the host's monotonic clock. The window is placed by the sim's own tick
    clock (its run.finished ``tick_clock``: when ticks started, on the same clock): from the start of tick
    ``CPU_WARMUP_TICKS`` to the start of the final tick. Neither the samples nor the window depend on when the ticks
    reach the supervisor: on a loaded machine they reach it late and in bursts, and a window placed by its progress
    measured nothing, or no time at all.

    Each process's CPU at the window's edges is interpolated between the samples on either side. A process must have
    been sampled before the window opened; one that exits before the window closes (the run's processes may leave
    before the last sample) is measured up to its last sample, with the ticks up to then. A process restarted in the
    run (its name seen with two pids) is left out: neither of its lives spans the window. CPU time is what a tick
    costs the machine, and unlike the tick rate it barely depends on what else runs on the cores.
    """

    name = "cpu-meter"

    def __init__(self, supervisor, n_agvs: int, sample_s: float = CPU_SAMPLE_S):
        super().__init__()
        self.sup = supervisor
        self.n_agvs = n_agvs
        self.sample_s = sample_s
        # "name:pid" -> [(monotonic seconds, CPU seconds), ...] in time order
        self.series: dict[str, list[tuple[float, float]]] = {}

    def _role(self, name: str) -> str:
        if name.startswith("agent-"):
            return "agv" if int(name.split("-", 1)[1]) < self.n_agvs else "picker"
        return name

    def _sample(self) -> dict[str, tuple[float, float]]:
        """One reading of every live process: "name:pid" -> (when, CPU seconds), each stamped as it is read."""
        import psutil

        out: dict[str, tuple[float, float]] = {}
        pids = [(name, child.pid) for name, child in list(self.sup.children.items()) if child.alive()]
        for name, pid in [*pids, ("supervisor", os.getpid())]:
            try:
                times = self.process(pid).cpu_times()
            except psutil.Error:
                continue
            out[f"{name}:{pid}"] = (time.monotonic(), times.user + times.system)
        return out

    def record(self, sample: dict[str, tuple[float, float]]) -> None:
        """Take one reading into the processes' series."""
        for key, point in sample.items():
            self.keep(self.series.setdefault(key, []), point)

    def reading(self) -> float:
        began = time.thread_time()  # CPU, not wall time: a loaded machine stretches the round, not its cost
        self.record(self._sample())
        return max(self.sample_s, CPU_DUTY * (time.thread_time() - began))

    def per_tick_ms(self, tick_clock: list | None) -> dict[str, float]:
        """Milliseconds of CPU per tick over the window that ``tick_clock`` (the sim's [[tick, monotonic seconds],
        ...]) places: per process role (agents: the mean over that role's processes) and total."""
        import numpy as np

        points = tick_points(tick_clock)
        if len(points) < 2:
            return {}
        ticks, times = np.array([p[0] for p in points], float), np.array([p[1] for p in points])
        first_tick, last_tick = float(CPU_WARMUP_TICKS), ticks[-1]
        if last_tick <= first_tick or ticks[0] > first_tick:
            return {}
        opens = tick_time(points, first_tick)
        closes = times[-1]
        pids: dict[str, int] = {}
        for key in self.series:
            name = key.rsplit(":", 1)[0]
            pids[name] = pids.get(name, 0) + 1
        sums: dict[str, list[float]] = {}
        for key, series in self.series.items():
            name = key.rsplit(":", 1)[0]
            at, cpu = np.array([p[0] for p in series]), np.array([p[1] for p in series])
            end = min(closes, at[-1])
            if pids[name] > 1 or at[0] > opens or end <= opens:
                continue
            span = float(np.interp(end, times, ticks)) - first_tick
            if span <= 0:
                continue
            used = float(np.interp(end, at, cpu)) - float(np.interp(opens, at, cpu))
            sums.setdefault(self._role(name), []).append(1e3 * used / span)
        if not sums:
            return {}
        out = {role: sum(v) / len(v) for role, v in sorted(sums.items())}
        out["total"] = sum(sum(v) for v in sums.values())
        return out


def load_average() -> str:
    """The 1/5/15-minute load averages: the tick rate on a shared machine means little without them."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def distributed_rate(config, insecure: bool = False) -> dict:
    """Run ``config`` with the supervisor; the sim's tick-loop rate from the record's run.finished event, and the
    CPU per tick of every process (:class:`CpuMeter`)."""
    from services.supervisor.launcher import Supervisor

    started = time.monotonic()
    supervisor = Supervisor(config, insecure=insecure)
    meter = CpuMeter(supervisor, config.n_agvs)
    meter.start()
    try:
        code = asyncio.run(supervisor.run())
    finally:
        meter.stop()
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
            "total_wall_s": time.monotonic() - started, "cpu_ms_per_tick": meter.per_tick_ms(finished.get("tick_clock"))}


def checkout(path: str, flag: str) -> Path:
    """A git checkout of morph-sim to measure (ValueError naming ``flag`` if it is not one)."""
    root = Path(path).expanduser().resolve()
    if not (root / "morph_sim" / "__init__.py").is_file():
        raise ValueError(f"{flag}: {root} is not a morph-sim checkout (no morph_sim/ there)")
    return root


def packages_of(root: Path | None) -> tuple[str, ...]:
    """The top-level packages of checkout ``root`` whose origin a measurement checks: ``morph_sim`` and, from the
    layout with the running system at the top, ``services`` (older checkouts hold it inside ``morph_sim``); the
    installed code (None) has both."""
    if root is not None and not (root / "services" / "__init__.py").is_file():
        return ("morph_sim",)
    return ("morph_sim", "services")


def revision(root: Path) -> str:
    """The checkout's git revision, ``+dirty`` with uncommitted changes."""
    import subprocess

    try:
        rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "(no git revision)"
    return rev + ("+dirty" if dirty else "")


def code_env(root: Path | None) -> dict[str, str]:
    """The environment of a measurement of checkout ``root`` (None: the installed code): the checkout first on the
    import path, which every process of the run inherits."""
    env = dict(os.environ)
    if root is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(root), *filter(None, [env.get("PYTHONPATH")])])
    return env


def code_cwd(root: Path | None) -> str:
    """The working directory of a measurement: the checkout itself, or (installed code) one holding no code, since
    ``python -m``/``-c`` put the working directory first on the import path."""
    return str(root) if root is not None else tempfile.gettempdir()


def code_of(env: dict[str, str], cwd: str, packages: tuple[str, ...] = ("morph_sim", "services")) -> Path | None:
    """The checkout whose ``packages`` a process started with ``env`` in ``cwd`` imports (None: more than one)."""
    import subprocess
    import sys

    show = "; ".join(f"import {name}; print({name}.__file__)" for name in packages)
    where = subprocess.run(
        [sys.executable, "-c", show],
        capture_output=True, text=True, env=env, cwd=cwd, timeout=60)
    if where.returncode != 0:
        return None
    roots = {Path(line).resolve().parents[1] for line in where.stdout.split()}
    return roots.pop() if len(roots) == 1 else None


def _knows_insecure(env: dict[str, str], cwd: str) -> bool:
    """Whether the code that ``env`` imports has ``bench distributed --insecure`` (a checkout from before the
    endpoint was secured has nothing to turn off)."""
    import subprocess
    import sys

    shown = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "distributed", "--help"],
                           capture_output=True, text=True, env=env, cwd=cwd, timeout=120)
    return "--insecure" in shown.stdout


def measure_code(args: argparse.Namespace, root: Path | None) -> dict:
    """One measurement in a fresh process: the code of checkout ``root`` (first on the import path of the bench and
    of every process of its run), or the installed code (None). Checks which code ran."""
    import subprocess
    import sys

    env, cwd = code_env(root), code_cwd(root)
    code = code_of(env, cwd, packages_of(root))
    if root is not None and code != root:
        raise RuntimeError(f"code: the measurement would import {code}, not {root}")
    argv = [sys.executable, "-m", "morph_sim.cli", "bench", "distributed", "--json", "--scale", args.scale,
            "--policy", args.policy, "--preset", args.preset, "--steps", str(args.steps),
            "--barrier-ticks", str(args.barrier_ticks), "--seed", str(args.seed),
            *(["--agvs", str(args.agvs)] if args.agvs is not None else []),
            *(["--pickers", str(args.pickers)] if args.pickers is not None else []),
            *(["--network", args.network] if args.network else [])]
    if args.insecure and _knows_insecure(env, cwd):
        argv.append("--insecure")
    done = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=cwd, timeout=3600)
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"the bench of {code} ended with status {done.returncode}: {done.stderr[-2000:]}")
    result = json.loads(lines[-1])
    result["code"] = str(code)
    result["revision"] = revision(code) if code is not None else "(no git revision)"
    return result


def _line(label: str, r: dict) -> str:
    cpu = r.get("cpu_ms_per_tick", {}).get("total")
    return (f"{label} {r['revision']}: {r['distributed_ticks_per_s']:.0f} ticks/s, "
            + (f"{cpu:.1f} ms CPU per tick, " if cpu is not None else "")
            + f"{r['ratio']:.0%} of the raw barrier ({r['barrier_ticks_per_s']:.0f} ticks/s), load {r['loadavg']}")


def before_after(args: argparse.Namespace) -> int:
    """``--against DIR``: the checkout (before) and the installed code (after), alternately, same flags."""
    import statistics

    before_root = checkout(args.against, "--against")
    runs: dict[str, list[dict]] = {"before": [], "after": []}
    for i in range(args.rounds):
        for label, root in (("before", before_root), ("after", None)):
            r = measure_code(args, root)
            runs[label].append(r)
            if not args.json:
                print(f"round {i + 1}/{args.rounds} " + _line(label, r), flush=True)

    summary = summarize(runs)
    if args.json:
        print(json.dumps({"summary": summary, "runs": runs}))
        return 0
    print(f"medians over {args.rounds} round(s), {args.scale} {args.policy}:")
    for label in ("before", "after"):
        m = summary[label]
        print(f"  {label} {m['revision']}: {m['ticks_per_s']:.0f} ticks/s, "
              + (f"{m['cpu_ms_per_tick']:.1f} ms CPU per tick, " if m["cpu_ms_per_tick"] else "")
              + f"{m['ratio_to_barrier']:.0%} of the raw barrier")
    ratio = summary["after_over_before"]
    print(f"  after / before: {ratio['ticks_per_s']:.2f}× ticks/s"
          + (f", {ratio['cpu_ms_per_tick']:.2f}× CPU per tick" if ratio["cpu_ms_per_tick"] else ""))
    pairs = summary["pairs"]
    if len(pairs["ticks_per_s"]) > 1:
        def spread(values: list[float]) -> str:
            return (" ".join(f"{v:.2f}" for v in values)
                    + f"× (median {statistics.median(values):.2f}×)")
        print("  round by round (each pair measured back to back): " + spread(pairs["ticks_per_s"]) + " ticks/s"
              + (", " + spread(pairs["cpu_ms_per_tick"]) + " CPU per tick" if pairs["cpu_ms_per_tick"] else ""))
    if summary["by_role"]:
        print("  CPU ms per tick by role, medians: " + ", ".join(
            f"{role} {m['before']:.2f} → {m['after']:.2f}" for role, m in summary["by_role"].items()))
    return 0


def summarize(runs: dict[str, list[dict]]) -> dict:
    """The before/after summary of alternating rounds: each side's medians and their ratio, the ratio round by
    round (a pair ran back to back, so a machine whose speed drifts over minutes moves both of it), and each role's
    median CPU per tick."""
    import statistics

    def cpu(r: dict, role: str = "total") -> float | None:
        return r.get("cpu_ms_per_tick", {}).get(role)

    def median(values: list[float | None]) -> float | None:
        kept = [v for v in values if v is not None]
        return statistics.median(kept) if kept else None

    summary: dict = {
        label: {"revision": runs[label][0]["revision"],
                "ticks_per_s": median([r["distributed_ticks_per_s"] for r in runs[label]]),
                "cpu_ms_per_tick": median([cpu(r) for r in runs[label]]),
                "ratio_to_barrier": median([r["ratio"] for r in runs[label]])}
        for label in ("before", "after")}
    b, a = summary["before"], summary["after"]
    summary["after_over_before"] = {
        "ticks_per_s": a["ticks_per_s"] / b["ticks_per_s"] if b["ticks_per_s"] else None,
        "cpu_ms_per_tick": (a["cpu_ms_per_tick"] / b["cpu_ms_per_tick"]
                            if a["cpu_ms_per_tick"] and b["cpu_ms_per_tick"] else None)}
    rounds = list(zip(runs["before"], runs["after"]))
    summary["pairs"] = {
        "ticks_per_s": [ra["distributed_ticks_per_s"] / rb["distributed_ticks_per_s"] for rb, ra in rounds
                        if rb["distributed_ticks_per_s"]],
        "cpu_ms_per_tick": [cpu(ra) / cpu(rb) for rb, ra in rounds if cpu(ra) and cpu(rb)]}
    roles = sorted({role for r in runs["before"] + runs["after"] for role in r.get("cpu_ms_per_tick", {})} - {"total"})
    by_role = {}
    for role in roles:
        before, after = median([cpu(r, role) for r in runs["before"]]), median([cpu(r, role) for r in runs["after"]])
        if before is not None and after is not None:
            by_role[role] = {"before": before, "after": after}
    summary["by_role"] = by_role
    return summary


def run(args: argparse.Namespace) -> int:
    if args.rounds < 1:
        raise ValueError(f"--rounds: {args.rounds} must be at least 1")
    if args.against is not None:
        return before_after(args)
    if args.code is not None:
        r = measure_code(args, checkout(args.code, "--code"))
        print(json.dumps(r) if args.json else _line("code", r))
        return 0
    return measure(args)


def measure(args: argparse.Namespace) -> int:
    from services.bus.barrier_bench import run_barrier
    from services.runconfig import RunConfig

    with tempfile.TemporaryDirectory(prefix="morph-bench-") as tmp:
        out = Path(args.output_dir) if args.output_dir else Path(tmp)
        config = RunConfig.coerce(dict(
            run_id=f"bench-{args.scale}-{args.policy}", scale=args.scale, policy=args.policy, preset=args.preset,
            agvs=args.agvs, pickers=args.pickers, steps=args.steps, seed=args.seed, output_dir=out,
            network=args.network,
            state_every=max(10, args.steps // 8), snapshot_every=max(10, args.steps // 8) * 4))
        dist = distributed_rate(config, insecure=args.insecure)
    n = config.n_agents
    barrier = run_barrier(n, args.barrier_ticks, 100, mode="raw")
    ratio = dist["ticks_per_s"] / barrier.ticks_per_s if barrier.ticks_per_s else float("nan")
    result = {"scale": args.scale, "policy": args.policy, "preset": args.preset, "agents": n,
              "distributed_ticks_per_s": round(dist["ticks_per_s"], 1), "distributed_ticks": dist["ticks"],
              "barrier_ticks_per_s": round(barrier.ticks_per_s, 1), "barrier_ticks": barrier.ticks,
              "ratio": round(ratio, 3),
              "cpu_ms_per_tick": {k: round(v, 3) for k, v in dist["cpu_ms_per_tick"].items()},
              "loadavg": load_average()}
    if args.json:
        print(json.dumps(result))
    else:
        label = args.policy + (f"/{args.preset}" if args.policy == "morph" else "") + (
            f", network {args.network}" if args.network else "")
        print(f"distributed {args.scale} ({n} agent processes, {label}): {dist['ticks_per_s']:.0f} ticks/s "
              f"over {dist['ticks']} ticks")
        cpu = dist["cpu_ms_per_tick"]
        if cpu:
            print("  CPU ms per tick: " + ", ".join(
                f"{role} {v:.2f}" + (" each" if role in ("agv", "picker") else "") for role, v in cpu.items()))
        print(f"raw Zenoh barrier, {n} agent processes: {barrier.ticks_per_s:.0f} ticks/s "
              f"(p50 {barrier.p50_ms:.2f} ms, p99 {barrier.p99_ms:.2f} ms)")
        print(f"ratio distributed / barrier: {ratio:.0%}  (load average {result['loadavg']})")
    return 0
