"""``morph-sim agent --id N``: one robot's coordination brain as its own process."""

from __future__ import annotations

import argparse
import json

NAME = "agent"
HELP = "run one agent service (AGV or picker brain) over Zenoh"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from morph_sim.services.runconfig import add_config_arguments

    parser.add_argument("--id", type=int, required=True, help="robot id (AGVs first, then pickers)")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    add_config_arguments(parser, skip=("listen",))


def run(args: argparse.Namespace) -> int:
    from morph_sim.commands.sim import service_config
    from morph_sim.services.agent.service import AgentService
    from morph_sim.services.supervisor.process import exit_now, run_or_exit, serve, setup_logging

    config = service_config(args)
    config.role_of(args.id)  # ValueError naming the agent id if it is outside the fleet
    if not config.endpoint:
        raise ValueError("endpoint: an agent needs --endpoint ENDPOINT (e.g. tcp/127.0.0.1:7447)")
    setup_logging(args.log_level, f"agent-{args.id}")
    counters = run_or_exit(NAME, serve(
        f"agent-{args.id}", lambda bus: AgentService(config, bus, args.id), lambda svc: svc.run(),
        lambda svc, why: svc.stop(), connect=config.endpoint))
    print(json.dumps({"agent": args.id, "ticks": counters.ticks, "requests": counters.requests,
                      "commits": counters.commits, "rejected": counters.rejected}))
    exit_now(0)
    return 1  # not reached
