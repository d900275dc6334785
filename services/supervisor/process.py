"""Running one service as its own OS process over Zenoh (``morph-sim sim|agent|monitor``).

Opens the session (the sim listens as the Zenoh router of the run unless an external endpoint is given; every other
process connects as a client — peers do not route between each other, see docs/services.md), turns SIGTERM/SIGINT
into the service's own stop, and always closes the session within a bounded time.
"""

from __future__ import annotations

import asyncio
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


ZENOH_CONFIG_ENV = "ZENOH_CONFIG"  # path of a Zenoh config file (zenoh's own convention): credentials, TLS …


def base_zenoh_config(environ: dict[str, str] | None = None):
    """The deployment's Zenoh config named by ``ZENOH_CONFIG`` (e.g. deploy/zenoh/client-agent-0.json5, which
    carries the user/password an ACL router checks), or None. A bad path or file is a ValueError naming it."""
    import os

    import zenoh

    path = (os.environ if environ is None else environ).get(ZENOH_CONFIG_ENV)
    if not path:
        return None
    try:
        return zenoh.Config.from_file(path)
    except Exception as exc:  # zenoh raises its own ZError for a missing or malformed file
        raise ValueError(f"{ZENOH_CONFIG_ENV}: cannot read Zenoh config {path!r}: {exc}") from None


async def open_bus(identity: str, *, listen: str | None = None, connect: str | None = None):
    from services.bus.zenoh_bus import ZenohBus, zenoh_config

    if not listen and not connect:
        raise ValueError("endpoint: a distributed service needs --endpoint (or --listen for the sim)")
    # our endpoints, mode and transport settings go on top of the deployment's file (if any)
    mode = "router" if listen else "client"
    config = zenoh_config(listen=listen, connect=None if listen else connect, mode=mode,
                          base=base_zenoh_config())
    return await ZenohBus.open(identity, listen=listen, connect=None if listen else connect, mode=mode,
                               config=config)


async def serve(identity: str, make: Callable[[Any], Any], run: Callable[[Any], Awaitable[Any]],
                stop: Callable[[Any, str], None], *, listen: str | None = None, connect: str | None = None
                ) -> Any:
    """Open the bus, build the service with ``make(bus)``, ``await run(service)``; signals call ``stop``."""
    bus = await open_bus(identity, listen=listen, connect=connect)
    loop = asyncio.get_running_loop()
    try:
        service = make(bus)
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
