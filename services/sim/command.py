"""``morph-sim sim`` / ``python -m services.sim``: the warehouse clock service as its own process (it hosts the
Zenoh endpoint by default)."""

from __future__ import annotations

import argparse
import json
import sys

NAME = "sim"
HELP = "run the sim clock service (warehouse + tick protocol) over Zenoh"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.envconfig import apply_env_defaults
    from services.runconfig import add_config_arguments

    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    parser.add_argument("--no-wait-monitor", action="store_true", help="start without a monitor")
    add_config_arguments(parser)
    apply_env_defaults(parser)  # per-command flags follow MORPH_LOG_LEVEL … like the RunConfig flags



def run(args: argparse.Namespace) -> int:
    from services.process import announce, exit_now, run_or_exit, serve, service_config, setup_logging
    from services.sim.service import SimService

    config = service_config(args)
    if not config.listen and not config.endpoint:
        raise ValueError("listen: the sim needs --listen ENDPOINT (host the run) or --endpoint ENDPOINT (router)")
    setup_logging(args.log_level, "sim")
    import os

    from services.process import ZENOH_CONFIG_ENV

    if config.listen and not os.environ.get(ZENOH_CONFIG_ENV):
        # hosting an endpoint without a config file means no credentials and no access control (docs/deploy.md)
        print(f"morph-sim sim: warning: the endpoint {config.listen} is open (no {ZENOH_CONFIG_ENV}): anyone who "
              "reaches it can stop the run or forge messages; `morph-sim credentials` writes a secured setup",
              file=sys.stderr)

    def make(bus):
        service = SimService(config, bus, wait_for_monitor=not args.no_wait_monitor, faults=_faults(config))
        where = f"listening on {config.listen}" if config.listen else f"connected to {config.endpoint}"
        announce(NAME, f"run {config.run_id}, {where}; waiting for {config.n_agents} agents"
                       f"{'' if args.no_wait_monitor else ' and the monitor'} ({config.steps} steps)")
        return service

    result = run_or_exit(NAME, serve(
        "sim", make,
        lambda svc: svc.run(), lambda svc, why: svc.stop(why), listen=config.listen, connect=config.endpoint))
    print(json.dumps({"steps": result.steps, "deliveries": result.deliveries, "rejected": result.rejected,
                      "absences": result.absences, "ticks_per_s": round(result.ticks_per_s, 1),
                      "stopped_early": result.stopped_early}))
    exit_now(0)  # a run ended by a stop request is a clean end; errors exit non-zero with a traceback
    return 1  # not reached


def _faults(config):
    """The sim's fault runtime: ``morph-sim faults set|list|reset`` reaches it on ctl/faults; in the run's
    fault time (``--fault-time``, virtual by default: every agent process runs its own clock, docs/faults.md)."""
    from services.faults.runtime import FaultRuntime

    # Crash faults are the supervisor's alone (it carries them out and records each crash at its tick): the sim gives
    # no verdict on them, so `faults set` never reports a crash the sim accepted but nobody carried out.
    return FaultRuntime.for_service(config, "sim")
