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
    from pathlib import Path

    from services.monitor.replay import replay

    path = Path(args.record)
    if not path.is_file():
        raise ValueError(f"record: {path} is not a file")
    result = asyncio.run(replay(path, Path(args.output_dir), args.run_id))
    print(json.dumps({"rows": len(result.rows), "deliveries": result.deliveries_total, "rejected": result.rejected}))
    return 0
