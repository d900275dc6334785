"""``morph-sim agent [--id N]`` / ``python -m services.agent``: one robot's coordination brain as its own process.

Without ``--id`` the agent claims an id from the sim's registry (``morph/<run>/registry``) under its instance name
(``--instance``, ``MORPH_INSTANCE``, else the host name and pid), so identical containers, or processes on one host,
can be started without numbering them; a restarted agent gets its robot back in a running run.
"""

from __future__ import annotations

import argparse
import asyncio
import json

NAME = "agent"
HELP = "run one agent service (AGV or picker brain) over Zenoh"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.envconfig import apply_env_defaults
    from services.runconfig import add_config_arguments

    parser.add_argument("--id", type=int, default=None,
                        help="robot id (AGVs first, then pickers); default: claim one from the sim's registry")
    parser.add_argument("--instance", default=None,
                        help="name this agent registers under when it claims an id (default: MORPH_INSTANCE, "
                             "else HOSTNAME-PID)")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    add_config_arguments(parser, skip=("listen",))
    apply_env_defaults(parser)


class ClaimingAgent:
    """Claims a robot id (unless one is given), then runs that robot's :class:`AgentService`."""

    def __init__(self, config, bus, agent_id: int | None, instance: str | None):
        self.config, self.bus = config, bus
        self.agent_id, self.instance = agent_id, instance
        self.role = None if agent_id is None else config.role_of(agent_id)
        self.service = None
        self._claim: asyncio.Task | None = None
        self._stopped = False

    async def run(self):
        from schemas.keys import RunKeys
        from services.agent.roles import make_agent
        from services.agent.service import AgentCounters
        from services.bus.registry import claim_id, default_instance

        if self.agent_id is None:
            self.instance = self.instance or default_instance()
            self._claim = asyncio.ensure_future(claim_id(
                self.bus, RunKeys(self.config.run_id), self.instance, timeout=self.config.ready_timeout))
            try:
                reply = await self._claim
            except asyncio.CancelledError:
                if self._stopped:
                    return AgentCounters()
                raise
            if (reply.n_agvs, reply.n_pickers) != (self.config.n_agvs, self.config.n_pickers):
                raise ValueError(f"agvs/pickers: the sim's fleet is {reply.n_agvs}+{reply.n_pickers}, this agent's "
                                 f"configuration {self.config.n_agvs}+{self.config.n_pickers}")
            self.agent_id, self.role = reply.agent_id, reply.role
        self._claim = asyncio.ensure_future(self._check_policy())  # a stop while it waits cancels it
        try:
            await self._claim
        except asyncio.CancelledError:
            if self._stopped:
                return AgentCounters()
            raise
        from services.process import announce

        announce("agent", f"agent {self.agent_id} ({self.config.role_of(self.agent_id)}) of run {self.config.run_id}, "
                          f"connected to {self.config.endpoint}; waiting for the sim's ticks")
        # a (re)started agent restores its brain from the monitor's latest states unless --cold-restart
        from services.faults.runtime import FaultRuntime

        # its own fault runtime: ingress faults, ctl/faults, the clock of the run's fault time (docs/faults.md)
        self.service = make_agent(self.config, self.bus, self.agent_id, restore=not self.config.cold_restart,
                                    faults=FaultRuntime.for_service(self.config, "agent"))
        if self._stopped:
            return AgentCounters()
        return await self.service.run()

    async def _check_policy(self) -> None:
        """Join only a run whose sim built the same policy as this agent (ValueError naming both otherwise)."""
        from schemas.keys import RunKeys
        from services.bus.registry import fetch_policy
        from services.protocol.registry import policy_mismatch

        announced = await fetch_policy(self.bus, RunKeys(self.config.run_id), timeout=self.config.ready_timeout)
        why = policy_mismatch(self.config.policy_announcement(), announced)
        if why is not None:
            raise ValueError(why)

    def stop(self) -> None:
        self._stopped = True
        if self.service is not None:
            self.service.stop()
        elif self._claim is not None:
            self._claim.cancel()


def run(args: argparse.Namespace) -> int:
    from services.process import exit_now, run_or_exit, serve, service_config, setup_logging

    config = service_config(args)
    if args.id is not None:
        config.role_of(args.id)  # ValueError naming the agent id if it is outside the fleet
    if not config.endpoint:
        raise ValueError("endpoint: an agent needs --endpoint ENDPOINT (e.g. tcp/127.0.0.1:7447)")
    if args.id is None:
        from services.bus.registry import default_instance

        args.instance = args.instance or default_instance()
    setup_logging(args.log_level, f"agent-{args.id if args.id is not None else args.instance}")
    holder: dict[str, ClaimingAgent] = {}

    def make(bus) -> ClaimingAgent:
        holder["agent"] = ClaimingAgent(config, bus, args.id, args.instance)
        return holder["agent"]

    counters = run_or_exit(NAME, serve(
        f"agent-{args.id}" if args.id is not None else f"agent-{args.instance}", make,
        lambda svc: svc.run(), lambda svc, why: svc.stop(), connect=config.endpoint))
    agent = holder["agent"]
    print(json.dumps({"agent": agent.agent_id, "role": agent.role, "instance": agent.instance,
                      "ticks": counters.ticks, "requests": counters.requests, "commits": counters.commits,
                      "rejected": counters.rejected}))
    exit_now(0)
    return 1  # not reached
