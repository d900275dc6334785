"""``morph-sim experiment scale|ablation``: the in-process lab (conditions × scales × seeds)."""

from __future__ import annotations

import sys
from pathlib import Path

from pydantic import ValidationError

NAME = "experiment"
HELP = "run the scale study or the ablation study in-process (parallel, with run records and tables)"


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
    parser.add_argument("suite", choices=("scale", "ablation"), help="which study")
    parser.add_argument("--preset", default=None, help="MORPH preset: reference (scale default) or paper "
                        "(ablation default), or a preset TOML path")
    parser.add_argument("--scales", default="tiny,small,medium,large", help="comma-separated scales")
    parser.add_argument("--seeds", default="42,7,123,999,2024", help="comma-separated seeds")
    parser.add_argument("--steps", type=int, default=800, help="steps per episode")
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


def run(args) -> int:
    import time

    started = time.perf_counter()
    from morph_sim.services.lab.runner import SCALE_STUDY
    from morph_sim.services.lab.suite import ABLATION_STUDY, SuiteConfig, markdown_table, run_suite, summarise

    preset = args.preset or ("reference" if args.suite == "scale" else "paper")
    default_conditions = SCALE_STUDY if args.suite == "scale" else ABLATION_STUDY
    try:
        seeds = tuple(int(s) for s in _csv(args.seeds))
    except ValueError:
        raise ValueError(f"seeds: expected comma-separated integers, got {args.seeds!r}") from None
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
    from morph_sim.services.agent.presets import load_preset

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
