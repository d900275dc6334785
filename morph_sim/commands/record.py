"""``morph-sim record``: record all bus traffic of a run (``morph/<run>/**``) to a file, for ``morph-sim replay``.

The run's configuration (fleet, steps, policy …), which a replay needs to recompute the record, comes from the run
itself: its monitor answers ``get morph/<run>/state/config``. No run flags to repeat, none to get wrong.
"""

from __future__ import annotations

import argparse
import sys

NAME = "record"
HELP = "record every message of a run to a file (msgpack frames with receive time) until the run ends"
CONFIG_WAIT = 10.0  # seconds to wait for the run's monitor to give the run's configuration
PROGRESS_EVERY = 2.0  # seconds between progress lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="file to write (appended if it exists), e.g. runs/r1.mbr")
    parser.add_argument("--run-id", dest="run", default=None,
                        help="run id (default: the run whose monitor is alive on the endpoint)")
    parser.add_argument("--timeout", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    _operator_args(parser)


async def run_config(bus, run_id: str, timeout: float = CONFIG_WAIT):
    """The RunConfig of the live run ``run_id``, from its monitor; ValueError if no monitor answers in time."""
    import asyncio
    import time

    from schemas import Event
    from schemas.keys import RunKeys
    from services.runconfig import RunConfig

    key = RunKeys(run_id).latest("config")
    deadline = time.monotonic() + timeout
    while True:
        for reply in await bus.get(key, timeout=min(2.0, timeout)):
            if not reply.ok:
                continue
            try:
                event = reply.decode(Event)
                return RunConfig.coerce(event.details["config"])
            except (ValueError, KeyError, TypeError) as exc:
                raise ValueError(f"run: the monitor of {run_id!r} gave an unreadable configuration: {exc}") from None
        if time.monotonic() > deadline:
            raise ValueError(f"run: no monitor of run {run_id!r} answered within {timeout:.0f} s (is the run up?)")
        await asyncio.sleep(0.2)


def _operator_args(parser) -> None:
    from services.process import add_operator_arguments

    add_operator_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import signal
    import time

    from morph_sim.commands.watch import check_run, find_run
    from schemas.keys import RunKeys, validate_run_id
    from services.inputs import finite, output_file
    from services.monitor.replay import BusRecorder
    from services.process import open_operator_bus, operator_endpoint

    if args.run is not None:
        validate_run_id(args.run)
    if args.timeout is not None:
        finite(args.timeout, "timeout", above=0)
    out = output_file(args.out, "out", parents=True)  # the recorder creates its directory
    endpoint = operator_endpoint(args, args.run)  # checks it, and the other operator options

    def say(line: str) -> None:
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    async def main() -> tuple[int, str]:
        bus = await open_operator_bus("recorder", endpoint, args, args.run)
        try:
            run_id = args.run
            if run_id is None:
                run_id = await find_run(bus)
            else:
                await check_run(bus, run_id)
            # subscribe before asking for the configuration, so that nothing sent meanwhile is missed
            early: list = []
            sink = [early.append]
            sub = await bus.subscribe(RunKeys(run_id).everything, lambda sample: sink[0](sample))
            config = await run_config(bus, run_id)
            rec = BusRecorder(bus, config, out)
            for sample in early:
                rec.on_sample(sample)
            sink[0] = rec.on_sample
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, rec.stop)
            say(f"recording run {run_id} ({config.scale}, {config.steps} steps) to {args.out}")

            async def progress() -> None:
                while True:
                    await asyncio.sleep(PROGRESS_EVERY)
                    say(f"recording run {run_id}: {rec.frames} messages, tick {rec.ticks}/{config.steps}")

            reporter = asyncio.get_running_loop().create_task(progress())
            try:
                frames = await rec.run(args.timeout, subscription=sub)
            finally:
                reporter.cancel()
            return frames, run_id
        finally:
            await bus.close()

    started = time.monotonic()
    frames, run_id = asyncio.run(main())
    print(f"recorded {frames} messages of run {run_id} to {args.out} in {time.monotonic() - started:.0f} s")
    return 0
