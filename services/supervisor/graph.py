"""The process graph of a distributed run, as data.

``process_graph(config, endpoint)`` lists every OS process of a run (sim, one agent per robot, monitor, and the air
where the network profile has shared capacity): its name, the
``morph-sim`` command line with real flags, the environment it needs and its restart policy. The supervisor starts
exactly these; docker-compose.yml is tested against them.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from typing import Literal

from services.runconfig import RunConfig

PROGRAM = "morph-sim"

# Zenoh's measured best settings for the lock-step loop (measured: docs/services.md): one app worker thread with every
# other runtime handed over to it; one BLAS thread per process (many processes share 2 cores).
ZENOH_RUNTIME = (
    "(rx: (handover: app), tx: (handover: app), acc: (handover: app), net: (handover: app), "
    "app: (worker_threads: 1))"
)
CHILD_ENV = {
    "ZENOH_RUNTIME": ZENOH_RUNTIME,
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "PYTHONUNBUFFERED": "1",
}

# Config fields every child receives as flags (the endpoint fields are set per role below).
_SHARED_FIELDS = tuple(name for name in RunConfig.model_fields if name not in ("endpoint", "listen"))


@dataclass(frozen=True)
class ProcessSpec:
    """One process of the run."""

    name: str  # "sim", "monitor", "agent-3", "air"
    role: Literal["sim", "agent", "monitor", "air"]
    argv: tuple[str, ...]  # starts with PROGRAM ("morph-sim")
    env: dict[str, str] = field(default_factory=dict)  # added to the parent's environment
    restart: Literal["never", "on-failure"] = "never"
    agent: int | None = None

    def command(self) -> list[str]:
        """The argv to exec here: ``morph-sim <role> …`` runs as ``python -m services.<role> …`` of this interpreter
        (the same flags and environment variables; the service needs none of the tool on top)."""
        assert self.argv[0] == PROGRAM and self.argv[1] == self.role
        return [sys.executable, "-m", f"services.{self.role}", *self.argv[2:]]

    def environment(self, base: dict[str, str] | None = None) -> dict[str, str]:
        return child_environment(self.env, base)


def role_of(cmdline: list[str]) -> str | None:
    """The role of a run's process from its command line (``ps``, psutil): ``sim``, ``agent``, ``monitor``, ``air``,
    or None."""
    for role in ("sim", "agent", "monitor", "air"):
        if f"services.{role}" in cmdline:
            return role
    return None


def child_environment(extra: dict[str, str], base: dict[str, str] | None = None) -> dict[str, str]:
    """``base`` (default: this process's environment) with ``extra`` on top: what a process of the run starts with."""
    env = dict(os.environ if base is None else base)
    if env.get("ZENOH_RUNTIME") == "":  # an empty value makes zenoh panic (zenoh 1.10.2)
        del env["ZENOH_RUNTIME"]
    env.update(extra)
    return env


def process_graph(config: RunConfig, endpoint: str, monitor_args: tuple[str, ...] = ()) -> list[ProcessSpec]:
    """Every process of a distributed run of ``config`` whose Zenoh endpoint is ``endpoint``.

    Without ``config.endpoint`` the sim hosts the endpoint (it listens on ``endpoint``; no router process, which
    we measured 25–45 % slower); with it every process, the sim included, connects to that router.
    """
    shared = config.to_argv(_SHARED_FIELDS)
    external = config.endpoint is not None
    sim_where = ["--endpoint", endpoint] if external else ["--listen", endpoint]
    specs = [ProcessSpec("sim", "sim", (PROGRAM, "sim", *shared, *sim_where), dict(CHILD_ENV), "never")]
    for agent in range(config.n_agents):
        specs.append(ProcessSpec(
            f"agent-{agent}", "agent", (PROGRAM, "agent", "--id", str(agent), *shared, "--endpoint", endpoint),
            dict(CHILD_ENV), "on-failure", agent))
    # on-failure: a restarted monitor appends to the same run record and declares the rows it missed;
    # monitor_args: the monitor's own flags (`up --max-rate/--prometheus-*`)
    specs.append(ProcessSpec("monitor", "monitor", (PROGRAM, "monitor", *shared, "--endpoint", endpoint, *monitor_args),
                             dict(CHILD_ENV), "on-failure"))
    if config.shared_air:
        # never restarted: its queues are the run's radio so far, which a new process could not know
        specs.append(ProcessSpec("air", "air", (PROGRAM, "air", *shared, "--endpoint", endpoint), dict(CHILD_ENV),
                                 "never"))
    return specs
