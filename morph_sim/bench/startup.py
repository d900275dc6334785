"""``morph-sim bench startup``: what starting a distributed run costs — CPU seconds and wall time to the first tick.

Each round runs ``morph-sim up`` (sim + one OS process per agent + monitor, secured endpoint, as a user starts it) in
a fresh process and measures it from outside, so the same measurement applies to any checkout (``--against``):

* **CPU-s of the whole run**: user + system time of ``up`` and every process it started, from the kernel's account
  of reaped children (``RUSAGE_CHILDREN``); a short run (``--steps 20``) is mostly start-up;
* **CPU-s at the first tick, per process role**: every process of the run is sampled (``psutil``) while it starts;
  each one's last sample before the sim's first tick (the record's ``run.started`` wall time) is its start-up cost;
* **wall seconds to the first tick**: from launching ``up`` to ``run.started``.

On a shared machine the wall time moves with the load; CPU seconds much less, so both are printed with the load
average. ``--against DIR`` measures another checkout and this one alternately (before/after).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NAME = "startup"
HELP = "CPU seconds and wall time a distributed run (up) costs before its first tick, per process role"

SAMPLE_S = 0.02  # seconds between CPU samples of the run's processes while they start


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import field_choices

    parser.add_argument("--scale", default="tiny", choices=field_choices("scale"),
                        help="warehouse size (default tiny: 5 AGVs + 3 pickers)")
    parser.add_argument("--steps", type=int, default=20, help="ticks of each run (default 20: mostly start-up)")
    parser.add_argument("--rounds", type=int, default=3, help="runs measured (of each checkout with --against)")
    parser.add_argument("--against", default=None, metavar="DIR",
                        help="before/after: the code of this git checkout and the installed one, alternately")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _role(cmdline: list[str]) -> str | None:
    from services.supervisor.graph import role_of

    if "services.supervisor.forkserver" in cmdline:  # the interpreter the run's processes are forked from
        return "fork-server"
    return role_of(cmdline)


def measure_up(scale: str, steps: int, env: dict[str, str], cwd: str) -> dict:
    """One ``morph-sim up`` run, measured from outside (see the module's docstring)."""
    import psutil

    with tempfile.TemporaryDirectory(prefix="morph-bench-startup-") as tmp:
        run_id = "bench-startup"
        argv = [sys.executable, "-m", "morph_sim.cli", "up", "--scale", scale, "--steps", str(steps), "--quiet",
                "--output-dir", tmp, "--run-id", run_id]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        launched = time.time()
        samples: dict[int, list[tuple[float, float]]] = {}  # pid -> [(wall time, CPU s)]
        roles: dict[int, str] = {}
        with open(Path(tmp) / "up.log", "wb") as log:
            up = subprocess.Popen(argv, env=env, cwd=cwd, stdin=subprocess.DEVNULL, stdout=log, stderr=log)
            try:
                deadline = time.monotonic() + 300
                while up.poll() is None:
                    if time.monotonic() > deadline:
                        raise RuntimeError("up did not end within 300 s")
                    try:
                        procs = [psutil.Process(up.pid), *psutil.Process(up.pid).children(recursive=True)]
                    except psutil.Error:
                        procs = []
                    for p in procs:
                        try:
                            # a child just forked (by exec or from the fork server) shows its parent's command
                            # line: look again until it has its own
                            if roles.get(p.pid) not in ("supervisor", "sim", "agent", "monitor"):
                                roles[p.pid] = "supervisor" if p.pid == up.pid else (_role(p.cmdline()) or "other")
                            cpu = p.cpu_times()
                            samples.setdefault(p.pid, []).append((time.time(), cpu.user + cpu.system))
                        except psutil.Error:
                            continue
                    time.sleep(SAMPLE_S)
            finally:
                if up.poll() is None:
                    up.kill()
                up.wait()
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if up.returncode != 0:
            raise RuntimeError(f"up ended with status {up.returncode}: "
                               f"{(Path(tmp) / 'up.log').read_text(errors='replace')[-2000:]}")
        started = None
        for line in (Path(tmp) / run_id / "events.jsonl").read_text().splitlines():
            event = json.loads(line)
            if event.get("kind") == "run.started":
                started = float(event["wall_time"])
                break
        if started is None:
            raise RuntimeError("the record has no run.started event")
    by_role: dict[str, list[float]] = {}
    for pid, series in samples.items():
        before_tick = [cpu for at, cpu in series if at <= started]
        if before_tick:
            by_role.setdefault(roles[pid], []).append(before_tick[-1])
    first_tick = {role: round(sum(v), 3) for role, v in sorted(by_role.items())}
    if "agent" in by_role:
        first_tick["agent_each"] = round(statistics.mean(by_role["agent"]), 3)
    first_tick["total"] = round(sum(sum(v) for v in by_role.values()), 3)
    return {"cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 3),
            "first_tick_wall_s": round(started - launched, 3), "first_tick_cpu_s": first_tick,
            "loadavg": " ".join(f"{x:.2f}" for x in os.getloadavg())}


def _line(label: str, r: dict) -> str:
    c = r["first_tick_cpu_s"]
    roles = ", ".join(f"{k} {v:.2f}" for k, v in c.items() if k not in ("total", "agent"))
    return (f"{label}: {r['cpu_s']:.2f} CPU-s in all, {c['total']:.2f} CPU-s before the first tick ({roles}), "
            f"first tick after {r['first_tick_wall_s']:.2f} s wall, load {r['loadavg']}")


def run(args: argparse.Namespace) -> int:
    from morph_sim.bench.distributed import checkout, code_cwd, code_env, code_of, packages_of, revision

    if args.rounds < 1:
        raise ValueError(f"--rounds: {args.rounds} must be at least 1")
    if args.steps < 1:
        raise ValueError(f"--steps: {args.steps} must be at least 1")
    checkouts: list[tuple[str, Path | None]] = [("after", None)]
    if args.against is not None:
        checkouts.insert(0, ("before", checkout(args.against, "--against")))
    runs: dict[str, list[dict]] = {label: [] for label, _ in checkouts}
    revisions: dict[str, str] = {}
    for i in range(args.rounds):
        for label, root in checkouts:  # alternately, so a change of load hits both alike
            env, cwd = code_env(root), code_cwd(root)
            code = code_of(env, cwd, packages_of(root))
            if root is not None and code != root:
                raise RuntimeError(f"code: the measurement would import {code}, not {root}")
            revisions[label] = revision(code) if code is not None else "(no git revision)"
            r = measure_up(args.scale, args.steps, env, cwd)
            runs[label].append(r)
            if not args.json:
                name = label if args.against is not None else "up"
                print(f"round {i + 1}/{args.rounds} " + _line(f"{name} {revisions[label]}", r), flush=True)
    summary = {label: {"revision": revisions[label],
                       "cpu_s": statistics.median(r["cpu_s"] for r in rs),
                       "first_tick_cpu_s": statistics.median(r["first_tick_cpu_s"]["total"] for r in rs),
                       "first_tick_wall_s": statistics.median(r["first_tick_wall_s"] for r in rs)}
               for label, rs in runs.items()}
    if args.json:
        print(json.dumps({"scale": args.scale, "steps": args.steps, "summary": summary, "runs": runs}))
        return 0
    print(f"medians over {args.rounds} round(s), up --scale {args.scale} --steps {args.steps}:")
    for label, m in summary.items():
        print(f"  {label} {m['revision']}: {m['cpu_s']:.2f} CPU-s in all, {m['first_tick_cpu_s']:.2f} CPU-s before "
              f"the first tick, first tick after {m['first_tick_wall_s']:.2f} s wall")
    if "before" in summary:
        b, a = summary["before"], summary["after"]
        print(f"  after / before: {a['cpu_s'] / b['cpu_s']:.2f}× CPU-s in all, "
              f"{a['first_tick_cpu_s'] / b['first_tick_cpu_s']:.2f}× CPU-s before the first tick, "
              f"{a['first_tick_wall_s'] / b['first_tick_wall_s']:.2f}× wall to the first tick")
    return 0
