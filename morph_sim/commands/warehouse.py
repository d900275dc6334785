"""``morph-sim warehouse``: one TA-RWARE heuristic episode in this process, with a summary (and optional images)."""

from __future__ import annotations

import argparse
import time

NAME = "warehouse"
HELP = "run TA-RWARE's heuristic controller for one episode and print deliveries, pick rate, clashes, stucks, speed"

# TA-RWARE's scripts/run_heuristic.py reports pick rate as deliveries * 3600 / (5 * steps): 5 s of robot time a step.
PICK_RATE_SECONDS_PER_STEP = 5.0
#: Largest image --png or --gif draws, in pixels (4096 × 4096): more than a screen shows, and within about 100 MB
#: for the frame, its copies and the cached background; the extralarge warehouse reaches it near --cell-px 90.
#: The size follows from --cell-px, so it is checked before the episode, not found when the first frame is drawn.
MAX_IMAGE_PIXELS = 4096 * 4096
#: Most frames a GIF keeps (every frame waits in memory until the episode ends): over 16 minutes of animation at the
#: default 10 fps; more is a --gif-every that was meant to be larger.
MAX_GIF_FRAMES = 10_000
#: Seeds the warehouse takes: its random state is numpy's RandomState, whose seed is 32 bits.
MAX_SEED = 2**32 - 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.world.layout import named_sizes

    sizes = named_sizes()
    defaults = ", ".join(f"{k} {a}+{p}" for k, (_, a, p) in sizes.items())
    parser.add_argument("--scale", default="tiny", help=f"warehouse size: {', '.join(sizes)} (default tiny)")
    parser.add_argument("--agvs", type=int, default=None, help=f"number of AGVs (default by scale: {defaults})")
    parser.add_argument("--pickers", type=int, default=None, help="number of pickers (default by scale)")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    parser.add_argument("--steps", type=int, default=800,
                        help="episode length (default 800, as the reference runs; the original registers 500)")
    parser.add_argument("--reward", choices=("individual", "global"), default="individual")
    parser.add_argument("--png", metavar="FILE", help="write the last frame as a PNG")
    parser.add_argument("--gif", metavar="FILE", help="write an animated GIF of the episode")
    parser.add_argument("--gif-every", type=int, default=2, metavar="K", help="GIF: keep every K-th step (default 2)")
    parser.add_argument("--fps", type=float, default=10.0, help="GIF frames per second (default 10)")
    parser.add_argument("--cell-px", type=int, default=20, help="image cell size in pixels (default 20)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from schemas.errors import invalid
    from services.inputs import at_most, finite, output_file
    from services.runconfig import MAX_STEPS
    from services.world.heuristic import run_episode
    from services.world.layout import layout_for
    from services.world.render import WAREHOUSE_LEGEND, image_size
    from services.world.warehouse import WarehouseConfig

    if args.steps is not None and not 1 <= args.steps <= MAX_STEPS:
        raise ValueError(f"steps: must be in 1..{MAX_STEPS:,}, got {args.steps}")
    if not 0 <= args.seed <= MAX_SEED:
        raise ValueError(f"seed: must be in 0..{MAX_SEED}, got {args.seed}")
    if args.gif_every < 1:
        raise ValueError(f"gif-every: must be >= 1, got {args.gif_every}")
    if args.cell_px < 4:
        raise ValueError(f"cell-px: must be >= 4, got {args.cell_px}")
    finite(args.fps, "fps", above=0)
    for flag in ("png", "gif"):  # before the episode: a path that cannot be written is known now
        if getattr(args, flag):
            output_file(getattr(args, flag), flag)
    try:
        config = WarehouseConfig.named(args.scale, args.agvs, args.pickers, max_steps=args.steps,
                                       reward_type=args.reward)
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        raise invalid(exc) from None
    if args.png or args.gif:
        layout = layout_for(config.layout)
        w, h = image_size(layout.H, layout.W, args.cell_px, header=True, legend=WAREHOUSE_LEGEND)
        at_most(w * h, MAX_IMAGE_PIXELS, "cell-px", f"pixels in a {w}×{h} image of the {args.scale} warehouse")
    if args.gif:
        at_most(config.max_steps // args.gif_every + 1, MAX_GIF_FRAMES, "gif-every",
                f"GIF frames ({config.max_steps} steps, one kept every {args.gif_every})")

    frames = []
    render_s = 0.0
    caption = f"{args.scale} {config.agvs}+{config.pickers} seed {args.seed}"

    console = Console(stderr=True)
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("deliveries {task.fields[deliveries]}"), TimeRemainingColumn(),
                        console=console, disable=args.no_progress, transient=True)
    delivered = 0

    with progress:
        task = progress.add_task(caption, total=config.max_steps, deliveries=0)

        def on_step(env, res):
            nonlocal delivered, render_s
            delivered += res.deliveries
            if args.gif and (env.steps % args.gif_every == 0 or res.done):
                t0 = time.perf_counter()
                frames.append(env.frame(caption=caption))
                render_s += time.perf_counter() - t0
            if args.png and res.done:
                t0 = time.perf_counter()
                frames_last[0] = env.frame(caption=caption)
                render_s += time.perf_counter() - t0
            if env.steps % 10 == 0 or res.done:
                progress.update(task, completed=env.steps, deliveries=delivered)

        frames_last = [None]
        result = run_episode(config, args.seed, on_step=on_step)

    sim_seconds = max(result.seconds - render_s, 1e-9)
    pick_rate = result.deliveries * 3600.0 / (PICK_RATE_SECONDS_PER_STEP * result.steps)
    out = Console()
    out.print(f"warehouse {caption}, {result.steps} steps")
    out.print(f"  deliveries  {result.deliveries}")
    out.print(f"  pick rate   {pick_rate:.1f} lines/h  (deliveries x 3600 / (5 s x steps), as the original)")
    out.print(f"  clashes     {result.clashes}")
    out.print(f"  stucks      {result.stucks}")
    out.print(f"  return      {result.global_return:.1f}  (sum over agents and steps)")
    out.print(f"  speed       {result.steps / sim_seconds:,.0f} steps/s  (simulation + controller)")
    if args.png:
        from services.world.render import save_png

        save_png(frames_last[0], args.png, cell_px=args.cell_px, legend=WAREHOUSE_LEGEND)
        out.print(f"  png         {args.png}")
    if args.gif:
        from services.world.render import write_gif

        n = write_gif(frames, args.gif, fps=args.fps, cell_px=args.cell_px, legend=WAREHOUSE_LEGEND)
        out.print(f"  gif         {args.gif} ({n} frames)")
    return 0


def _short(exc: Exception) -> str:
    from pydantic import ValidationError

    from schemas.errors import explain

    return explain(exc) if isinstance(exc, ValidationError) else str(exc)
