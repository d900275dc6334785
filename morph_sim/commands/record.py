"""``morph-sim record``: record all bus traffic of a run (``morph/<run>/**``) to a file, for ``morph-sim replay``."""

from __future__ import annotations

import argparse

NAME = "record"
HELP = "record every message of a run to a file (msgpack frames with receive time) until the run ends"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--out", required=True, help="file to write (appended if it exists), e.g. runs/r1.mbr")
    parser.add_argument("--timeout", type=float, default=None, help="stop after this many seconds")
    add_config_arguments(parser, skip=("listen",))
    from services.supervisor.process import add_operator_arguments

    add_operator_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import signal
    from pathlib import Path

    from services.monitor.replay import BusRecorder
    from services.runconfig import config_from_args
    from services.supervisor.process import open_operator_bus

    config = config_from_args(args)
    if not config.endpoint:
        raise ValueError("endpoint: record needs --endpoint ENDPOINT of the run (e.g. tcp/127.0.0.1:7447)")

    async def main() -> int:
        bus = await open_operator_bus("recorder", config.endpoint, args, config.run_id, config.output_dir)
        try:
            rec = BusRecorder(bus, config, Path(args.out))
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, rec.stop)
            return await rec.run(args.timeout)
        finally:
            await bus.close()

    frames = asyncio.run(main())
    print(f"recorded {frames} messages of run {config.run_id} to {args.out}")
    return 0
