"""``morph-sim run``: sim, agents and monitor in one process over LocalBus (deterministic, no network)."""

from __future__ import annotations

import argparse
import asyncio
import sys
import time

NAME = "run"
HELP = "run all services in one process over the in-process bus (deterministic)"
PROGRESS_EVERY = 2.0  # seconds between progress lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--no-record", action="store_true", help="do not write runs/<run-id>/")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    add_config_arguments(parser, skip=("endpoint", "listen"))


def run(args: argparse.Namespace) -> int:
    from morph_sim.local import run_local
    from services.runconfig import config_from_args

    config = config_from_args(args)
    if config.fault_schedule:
        from services.faults.schedule import load_schedule

        crashes = [i for i, c in enumerate(load_schedule(config.fault_schedule).at) if c.spec and c.spec.crash]
        if crashes:  # nobody here kills and restarts processes: say so instead of running without the crash
            raise ValueError(f"fault_schedule: at[{crashes[0]}] is a crash fault, which needs agent processes and "
                             "a supervisor to kill and restart them: use `morph-sim up`")
    faults = None
    if config.network is not None or config.fault_schedule:
        from services.faults.runtime import FaultRuntime

        faults = FaultRuntime.for_service(config, "sim")
    if not args.no_record:
        from morph_sim.commands.up import claim_record_dir

        claim_record_dir(config.record_dir)
    started = time.monotonic()
    shown = [started]

    def progress(t: int, deliveries: int) -> None:  # a line every PROGRESS_EVERY seconds, on stderr
        now = time.monotonic()
        if now - shown[0] >= PROGRESS_EVERY and not args.quiet:
            shown[0] = now
            print(f"tick {t}/{config.steps}  deliveries {deliveries}  {t / (now - started):.0f} ticks/s",
                  file=sys.stderr, flush=True)

    result = asyncio.run(run_local(config, record=not args.no_record, faults=faults, progress=progress))
    wall = time.monotonic() - started
    rows = result.monitor.rows
    links = rows[-1]["links"] if rows else 0
    print(f"run {config.run_id}: {config.scale} {config.n_agvs}+{config.n_pickers} policy {config.policy}"
          f"{'/' + config.preset if config.policy == 'morph' else ''} seed {config.seed}: "
          f"{result.sim.steps} ticks, {result.sim.deliveries} deliveries, {links} links at the end, "
          f"{result.sim.steps / wall:.0f} ticks/s")
    comm = result.monitor.communication(result.sim.steps, config.n_agents)
    print(f"communication: {comm['messages']} protocol messages, {comm['bytes'] / 1000:.1f} kB"
          + (f"; per delivery {comm['messages_per_delivery']:.1f} messages, {comm['bytes_per_delivery']:.0f} B"
             if comm["messages_per_delivery"] is not None else "; no delivery")
          + f"; per agent per tick {comm['messages_per_agent_tick']:.2f} messages, "
            f"{comm['bytes_per_agent_tick']:.0f} B")
    if faults is not None and faults.network is not None:
        lost = faults.network_losses()
        print(f"network {config.network}: {len(faults.network.events)} hand-overs, "
              f"{faults.network.stats.outage_seconds:.1f} robot-seconds of outage, "
              f"{result.sim.network_stops} robot-steps stopped by silence; "
              + ("lost " + ", ".join(f"{n} to {cause}" for cause, n in lost.items() if n) if any(lost.values())
                 else "nothing lost"))
    if not args.no_record:
        print(f"record: {config.record_dir}")
    return 0
