"""Running one service as its own OS process over Zenoh (``morph-sim sim|agent|monitor``).

Opens the session (the sim listens as the Zenoh router of the run unless an external endpoint is given; every other
process connects as a client — peers do not route between each other, see docs/services.md), turns SIGTERM/SIGINT
into the service's own stop, and always closes the session within a bounded time.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import sys
from collections.abc import Awaitable, Callable
from typing import Any

log = logging.getLogger("morph_sim.process")


def setup_logging(level: str = "WARNING", name: str = "") -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.WARNING), stream=sys.stderr,
                        format=f"%(asctime)s {name} %(levelname)s %(name)s: %(message)s")


def service_config(args):
    """Config of a standalone service: the run id must be given (flag or MORPH_RUN_ID), never generated."""
    import os

    from services.runconfig import RunConfig, config_from_args

    if getattr(args, "cfg_run_id", None) is None and not os.environ.get(RunConfig.env_name("run_id")):
        raise ValueError("run_id: a service process needs --run-id (or MORPH_RUN_ID) so it joins the right run")
    return config_from_args(args)


def command_main(command, argv=None) -> int:
    """``python -m services.<name>``: the same flags, help and one-line errors as ``morph-sim <name>``."""
    import argparse

    parser = argparse.ArgumentParser(prog=f"python -m services.{command.NAME}", description=command.HELP)
    command.add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return int(command.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ValueError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    except ConnectionError as exc:  # no endpoint there, or it refuses these credentials: one line
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 1


ZENOH_CONFIG_ENV = "ZENOH_CONFIG"  # path of a Zenoh config file (zenoh's own convention): credentials, TLS …


def base_zenoh_config(environ: dict[str, str] | None = None, path: str | None = None, what: str = ZENOH_CONFIG_ENV):
    """The deployment's Zenoh config named by ``path`` or else ``ZENOH_CONFIG`` (e.g. a run's
    ``credentials/agent-0.json5``, which carries the user/password the endpoint checks), or None. A bad path or file
    is a ValueError naming it."""
    import os

    import zenoh

    if not path:
        path = (os.environ if environ is None else environ).get(ZENOH_CONFIG_ENV)
    if not path:
        return None
    from services.inputs import input_file

    input_file(path, what)  # zenoh reads the file whole: not a directory, a device, nor one of any size
    try:
        return zenoh.Config.from_file(path)
    except Exception as exc:  # zenoh raises its own ZError for a missing or malformed file
        raise ValueError(f"{what}: cannot read Zenoh config {path!r}: {exc}") from None


async def open_bus(identity: str, *, listen: str | None = None, connect: str | None = None,
                   config_file: str | None = None, what: str = ZENOH_CONFIG_ENV, connect_timeout: float = 10.0):
    """A session on the run: ``listen`` hosts the endpoint, ``connect`` joins it (giving up after
    ``connect_timeout`` seconds). The Zenoh config file (credentials, access control) is ``config_file``, else the one
    ``ZENOH_CONFIG`` names, else none (an open endpoint)."""
    from services.bus.zenoh_bus import ZenohBus, zenoh_config

    if not listen and not connect:
        raise ValueError("endpoint: a distributed service needs --endpoint (or --listen for the sim)")
    # our endpoints, mode and transport settings go on top of the deployment's file (if any)
    mode = "router" if listen else "client"
    config = zenoh_config(listen=listen, connect=None if listen else connect, mode=mode,
                          connect_timeout=connect_timeout, base=base_zenoh_config(path=config_file, what=what))
    return await ZenohBus.open(identity, listen=listen, connect=None if listen else connect, mode=mode,
                               config=config, connect_timeout=connect_timeout)


DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"  # where an operator command looks when nothing tells it where the run is


def add_operator_arguments(parser) -> None:
    """``--endpoint``, ``--credentials``, ``--connect-timeout`` and ``--output-dir`` of the operator commands (watch,
    faults, record, stop)."""
    parser.add_argument("--endpoint", default=None,
                        help="Zenoh endpoint of the run (default: where the run of --run ID is hosted, from its "
                             f"record <output-dir>/<run>/credentials/where or manifest.json; else {DEFAULT_ENDPOINT})")
    parser.add_argument("--credentials", default=None, metavar="FILE",
                        help="Zenoh config with the operator's user/password (default: $ZENOH_CONFIG, else "
                             "<output-dir>/<run>/credentials/operator.json5 written by `morph-sim up`)")
    parser.add_argument("--connect-timeout", type=float, default=10.0, metavar="SECONDS",
                        help="give up when the endpoint does not answer within this time (default 10)")
    if not any(a.dest in ("output_dir", "cfg_output_dir") for a in parser._actions):
        parser.add_argument("--output-dir", default="runs", help="parent directory of run records (default runs)")


def operator_credentials(args, run_id: str | None, output_dir=None) -> str | None:
    """The operator's Zenoh config file for ``run_id``: ``--credentials``, ``ZENOH_CONFIG``, the run directory's
    ``credentials/operator.json5``, or None (an insecure run)."""
    from pathlib import Path

    from services.credentials import operator_config_path

    if getattr(args, "credentials", None):
        return args.credentials
    out = Path(output_dir if output_dir is not None else getattr(args, "output_dir", None) or "runs")
    if run_id is None:
        import os

        from services.credentials import find_operator_config

        return os.environ.get(ZENOH_CONFIG_ENV) or find_operator_config(out, operator_endpoint(args, None))
    return operator_config_path(out / run_id)


def operator_endpoint(args, run_id: str | None, output_dir=None) -> str:
    """The endpoint an operator command connects to: ``--endpoint``; else where run ``run_id`` is hosted, as its
    record says (``credentials/where``, written by ``up`` before any process starts; else the endpoint in the
    monitor's ``manifest.json``, which an ``--insecure`` run has too); else :data:`DEFAULT_ENDPOINT`. ``up`` hosts
    a run on a free port, so the record is the only place that knows it.

    Every operator command asks for its endpoint before it connects, so this is where the operator options are
    checked: the endpoint (wherever it came from), ``--connect-timeout`` and the ``--credentials`` file."""
    from services.inputs import endpoint, finite, input_file

    if getattr(args, "connect_timeout", None) is not None:
        finite(args.connect_timeout, "connect_timeout", above=0)
    if getattr(args, "credentials", None):
        input_file(args.credentials, "credentials")
    if getattr(args, "endpoint", None):
        return endpoint(args.endpoint, "endpoint")
    where, source = _recorded_endpoint(args, run_id, output_dir)
    return endpoint(where, f"endpoint (from {source})") if where else DEFAULT_ENDPOINT


def _recorded_endpoint(args, run_id: str | None, output_dir=None) -> tuple[str, str]:
    """(endpoint, the file that says so) for run ``run_id`` from its record, or ("", "")."""
    import json
    from pathlib import Path

    from services.credentials import WHERE_FILE, run_credentials
    from services.inputs import read_text

    if run_id is None:
        return "", ""
    record = Path(output_dir if output_dir is not None else getattr(args, "output_dir", None) or "runs") / run_id
    where_file = run_credentials(record).directory / WHERE_FILE
    try:
        where = read_text(where_file, "endpoint").strip() if where_file.exists() else ""
    except ValueError:
        where = ""
    if where:
        return where, str(where_file)
    try:
        manifest = read_text(record / "manifest.json", "endpoint") if (record / "manifest.json").exists() else "{}"
        where = json.loads(manifest).get("config", {}).get("endpoint") or ""
    except (ValueError, AttributeError):
        where = ""
    return (where, str(record / "manifest.json")) if where else ("", "")


async def open_operator_bus(identity: str, endpoint: str, args, run_id: str | None, output_dir=None):
    """An operator command's session: with the run's operator credentials when it has them (secure by default)."""
    path = operator_credentials(args, run_id, output_dir)
    try:
        return await open_bus(identity, connect=endpoint, config_file=path,
                              what="credentials" if path and getattr(args, "credentials", None) else ZENOH_CONFIG_ENV,
                              connect_timeout=getattr(args, "connect_timeout", 10.0))
    except ConnectionError as exc:
        hint = (f" (used credentials {path})" if path else
                " (no credentials: a secured run needs its operator credentials, --credentials FILE or --run ID "
                "with --output-dir where `morph-sim up` wrote them)")
        raise ConnectionError(f"{exc}{hint}") from None


async def serve(identity: str, make: Callable[[Any], Any], run: Callable[[Any], Awaitable[Any]],
                stop: Callable[[Any, str], None], *, listen: str | None = None, connect: str | None = None
                ) -> Any:
    """Open the bus, build the service with ``make(bus)``, ``await run(service)``; signals call ``stop``."""
    bus = await open_bus(identity, listen=listen, connect=connect)
    loop = asyncio.get_running_loop()
    try:
        service = make(bus)
        # Everything imported and built so far lives as long as the process: out of the collector's sight, each
        # collection during the run scans only what the run allocates (the process is this one service). No
        # collection first: it would cost every process tens of milliseconds to free a few startup leftovers.
        gc.freeze()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop, service, signal.Signals(sig).name)
        return await run(service)
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                loop.remove_signal_handler(sig)
            except Exception:
                pass
        await bus.close()


def announce(command: str, line: str) -> None:
    """The one line a service prints when its session is open (a process started by hand says where it is and
    what it waits for; under ``up`` the line goes to the child's log)."""
    print(f"morph-sim {command}: {line}", file=sys.stderr, flush=True)


def exit_now(code: int) -> None:
    """Leave without interpreter teardown: Zenoh's native threads can abort a normal exit (measured with zenoh 1.10.2)."""
    import os

    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(code)


def run_or_exit(command: str, main: Awaitable[Any]) -> Any:
    """``asyncio.run(main)``; a session that cannot open ends the process with one clear line and status 1."""
    try:
        return asyncio.run(main)
    except ConnectionError as exc:
        print(f"morph-sim {command}: error: {exc}", file=sys.stderr)
        exit_now(1)
