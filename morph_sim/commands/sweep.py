"""``morph-sim sweep``: any grid of RunConfig fields and fault parameters × seeds (morph_sim/lab/sweep.py)."""

from __future__ import annotations

import argparse
import sys

NAME = "sweep"
HELP = "sweep any RunConfig field and fault parameter over a grid × seeds; tidy table, resumable, local or Dask"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", nargs="?", help="a sweep TOML file ([grid], [base], seeds, engine; docs/sweep.md)")
    parser.add_argument("--grid", action="append", default=[], metavar="FIELD=V1,V2",
                        help="an axis: a RunConfig field (policy, scale, preset, ablation, radius, steps, …) or a "
                             "fault parameter (faults.loss, faults.latency.delay, …); repeat for more axes")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="fixed",
                        help="a field fixed for every episode, e.g. --set steps=400")
    parser.add_argument("--seeds", default=None, help="seeds of every condition: 1-20, 1,2,5 (default 1)")
    parser.add_argument("--engine", choices=("lab", "services"), default=None,
                        help="lab: the pure core (fast; default); services: the services over the in-process bus")
    parser.add_argument("--baseline", action="append", default=[], metavar="AXIS=VALUE",
                        help="what each condition is compared with (default policy=morph when swept, else the "
                             "first axis' first value)")
    parser.add_argument("--executor", choices=("local", "dask"), default=None,
                        help="local processes (default) or a Dask cluster (needs 'morph-sim[cluster]')")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://HOST:8786")
    parser.add_argument("--jobs", type=int, default=None, help="local worker processes (default 2)")
    parser.add_argument("--out", default=None, help="parent directory of the sweep record (default runs)")
    parser.add_argument("--run-id", default=None,
                        help="the sweep's record name; give the same one to resume an interrupted sweep")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _pairs(items: list[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        k, eq, v = item.partition("=")
        if not eq or not k.strip():
            raise ValueError(f"{what}: {item!r} is not like field=value")
        out[k.strip()] = v
    return out


def run(args: argparse.Namespace) -> int:
    from morph_sim.lab.executors import check_jobs
    from morph_sim.lab.sweep import (
        SweepPlan,
        comparison_markdown,
        default_sweep_id,
        parse_grid_arg,
        plan_from_toml,
        run_sweep,
    )
    from services.inputs import output_dir

    file_run: dict = {}
    if args.file:
        if args.grid or args.fixed or args.seeds or args.engine or args.baseline:
            raise ValueError("sweep: give either a sweep file or --grid/--set/--seeds/--engine/--baseline")
        plan, file_run = plan_from_toml(args.file)
    else:
        if not args.grid:
            raise ValueError("grid: give at least one --grid FIELD=V1,V2 (or a sweep file)")
        plan = SweepPlan.build(grid=[parse_grid_arg(g) for g in args.grid], seeds=args.seeds or "1",
                               base=_pairs(args.fixed, "set"), engine=args.engine or "lab",
                               baseline=_pairs(args.baseline, "baseline") or None)
    executor = args.executor or file_run.get("executor", "local")
    jobs = check_jobs(args.jobs if args.jobs is not None else int(file_run.get("jobs", 2)))
    scheduler = args.scheduler or file_run.get("scheduler")
    if executor == "dask" and not scheduler:
        raise ValueError("scheduler: --executor dask needs --scheduler tcp://HOST:8786")
    out = output_dir(args.out or file_run.get("out", "runs"), "out")
    n = len(plan.episodes())
    print(f"sweep: {len(plan.conditions())} conditions × {len(plan.seeds)} seeds = {n} episodes "
          f"({plan.engine} engine, {executor} executor)", file=sys.stderr)
    from morph_sim.lab.sweep import count_done

    run_id = args.run_id or file_run.get("run_id") or default_sweep_id()
    try:
        result = run_sweep(plan, out, run_id, executor=executor, jobs=jobs, scheduler=scheduler,
                           progress=not args.no_progress, argv=sys.argv)
    except ImportError as exc:  # the dask executor without the [cluster] extra: one line saying how to get it
        print(f"morph-sim sweep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sweep {run_id}: interrupted with {count_done(out / run_id)} of {n} episodes in the record; the same "
              f"command with --run-id {run_id} resumes it", file=sys.stderr)
        return 130
    print(comparison_markdown(plan, result.comparison), end="")
    names = ", ".join(p.name for p in result.files.values())
    print(f"sweep {result.dir.name}: {result.ran} episodes run, {result.skipped} already in the record, "
          f"{result.wall_s:.1f} s; {result.dir}/ ({names})")
    return 0
