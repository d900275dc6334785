"""``morph-sim up``: a distributed run on this machine — sim, one process per agent, monitor — over Zenoh."""

from __future__ import annotations

import argparse
import asyncio
import sys

NAME = "up"
HELP = "start a distributed run: sim (Zenoh endpoint), one process per agent, monitor; live progress"
EPILOG = ("exit status: 0 the run completed and its record (every row, summary) agrees with the sim; 1 a process "
          "failed, the run stalled or the record is incomplete (the last line says which); 2 bad flags or "
          "configuration; 3 the run was stopped from outside before its steps; 130/143 interrupted (SIGINT/SIGTERM)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--quiet", action="store_true", help="no live progress line")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from services.runconfig import config_from_args
    from services.supervisor.launcher import StartError, Supervisor

    config = config_from_args(args)
    claim_record_dir(config.record_dir)
    console = Console(stderr=True)
    status = None
    if not args.quiet:
        status = console.status("starting …")
        status.start()

    def show(progress, line: str) -> None:
        if status is not None:
            status.update(line)
        if progress.finished:
            console.print(line)

    supervisor = Supervisor(config, on_progress=show)
    try:
        code = asyncio.run(supervisor.run())
    except StartError as exc:
        if status is not None:
            status.stop()
        print(f"morph-sim up: error: {exc}", file=sys.stderr)
        return 1
    finally:
        if status is not None:
            status.stop()
    restarts = sum(c.restarts for c in supervisor.children.values())
    check = supervisor.check
    numbers = (f"{check.rows} rows, {check.deliveries} deliveries, " if check is not None and check.rows else "")
    print(f"run {config.run_id}: {supervisor.outcome}; {numbers}{len(supervisor.children)} processes, "
          f"{restarts} restarts; record: {config.record_dir}")
    return code


def claim_record_dir(directory) -> None:
    """Create the run's record directory, refusing one that exists: a second run under the same id would append to
    the first one's record (a restarted monitor does that on purpose). A run cannot be resumed (the world restarts
    at tick 0), so there is nothing to continue. Raises ValueError (one line, exit 2) naming the problem."""
    import os
    import tempfile
    from pathlib import Path

    directory = Path(directory)
    try:
        directory.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        reason = "not a directory" if isinstance(exc, FileExistsError) else exc.strerror or exc
        raise ValueError(f"output_dir: cannot create {directory.parent}: {reason}") from None
    try:
        directory.mkdir()
    except FileExistsError:
        raise ValueError(f"run_id: {directory} exists (a run with this id was recorded there); choose another "
                         "--run-id or remove it") from None
    except OSError as exc:
        raise ValueError(f"output_dir: cannot create {directory}: {exc.strerror or exc}") from None
    try:  # writable, not just creatable (e.g. a read-only bind mount)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        try:
            os.rmdir(directory)
        except OSError:
            pass
        raise ValueError(f"output_dir: cannot write in {directory}: {exc.strerror or exc}") from None
