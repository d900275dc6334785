"""Which agent a robot id gets: an AGV's or a picker's."""

from __future__ import annotations

from services.agent.agv import AgvService
from services.agent.picker import PickerService
from services.agent.service import AgentCounters, AgentService
from services.bus.base import Bus
from services.runconfig import RunConfig


def make_agent(config: RunConfig, bus: Bus, agent_id: int, **options) -> AgentService:
    """The agent of robot ``agent_id`` of the run of ``config`` over ``bus`` (AGVs first, then pickers);
    ``options``: :class:`AgentService`'s keywords (``restore``, ``faults``)."""
    if not 0 <= agent_id < config.n_agents:
        raise ValueError(f"id: agent {agent_id} outside 0..{config.n_agents - 1} for this fleet")
    role = AgvService if agent_id < config.n_agvs else PickerService
    return role(config, bus, agent_id, **options)


async def run_agent(config: RunConfig, bus: Bus, agent_id: int) -> AgentCounters:
    return await make_agent(config, bus, agent_id).run()
