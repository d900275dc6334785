"""``morph-sim air`` / ``python -m services.air``: the shared air of a run whose network profile limits rates, as its
own process (services/air/service.py)."""

from __future__ import annotations

import argparse
import json

NAME = "air"
HELP = "run the shared air (the radio of a rate-limited network profile) over Zenoh"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.envconfig import apply_env_defaults
    from services.runconfig import add_config_arguments

    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    add_config_arguments(parser, skip=("listen",))
    apply_env_defaults(parser)


def run(args: argparse.Namespace) -> int:
    from services.process import announce, exit_now, run_or_exit, serve, service_config, setup_logging

    config = service_config(args)
    if not config.endpoint:
        raise ValueError("endpoint: the air needs --endpoint ENDPOINT (e.g. tcp/127.0.0.1:7447)")
    if not config.shared_air:
        raise ValueError(f"network: the air judges a profile with shared capacity (link_rate/ap_rate); "
                         f"{config.network or 'no profile'!r} has none, and its run needs no air")
    setup_logging(args.log_level, NAME)

    def make(bus):
        from services.air.service import AirService

        announce(NAME, f"run {config.run_id}, connected to {config.endpoint}; judging profile {config.network}")
        return AirService(config, bus)

    result = run_or_exit(NAME, serve(NAME, make, lambda svc: svc.run(), lambda svc, why: svc.stop(why),
                                     connect=config.endpoint))
    print(json.dumps(result))
    exit_now(0)
    return 1  # not reached
