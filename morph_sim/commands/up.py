"""``morph-sim up``: a distributed run on this machine — sim, one process per agent, monitor — over Zenoh."""

from __future__ import annotations

import argparse
import asyncio
import sys

NAME = "up"
HELP = "start a distributed run: sim (Zenoh endpoint), one process per agent, monitor; live progress"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--quiet", action="store_true", help="no live progress line")
    parser.add_argument("--insecure", action="store_true",
                        help="open endpoint: no credentials, no access control (anyone who reaches the endpoint "
                             "can publish anything); default: per-run credentials in <record>/credentials")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from services.runconfig import config_from_args
    from services.supervisor.launcher import StartError, Supervisor

    config = config_from_args(args)
    try:  # the live line needs the [cli] extra; a service-only install (a container) prints the last line alone
        from rich.console import Console
    except ImportError:
        Console = None
    console = Console(stderr=True) if Console is not None else None
    status = None
    if not args.quiet and console is not None:
        status = console.status("starting …")
        status.start()

    def show(progress, line: str) -> None:
        if status is not None:
            status.update(line)
        if progress.finished:
            if console is not None:
                console.print(line)
            else:
                print(line, file=sys.stderr)

    try:
        supervisor = Supervisor(config, on_progress=show, insecure=args.insecure)
    except StartError as exc:
        if status is not None:
            status.stop()
        print(f"morph-sim up: error: {exc}", file=sys.stderr)
        return 1
    if supervisor.credentials is not None:
        print(f"run {config.run_id}: secured endpoint {supervisor.endpoint}; operator credentials "
              f"{supervisor.credentials.operator} (watch/faults/record/stop find them with --run {config.run_id})",
              file=sys.stderr)
    elif args.insecure and not supervisor.external:
        print(f"morph-sim up: warning: INSECURE run: the endpoint {supervisor.endpoint} has no credentials and no "
              "access control; anyone who reaches it can stop the run, inject faults or forge messages",
              file=sys.stderr)
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
    print(f"run {config.run_id}: {len(supervisor.children)} processes, {restarts} restarts, "
          f"{'completed' if code == 0 else 'interrupted'}; record: {config.record_dir}")
    return code
