"""``morph-sim replay``: feed a bus record into a monitor offline and write a fresh run record (metrics recomputed)."""

from __future__ import annotations

import argparse

NAME = "replay"
HELP = "replay a bus record (morph-sim record) into a monitor offline; writes a new run record"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("record", help="bus record file written by morph-sim record")
    parser.add_argument("--output-dir", default="runs/replay", help="parent directory of the new run record")
    parser.add_argument("--run-id", default=None, help="run id of the new record (default: the recorded run's)")


def run(args: argparse.Namespace) -> int:
    import asyncio
    import json

    from services.inputs import input_file, output_dir
    from services.monitor.replay import replay

    path = input_file(args.record, "record", limit=None)  # read frame by frame: any size, but a file
    result = asyncio.run(replay(path, output_dir(args.output_dir, "output_dir"), args.run_id))
    print(json.dumps({"rows": len(result.rows), "deliveries": result.deliveries_total, "rejected": result.rejected}))
    return 0
