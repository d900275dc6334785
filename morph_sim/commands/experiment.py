"""``morph-sim experiment scale|ablation|shift|emergent|faults|network|audit``: the in-process lab.

scale/ablation: conditions × scales × seeds (the reference's study); shift: the paper's six-phase demand-shift
experiment with recovery times; emergent: W snapshots, Spearman, link lifetimes, η and λ₂ over long episodes;
faults: the loss/latency sweep (morph_sim/lab/faults_experiment.py); network: the policies under the named network
profiles (morph_sim/lab/network_study.py); audit: the paper preset's departures from the
paper, each measured (morph_sim/lab/audit.py; --conditions picks variants, default scales small,medium and seeds
11..15). A flag the chosen study cannot honour is refused with a one-line message naming it (``FLAGS``), never
silently ignored.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pydantic import ValidationError

from schemas.errors import invalid

NAME = "experiment"
HELP = ("run an in-process study: scale, ablation, shift, emergent, faults, network or audit (parallel, with run "
        "records)")


def _csv(value: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in value.split(",") if v.strip())


def _radii(value: str) -> dict[str, int]:
    out = {}
    for part in _csv(value):
        if "=" not in part:
            raise ValueError(f"radius: expected scale=r pairs like tiny=10,medium=6, got {part!r}")
        k, v = part.split("=", 1)
        try:
            out[k.strip()] = int(v)
        except ValueError:
            raise ValueError(f"radius: {v!r} is not an integer") from None
    return out


def add_arguments(parser) -> None:
    # Every optional flag defaults to None (or False), so a flag the user gave is known and a study that cannot
    # honour it refuses it (FLAGS below) instead of running something else than asked.
    parser.add_argument("suite", choices=SUITES, help="which study: " + ", ".join(SUITES) + ". faults' default grid: "
                        "four scales × latency 0–10 ticks and Bernoulli/Gilbert–Elliott loss 0–50 %% on dispatch, "
                        "fleet broadcast and both × five policies × seeds 1–10, T = 800 (2,600 episodes a scale, "
                        "≈ 28 min of two idle cores in all). network's default grid: four scales × five profiles × six "
                        "policies × seeds 301–310, T = 800 (tiny, small), 600 (medium), 400 (large) (1,200 episodes, "
                        "measured: 2 min 54 s on two idle cores)")
    parser.add_argument("--preset", default=None, help="scale/ablation: MORPH preset reference (scale default) or "
                        "paper (ablation default), or a preset TOML path; emergent: comma-separated presets "
                        "(default reference,paper)")
    parser.add_argument("--scales", default=None, help="comma-separated scales (tiny, small, medium, large); "
                        "scale/ablation: default all four; shift/emergent: one scale, default medium")
    parser.add_argument("--seeds", default=None, help="comma-separated seeds (default: 42,7,123,999,2024; "
                        "shift: those and 1..15)")
    parser.add_argument("--steps", type=int, default=None, help="steps per episode (default 800; emergent 1500)")
    parser.add_argument("--phase-steps", type=int, default=None, help="shift: steps per phase (default 400)")
    parser.add_argument("--demand", choices=("requests", "assignment", "none"), default=None,
                        help="shift: new requests from the active half (requests, the paper's; default), "
                        "shift.py's assignment filter, or none (the no-shift control)")
    parser.add_argument("--loss", type=float, default=None, help="shift/emergent: Gilbert–Elliott message loss "
                        "in percent (mean), bursty; default 0 = no faults")
    parser.add_argument("--quick", action="store_true", help="faults only: the reduced sweep (tiny, MORPH reference "
                        "and Full-Graph, loss 0/30 %%, latency 0/1 tick, 1 seed, 150 steps)")
    parser.add_argument("--profiles", default=None, help="network: comma-separated network profiles (default lan, "
                        "wifi-fast-roaming, wifi-legacy-roaming, congested, lossy-mesh)")
    parser.add_argument("--services-cell", default=None, metavar="SCALE:PROFILE:CONDITION",
                        help="network: also run this cell's seeds through the services in one process (morph-sim "
                             "run's sim, agents, monitor and, under a rate-limited profile, the air) and check they "
                             "give the lab's deliveries and view ages; exit 1 if not")
    parser.add_argument("--targets", default=None, help="faults: where the faults act, comma-separated: dispatch "
                        "(request, reply, commitment, refusal), fleet (the fleet broadcast), both; default all three")
    parser.add_argument("--loss-levels", default=None, help="faults: loss levels in percent, Bernoulli and "
                        "Gilbert–Elliott (default 0,10,20,30,40,50)")
    parser.add_argument("--latency-levels", default=None, help="faults: mean latencies in ticks, jitter ¼ of the "
                        "mean (default 0,0.1,0.25,0.5,1,2,5,10)")
    parser.add_argument("--conditions", default=None, help="scale/ablation/shift/faults: comma-separated "
                        "conditions (default: the study's; faults: morph, morph-paper, full, tsg, proximity); scale, ablation, shift, faults and network also take "
                        "any policy --policy takes (an installed entry point, package.module:Class)")
    parser.add_argument("--dispatch", choices=("concurrent", "sequential"), default=None,
                        help="scale/ablation: picker resolution, concurrent (all pickers at once) or sequential "
                        "(the reference's); default: sequential with --reference-stream, else concurrent")
    parser.add_argument("--reference-stream", action="store_true",
                        help="scale/ablation: draw gates from the warehouse's request stream, as the reference does")
    parser.add_argument("--radius", default=None, help="scale/ablation: Proximity radii per scale, e.g. "
                        "tiny=10,small=10,medium=6,large=8 (default: calibrate as the reference); shift: one radius "
                        "(default 6)")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default 2)")
    parser.add_argument("--executor", choices=("local", "dask"), default=None,
                        help="scale/ablation: local processes (default) or a Dask cluster ('morph-sim[cluster]')")
    parser.add_argument("--scheduler", default=None, help="scale/ablation: Dask scheduler address, e.g. "
                        "tcp://HOST:8786")
    parser.add_argument("--fiedler-every", type=int, default=None,
                        help="scale/ablation: compute λ₂ every this many ticks (default 10)")
    parser.add_argument("--out", default="runs", help="root directory of run records")
    parser.add_argument("--run-id", default=None, help="run record directory name")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


SUITES = ("scale", "ablation", "shift", "emergent", "faults", "network", "audit")
_COMMON = {"out", "run_id", "no_progress"}
_SUITE = {"preset", "scales", "seeds", "steps", "conditions", "dispatch", "reference_stream", "radius", "jobs",
          "fiedler_every", "executor", "scheduler"}
# the flags each study honours; any other optional flag given is refused with a one-line message
FLAGS = {
    "scale": _COMMON | _SUITE,
    "ablation": _COMMON | _SUITE,
    "shift": _COMMON | {"scales", "seeds", "phase_steps", "demand", "loss", "conditions", "radius", "jobs"},
    "emergent": _COMMON | {"preset", "scales", "seeds", "steps", "loss", "jobs"},
    "faults": _COMMON | {"quick", "scales", "seeds", "steps", "jobs", "conditions", "targets", "loss_levels",
                         "latency_levels"},
    "network": _COMMON | {"scales", "seeds", "steps", "jobs", "conditions", "profiles", "services_cell"},
    # audit: --conditions names the variants (morph_sim/lab/audit.py)
    "audit": _COMMON | {"scales", "seeds", "steps", "conditions", "jobs"},
}
_WHY = {
    ("shift", "steps"): "its length is 6 phases × --phase-steps",
}


def refuse_unhonoured(args) -> None:
    """ValueError naming the first flag given that ``args.suite`` cannot honour."""
    for name in sorted(vars(args)):
        if name.startswith("_") or name in ("suite", "command") or name in FLAGS[args.suite]:
            continue
        value = getattr(args, name)
        if value is None or value is False:
            continue
        flag = "--" + name.replace("_", "-")
        honoured = [s for s in SUITES if name in FLAGS[s]]
        why = _WHY.get((args.suite, name))
        if why is None and honoured:
            why = (f"only {honoured[0]} takes it" if len(honoured) == 1 else
                   f"only {', '.join(honoured[:-1])} and {honoured[-1]} take it")
        raise ValueError(f"{name}: experiment {args.suite} does not take {flag}" + (f" ({why})" if why else ""))


def _one_scale(args) -> str:
    """The single scale of a study that runs at one (shift, emergent)."""
    if args.scales is None:
        return "medium"
    scales = _csv(args.scales)
    if len(scales) != 1:
        raise ValueError(f"scales: experiment {args.suite} runs at one scale, got {args.scales!r} "
                         "(give one, e.g. --scales tiny)")
    from services.world.layout import named_sizes

    if scales[0] not in named_sizes():
        raise ValueError(f"scales: unknown scale {scales[0]!r} (choose from {', '.join(named_sizes())})")
    return scales[0]


def _seeds(value: str | None, default: tuple[int, ...]) -> tuple[int, ...]:
    if value is None:
        return default
    try:
        out = tuple(int(s) for s in _csv(value))
    except ValueError:
        raise ValueError(f"seeds: expected comma-separated integers, got {value!r}") from None
    if not out:
        raise ValueError("seeds: at least one seed")
    return out


def _validated(model, **kw):
    try:
        return model(**kw)
    except ValidationError as exc:
        raise invalid(exc) from None


def _run_shift(args) -> int:
    from morph_sim.lab.shift import SHIFT_CONDITIONS, SHIFT_SEEDS, ShiftConfig, markdown_shift, run_shift

    if args.radius is not None and not args.radius.strip().isdigit():
        raise ValueError(f"radius: experiment shift takes one integer radius, got {args.radius!r}")
    cfg = _validated(
        ShiftConfig, scale=_one_scale(args), seeds=_seeds(args.seeds, SHIFT_SEEDS),
        phase_steps=400 if args.phase_steps is None else args.phase_steps,
        conditions=_csv(args.conditions) if args.conditions else tuple(SHIFT_CONDITIONS),
        demand_mode=args.demand or "requests", jobs=2 if args.jobs is None else args.jobs,
        loss_percent=args.loss or 0.0,
        **({"radius": int(args.radius)} if args.radius is not None else {}),
    )
    res = run_shift(cfg, Path(args.out), args.run_id, show_progress=not args.no_progress,
                    argv=["morph-sim", *sys.argv[1:]])
    print(markdown_shift(cfg, res.rows, res.wall_s))
    print(f"shift wall time: {res.wall_s:.1f} s for {len(res.episodes)} episodes")
    if res.run_dir is not None:
        print(f"run record: {res.run_dir}")
    return 0


def _run_emergent(args) -> int:
    from morph_sim.lab.emergent import EmergentConfig, markdown_emergent, run_emergent

    cfg = _validated(
        EmergentConfig, scale=_one_scale(args), seeds=_seeds(args.seeds, (42, 7, 123, 999, 2024)),
        steps=1500 if args.steps is None else args.steps,
        presets=_csv(args.preset) if args.preset else ("reference", "paper"), jobs=2 if args.jobs is None else args.jobs,
        loss_percent=args.loss or 0.0,
    )
    res = run_emergent(cfg, Path(args.out), args.run_id, show_progress=not args.no_progress,
                       argv=["morph-sim", *sys.argv[1:]])
    print(markdown_emergent(res))
    if res.run_dir is not None:
        print(f"run record: {res.run_dir}")
    return 0


def _levels(value: str | None, what: str) -> tuple[float, ...] | None:
    if value is None:
        return None
    try:
        out = tuple(float(v) for v in _csv(value))
    except ValueError:
        raise ValueError(f"{what}: expected comma-separated numbers, got {value!r}") from None
    if not out:
        raise ValueError(f"{what}: at least one level")
    return out


def _scales(value: str | None, default: str) -> tuple[str, ...]:
    from services.world.layout import named_sizes

    scales = _csv(value or default)
    for sc in scales:
        if sc not in named_sizes():
            raise ValueError(f"scales: unknown scale {sc!r} (choose from {', '.join(named_sizes())})")
    if not scales:
        raise ValueError("scales: at least one scale")
    return scales


def _run_dir(args, kind: str) -> Path:
    from datetime import datetime, timezone

    from schemas.keys import validate_run_id

    run_id = args.run_id or f"{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}-{kind}"
    validate_run_id(run_id)
    return Path(args.out) / run_id


def _interrupted(kind: str, run_dir: Path, total: int) -> int:
    from morph_sim.lab.grid import count_done

    print(f"experiment {kind}: interrupted with {count_done(run_dir)} of {total} episodes in the record; the same "
          f"command with --run-id {run_dir.name} resumes it", file=sys.stderr)
    return 130


def _run_faults(args) -> int:
    from morph_sim.lab.faults_experiment import fault_tasks, grid_plan, run_experiment

    plan = grid_plan(quick=args.quick, scales=_scales(args.scales, "tiny" if args.quick else "tiny,small,medium,large"),
                     seeds=_seeds(args.seeds, ()) or None, steps=args.steps,
                     conditions=_csv(args.conditions) if args.conditions else None,
                     targets=_csv(args.targets) if args.targets else None,
                     loss=_levels(args.loss_levels, "loss-levels"), latency=_levels(args.latency_levels,
                                                                                    "latency-levels"))
    jobs = 2 if args.jobs is None else args.jobs
    if jobs < 1:
        raise ValueError(f"jobs: must be at least 1, got {jobs}")
    run_dir = _run_dir(args, "faults")
    n = len(fault_tasks(**{k: plan[k] for k in ("scales", "targets", "conditions", "loss", "latency", "seeds",
                                                "steps")}))
    print(f"experiment faults: {len(plan['scales'])} scales × {len(plan['conditions'])} policies × "
          f"{len(plan['seeds'])} seeds, targets {', '.join(plan['targets'])}, T = {plan['steps']}: {n} episodes "
          f"→ {run_dir}", file=sys.stderr)
    return _run_grid("faults", run_dir, n, lambda: run_experiment(
        run_dir, progress=not args.no_progress, jobs=jobs, argv=["morph-sim", *sys.argv[1:]],
        **{k: v for k, v in plan.items() if k != "steps"}, steps=plan["steps"]))


def _run_grid(study: str, run_dir, n: int, run) -> int:
    """Run a study's grid of ``n`` episodes (``run()``), print its tables and where its files are; Ctrl-C says how to
    resume."""
    try:
        res = run()
    except KeyboardInterrupt:
        return _interrupted(study, run_dir, n)
    print(res["markdown"])
    print(f"{study} experiment: {res['ran']} episodes run, {res['skipped']} already in the record, "
          f"{res['wall_s']:.1f} s; {res['md']}, {res['json']}, {', '.join(res['pngs'])}")
    return 0


def _run_network(args) -> int:
    from morph_sim.lab.network_study import PROFILES, SCALES, SEEDS, grid_plan, network_tasks, parse_cell, run_study

    plan = grid_plan(scales=_scales(args.scales, ",".join(SCALES)),
                     profiles=_csv(args.profiles) if args.profiles else PROFILES,
                     conditions=_csv(args.conditions) if args.conditions else None,
                     seeds=_seeds(args.seeds, SEEDS), steps=args.steps)
    jobs = 2 if args.jobs is None else args.jobs
    if jobs < 1:
        raise ValueError(f"jobs: must be at least 1, got {jobs}")
    cell = parse_cell(args.services_cell, plan) if args.services_cell else None
    run_dir = _run_dir(args, "network")
    n = len(network_tasks(plan))
    print(f"experiment network: {len(plan['scales'])} scales × {len(plan['profiles'])} profiles × "
          f"{len(plan['conditions'])} policies × {len(plan['seeds'])} seeds = {n} episodes → {run_dir}",
          file=sys.stderr)
    checked: list[dict] = []

    def study():
        res = run_study(run_dir, plan, jobs=jobs, progress=not args.no_progress, argv=["morph-sim", *sys.argv[1:]],
                        services_cell=cell)
        checked.append(res)
        return res

    code = _run_grid("network", run_dir, n, study)
    check = checked[0].get("services_check") if checked else None
    if code == 0 and check is not None:
        if not check["equal"]:
            print(f"experiment network: the services differ from the lab in {check['condition']} under "
                  f"{check['profile']} at {check['scale']}: {run_dir}/services_check.json", file=sys.stderr)
            return 1
        print(f"experiment network: services cross-check of {check['condition']} under {check['profile']} at "
              f"{check['scale']}: {len(check['seeds'])} seed{'s' if len(check['seeds']) != 1 else ''}, the lab's "
              "deliveries and view ages", file=sys.stderr)
    return code


def _run_audit(args) -> int:
    from datetime import datetime, timezone

    from morph_sim.lab.audit import VARIANTS, run_audit

    run_id = args.run_id or f"{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}-audit"
    scales = _csv(args.scales) if args.scales else ("small", "medium")
    res = run_audit(Path(args.out) / run_id, scales=scales, seeds=_seeds(args.seeds, (11, 12, 13, 14, 15)),
                    steps=args.steps or 800, variants=_csv(args.conditions) if args.conditions else tuple(VARIANTS),
                    jobs=args.jobs or 2, show_progress=not args.no_progress, argv=["morph-sim", *sys.argv[1:]])
    print((res.run_dir / "audit.md").read_text(encoding="utf-8"))
    print(f"run record: {res.run_dir}")
    return 0


def run(args) -> int:
    import time

    if args.executor == "dask" and args.suite not in ("scale", "ablation"):
        raise ValueError(f"executor: the dask executor runs the scale and ablation studies (and sweeps), "
                         f"not {args.suite}")
    refuse_unhonoured(args)
    from morph_sim.lab.executors import check_jobs
    from services.inputs import output_dir

    output_dir(args.out, "out")  # before the first episode: its record goes there
    if args.jobs is not None:
        check_jobs(args.jobs)
    args.executor = args.executor or "local"
    if args.executor == "dask" and not args.scheduler:
        raise ValueError("scheduler: --executor dask needs --scheduler tcp://HOST:8786")
    if args.suite == "audit":
        return _run_audit(args)
    if args.suite == "shift":
        return _run_shift(args)
    if args.suite == "emergent":
        return _run_emergent(args)
    if args.suite == "faults":
        return _run_faults(args)
    if args.suite == "network":
        return _run_network(args)
    started = time.perf_counter()
    from morph_sim.lab.suite import SuiteConfig, markdown_table, run_suite, summarise
    from services.policies.conditions import ABLATION_STUDY, SCALE_STUDY

    preset = args.preset or ("reference" if args.suite == "scale" else "paper")
    default_conditions = SCALE_STUDY if args.suite == "scale" else ABLATION_STUDY
    seeds = _seeds(args.seeds, (42, 7, 123, 999, 2024))
    args.steps = 800 if args.steps is None else args.steps
    if args.steps < 1:
        raise ValueError("steps: must be >= 1")
    dispatch = args.dispatch or ("sequential" if args.reference_stream else "concurrent")
    try:
        cfg = SuiteConfig(
            kind=args.suite, preset=preset, scales=_csv(args.scales or "tiny,small,medium,large"), seeds=seeds,
            steps=args.steps, conditions=_csv(args.conditions) if args.conditions else default_conditions,
            dispatch=dispatch, shared_stream=args.reference_stream,
            radii=_radii(args.radius) if args.radius else None, jobs=2 if args.jobs is None else args.jobs,
            fiedler_every=10 if args.fiedler_every is None else args.fiedler_every,
        )
    except ValidationError as exc:
        from schemas.errors import explain

        raise ValueError(explain(exc, first_only=True)) from None
    from services.policies.presets import load_preset

    load_preset(preset)  # fail early, naming the preset
    try:
        result = run_suite(cfg, Path(args.out), args.run_id, show_progress=not args.no_progress,
                           argv=["morph-sim", *sys.argv[1:]], executor=args.executor, scheduler=args.scheduler)
    except ImportError as exc:  # the dask executor without the [cluster] extra
        print(f"morph-sim experiment: error: {exc}", file=sys.stderr)
        return 2
    rows = summarise(cfg, result.episodes)
    print(markdown_table(cfg, rows, result.wall_s, result.radii))
    print(f"study wall time: {result.wall_s:.1f} s for {len(result.episodes)} episodes"
          + (" (+ Proximity calibration)" if result.calibration else "")
          + f"; {time.perf_counter() - started:.1f} s in all, with run records and plots")
    if result.run_dir is not None:
        print(f"run record: {result.run_dir}")
    return 0
