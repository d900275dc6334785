"""``morph-sim run``: the sim, every agent and the monitor as tasks of one event loop over a LocalBus.

Same service code as the distributed run; LocalBus delivers in a fixed order, so the run is deterministic and fast.
The lab and most tests use it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass

from services.agent.roles import make_agent
from services.agent.service import AgentCounters
from services.bus.base import Bus
from services.bus.local import LocalNetwork
from services.monitor.service import MonitorResult, MonitorService
from services.runconfig import RunConfig
from services.sim.result import SimResult
from services.sim.service import SimService


@dataclass
class LocalRun:
    sim: SimResult
    monitor: MonitorResult
    agents: list[AgentCounters]


async def run_local(config: RunConfig, *, record: bool = True, network: LocalNetwork | None = None,
                    on_bus: Callable[[str, Bus], None] | None = None, faults=None,
                    progress: Callable[[int, int], None] | None = None) -> LocalRun:
    """Run ``config`` in this loop. ``on_bus(name, bus)`` sees every session (tests install fault layers there);
    ``progress(t, deliveries so far)`` is called at the start of every tick.

    ``faults``: a FaultRuntime for the sim's session (default: one when ``config.fault_schedule`` is set);
    every agent session then gets its own runtime like it (``FaultRuntime.like``: same seed, Δ, fault time and
    schedule), as each agent process of ``morph-sim up`` has, and the monitor stamps the sim's clock."""
    if faults is None and (config.fault_schedule or config.network):
        from services.faults.runtime import FaultRuntime

        faults = FaultRuntime.for_service(config, "sim")
    net = network or LocalNetwork()
    buses: list[Bus] = []

    def session(name: str) -> Bus:
        bus = net.session(name)
        buses.append(bus)
        if faults is not None and faults.vtime is not None:
            bus.set_clock(faults.now)
        if on_bus is not None:
            on_bus(name, bus)
        return bus

    monitor = MonitorService(config, session("monitor"), record=record)
    agents = [make_agent(config, session(f"agent-{i}"), i, faults=None if faults is None else faults.like())
              for i in range(config.n_agents)]
    sim = SimService(config, session("sim"), faults=faults,
                     on_tick=None if progress is None else lambda t, obs: progress(t, sim.ctl.deliveries))
    tasks = [asyncio.create_task(monitor.run(), name="monitor")]
    tasks += [asyncio.create_task(a.run(), name=f"agent-{a.id}") for a in agents]
    air = None
    if config.shared_air:  # the radio's shared capacity: its own service, as in `up`
        from services.air.service import AirService

        air = asyncio.create_task(AirService(config, session("air")).run(), name="air")
    try:
        sim_result = await sim.run()
        done, pending = await asyncio.wait(tasks + ([air] if air is not None else []),
                                           timeout=max(5.0, config.phase_timeout))
        for task in done:
            task.result()  # surface a crashed service
        if pending:
            raise RuntimeError(f"services did not stop after the run: {sorted(t.get_name() for t in pending)}")
        return LocalRun(sim_result, tasks[0].result(), [t.result() for t in tasks[1:]])
    finally:
        for task in tasks + ([air] if air is not None else []):
            if not task.done():
                task.cancel()
        for bus in buses:
            await bus.close()
