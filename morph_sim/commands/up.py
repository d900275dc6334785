"""``morph-sim up``: a distributed run on this machine — sim, one process per agent, monitor — over Zenoh."""

from __future__ import annotations

import argparse
import asyncio
import shutil
import sys
from pathlib import Path

NAME = "up"
HELP = "start a distributed run: sim (Zenoh endpoint), one process per agent, monitor; live progress"
EPILOG = ("exit status: 0 the run completed and its record (every row, summary) agrees with the sim; 1 a process "
          "failed, the run stalled or the record is incomplete (the last line says which); 2 bad flags or "
          "configuration; 3 the run was stopped from outside before its steps; 130/143 interrupted (SIGINT/SIGTERM)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--quiet", action="store_true", help="no live progress line")
    parser.add_argument("--max-rate", type=float, default=10.0,
                        help="metric stream updates per second at most (monitor; 0 = every row)")
    parser.add_argument("--prometheus-port", type=int, default=None,
                        help="the monitor serves Prometheus /metrics on PORT (env MORPH_PROMETHEUS_PORT; default off)")
    parser.add_argument("--prometheus-host", default="127.0.0.1", help="address of /metrics (default 127.0.0.1)")
    parser.add_argument("--prometheus-grace", type=float, default=15.0,
                        help="seconds /metrics keeps serving the final values after the run (default 15)")
    parser.add_argument("--bus-record", default=None, metavar="FILE",
                        help="also record the run's messages from its first tick to FILE (the monitor writes "
                             "what it receives, all but its own metric streams and events; `morph-sim replay FILE` "
                             "recomputes the record; `morph-sim record` joins a run already going)")
    parser.add_argument("--insecure", action="store_true",
                        help="open endpoint: no credentials, no access control (anyone who reaches the endpoint "
                             "can publish anything); default: per-run credentials in <record>/credentials")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from services.runconfig import config_from_args
    from services.supervisor.launcher import StartError, Supervisor

    config = config_from_args(args)
    monitor_args, grace = monitor_flags(args)
    claim_record_dir(config.record_dir)
    try:  # the live line needs the [cli] extra; a service-only install (a container) prints the last line alone
        from rich.console import Console
    except ImportError:
        Console = None
    console = Console(stderr=True) if Console is not None else None
    status = None

    def show(progress, line: str) -> None:
        if status is not None:
            status.update(line)
        if progress.finished:
            if console is not None:
                console.print(line)
            else:
                print(line, file=sys.stderr)

    try:
        supervisor = Supervisor(config, on_progress=show, insecure=args.insecure, monitor_args=monitor_args,
                                end_grace=grace)
    except (StartError, ValueError) as exc:
        # refused before any process started: the directory this call created goes, so the run id stays free for
        # the corrected command
        shutil.rmtree(config.record_dir, ignore_errors=True)
        if isinstance(exc, ValueError):
            raise  # bad configuration: one line, exit 2
        print(f"morph-sim up: error: {exc}", file=sys.stderr)
        return 1
    try:
        supervisor.prestart()  # while this process is one thread: before the live line's
    except StartError as exc:
        print(f"morph-sim up: error: {exc}", file=sys.stderr)
        return 1
    if not args.quiet and console is not None:
        status = console.status("starting …")
        status.start()
    if supervisor.credentials is not None:
        # the operator commands read the endpoint and the credentials from the record, which they look for under
        # their own --output-dir (default runs)
        elsewhere = "" if Path(config.output_dir) == Path("runs") else f" --output-dir {config.output_dir}"
        print(f"run {config.run_id}: secured endpoint {supervisor.endpoint}; operator credentials "
              f"{supervisor.credentials.operator} (watch/faults/record/stop find them with --run {config.run_id}"
              f"{elsewhere})", file=sys.stderr)
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
    check = supervisor.check
    numbers = (f"{check.rows} rows, {check.deliveries} deliveries, " if check is not None and check.rows else "")
    print(f"run {config.run_id}: {supervisor.outcome}; {numbers}{len(supervisor.children)} processes, "
          f"{restarts} restarts; record: {config.record_dir}")
    return code


def monitor_flags(args: argparse.Namespace) -> tuple[tuple[str, ...], float]:
    """The monitor's own flags from up's, checked before any process starts (a busy port is named now, not in a
    child's log); and the seconds the monitor keeps serving after the run."""
    import os
    import socket

    from services.inputs import finite, output_file

    finite(args.max_rate, "max_rate", at_least=0)
    finite(args.prometheus_grace, "prometheus_grace", at_least=0)
    flags: list[str] = ["--max-rate", repr(float(args.max_rate))]
    if args.bus_record:
        flags += ["--bus-record", str(output_file(args.bus_record, "bus_record", parents=True).resolve())]
    port = args.prometheus_port
    if port is None and os.environ.get("MORPH_PROMETHEUS_PORT"):
        try:
            port = int(os.environ["MORPH_PROMETHEUS_PORT"])
        except ValueError:
            raise ValueError(f"MORPH_PROMETHEUS_PORT: not a port: {os.environ['MORPH_PROMETHEUS_PORT']!r}") from None
    if port is None:
        return tuple(flags), 0.0
    if not 0 < port < 65536:
        raise ValueError(f"prometheus_port: {port} is not a TCP port (1-65535)")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((args.prometheus_host, port))
        except OSError as exc:
            raise ValueError(f"prometheus_port: {args.prometheus_host}:{port} is not available "
                             f"({exc.strerror or exc})") from None
    flags += ["--prometheus-port", str(port), "--prometheus-host", args.prometheus_host,
              "--prometheus-grace", repr(float(args.prometheus_grace))]
    return tuple(flags), float(args.prometheus_grace)


def claim_record_dir(directory, how: str = "choose another --run-id or remove it") -> None:
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
        raise ValueError(f"run_id: {directory} exists (a run with this id was recorded there); {how}") from None
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
