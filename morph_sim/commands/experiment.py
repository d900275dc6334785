"""``morph-sim experiment scale|ablation|shift|emergent|faults``: the in-process lab.

scale/ablation: conditions × scales × seeds (the reference's study); shift: the paper's six-phase demand-shift
experiment with recovery times; emergent: W snapshots, Spearman, link lifetimes, η and λ₂ over long episodes;
faults: the faults helper's loss/latency sweep (services/lab/faults_experiment.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

from pydantic import ValidationError

NAME = "experiment"
HELP = "run an in-process study: scale, ablation, shift, emergent or faults (parallel, with run records)"


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
    parser.add_argument("suite", choices=("scale", "ablation", "shift", "emergent", "faults"), help="which study")
    parser.add_argument("--preset", default=None, help="MORPH preset: reference (scale default) or paper "
                        "(ablation default), or a preset TOML path")
    parser.add_argument("--scales", default="tiny,small,medium,large", help="comma-separated scales")
    parser.add_argument("--seeds", default=None, help="comma-separated seeds (default: 42,7,123,999,2024; "
                        "shift: those and 1..15)")
    parser.add_argument("--steps", type=int, default=None, help="steps per episode (default 800; emergent 1500)")
    parser.add_argument("--phase-steps", type=int, default=400, help="shift: steps per phase")
    parser.add_argument("--demand", choices=("requests", "assignment", "none"), default="requests",
                        help="shift: new requests from the active half (paper), shift.py's assignment filter, "
                        "or none (the no-shift control)")
    parser.add_argument("--loss", type=float, default=0.0, help="shift/emergent: Gilbert–Elliott message loss "
                        "in percent (mean), bursty; 0 = no faults")
    parser.add_argument("--quick", action="store_true", help="faults: the reduced sweep")
    parser.add_argument("--conditions", default=None, help="comma-separated conditions (default: the study's)")
    parser.add_argument("--dispatch", choices=("concurrent", "sequential"), default=None,
                        help="picker resolution: concurrent (DESIGN §3) or sequential (the reference); "
                        "default: sequential with --reference-stream, else concurrent")
    parser.add_argument("--reference-stream", action="store_true",
                        help="draw gates from the warehouse's request stream, as the reference does")
    parser.add_argument("--radius", default=None, help="Proximity radii, e.g. tiny=10,small=10,medium=6,large=8 "
                        "(default: calibrate as the reference)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes")
    parser.add_argument("--fiedler-every", type=int, default=10, help="compute λ₂ every this many ticks")
    parser.add_argument("--out", default="runs", help="root directory of run records")
    parser.add_argument("--run-id", default=None, help="run record directory name")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


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
    from pydantic import ValidationError as _VE

    try:
        return model(**kw)
    except _VE as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "config"
        raise ValueError(f"{field}: {err['msg']}") from None


def _run_shift(args) -> int:
    from morph_sim.lab.shift import SHIFT_CONDITIONS, SHIFT_SEEDS, ShiftConfig, markdown_shift, run_shift

    cfg = _validated(
        ShiftConfig, seeds=_seeds(args.seeds, SHIFT_SEEDS), phase_steps=args.phase_steps,
        conditions=_csv(args.conditions) if args.conditions else tuple(SHIFT_CONDITIONS),
        demand_mode=args.demand, jobs=args.jobs, loss_percent=args.loss,
        **({"radius": int(args.radius)} if args.radius and args.radius.isdigit() else {}),
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
        EmergentConfig, seeds=_seeds(args.seeds, (42, 7, 123, 999, 2024)), steps=args.steps or 1500,
        presets=_csv(args.preset) if args.preset else ("reference", "paper"), jobs=args.jobs,
        loss_percent=args.loss,
    )
    res = run_emergent(cfg, Path(args.out), args.run_id, show_progress=not args.no_progress,
                       argv=["morph-sim", *sys.argv[1:]])
    print(markdown_emergent(res))
    if res.run_dir is not None:
        print(f"run record: {res.run_dir}")
    return 0


def _run_faults(args) -> int:
    from datetime import datetime, timezone

    from morph_sim.lab.faults_experiment import CONDITIONS, markdown, run_experiment

    scales = tuple(_csv(args.scales))
    seeds = _seeds(args.seeds, ()) or None
    if args.steps is not None and args.steps < 1:
        raise ValueError("steps: must be >= 1")
    conditions = tuple(_csv(args.conditions)) if args.conditions else None
    for c in conditions or ():
        if c not in CONDITIONS:
            raise ValueError(f"conditions: unknown {c!r}; choose from {', '.join(CONDITIONS)}")
    out = Path(args.out) / (args.run_id or f"{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}-faults")
    out.mkdir(parents=True, exist_ok=True)
    bar = None if args.no_progress else _Progress("faults")
    res = run_experiment(out, quick=args.quick, scales=scales, seeds=seeds, steps=args.steps, jobs=args.jobs,
                         conditions=conditions, progress=None if bar is None else bar.update)
    if bar is not None:
        bar.close()
    print(markdown(res["rows"]))
    print(f"faults experiment: {len(res['rows'])} rows in {res['wall_s']:.1f} s; {res['json']}, "
          f"{', '.join(res['pngs'])}")
    return 0


class _Progress:
    """A one-line progress bar on stderr: episodes done of total."""

    def __init__(self, what: str):
        self.what = what

    def update(self, _episode, done: int, total: int) -> None:
        width = 30
        filled = width * done // max(total, 1)
        sys.stderr.write(f"\r{self.what} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}")
        sys.stderr.flush()

    def close(self) -> None:
        sys.stderr.write("\n")


def run(args) -> int:
    import time

    if args.suite == "shift":
        return _run_shift(args)
    if args.suite == "emergent":
        return _run_emergent(args)
    if args.suite == "faults":
        return _run_faults(args)
    started = time.perf_counter()
    from morph_sim.lab.runner import SCALE_STUDY
    from morph_sim.lab.suite import ABLATION_STUDY, SuiteConfig, markdown_table, run_suite, summarise

    preset = args.preset or ("reference" if args.suite == "scale" else "paper")
    default_conditions = SCALE_STUDY if args.suite == "scale" else ABLATION_STUDY
    seeds = _seeds(args.seeds, (42, 7, 123, 999, 2024))
    args.steps = 800 if args.steps is None else args.steps
    if args.steps < 1:
        raise ValueError("steps: must be >= 1")
    dispatch = args.dispatch or ("sequential" if args.reference_stream else "concurrent")
    try:
        cfg = SuiteConfig(
            kind=args.suite, preset=preset, scales=_csv(args.scales), seeds=seeds, steps=args.steps,
            conditions=_csv(args.conditions) if args.conditions else default_conditions,
            dispatch=dispatch, shared_stream=args.reference_stream,
            radii=_radii(args.radius) if args.radius else None, jobs=args.jobs, fiedler_every=args.fiedler_every,
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "config"
        raise ValueError(f"{field}: {err['msg']}") from None
    from services.agent.presets import load_preset

    load_preset(preset)  # fail early, naming the preset
    result = run_suite(cfg, Path(args.out), args.run_id, show_progress=not args.no_progress,
                       argv=["morph-sim", *sys.argv[1:]])
    rows = summarise(cfg, result.episodes)
    print(markdown_table(cfg, rows, result.wall_s, result.radii))
    print(f"study wall time: {result.wall_s:.1f} s for {len(result.episodes)} episodes"
          + (" (+ Proximity calibration)" if result.calibration else "")
          + f"; {time.perf_counter() - started:.1f} s in all, with run records and plots")
    if result.run_dir is not None:
        print(f"run record: {result.run_dir}")
    return 0
