"""A restarted agent restores its plasticity state from the latest published states: the restored brain's
state message equals the last one published (W row, links, thresholds, ages, h, η, d̂), for both MORPH presets."""

from __future__ import annotations

import numpy as np
import pytest

from services.agent.roles import make_agent
from services.bus import LocalNetwork
from services.faults.restore import restore_brains
from services.protocol.tick import first_in_mission_order
from services.runconfig import RunConfig
from services.sim.wire import make_controller


def trained_agents(config: RunConfig, net: LocalNetwork):
    agents = [make_agent(config, net.session(str(i)), i) for i in range(config.n_agents)]
    ctl = make_controller(config)
    for _ in range(120):  # every agent learns from every tick and each AGV decides with its own brain, as over the bus
        obs = ctl.begin_tick()
        for a in agents:
            a.brains.learn(obs)
        requests = []
        for agv in obs.requesters().tolist():
            brains = agents[agv].brains
            picker = brains.candidate(agv, obs)
            if picker >= 0 and brains.draw(agv) < brains.probability(agv, picker, obs):
                requests.append((agv, picker))
        ctl.commit(first_in_mission_order(requests))
        ctl.finish_tick()
    return agents, ctl.t


@pytest.mark.parametrize("preset", ["reference", "paper"])
def test_restored_state_equals_the_last_published(preset: str) -> None:
    config = RunConfig(run_id="rs", scale="tiny", policy="morph", preset=preset, seed=7, steps=200)
    net = LocalNetwork()
    agents, t = trained_agents(config, net)
    published = {a.id: a.state_message(t) for a in agents}
    victim = 2
    assert any(published[victim].w_row)  # a state worth restoring
    fresh = make_agent(config, net.session("2b"), victim)
    assert not any(fresh.state_message(t).w_row)
    assert restore_brains(fresh.brains, victim, published) == t
    restored = fresh.state_message(t)
    for field in ("w_row", "a_row", "theta_row", "age_row", "h", "eta", "d_hat", "t"):
        assert getattr(restored, field) == getattr(published[victim], field), field
    if preset == "reference":  # the whole symmetric replica comes back from every agent's row
        original = agents[victim].brains
        assert np.array_equal(fresh.brains.state.W[0], original.state.W[original._rep[0]])
    assert restore_brains(fresh.brains, 9, {}) is None


async def test_restart_restores_from_the_real_monitor_over_the_bus() -> None:
    import asyncio

    from services.faults.restore import fetch_states
    from services.monitor.service import MonitorService

    config = RunConfig(run_id="rs2", scale="tiny", policy="morph", preset="paper", seed=3, steps=200)
    net = LocalNetwork()
    monitor = MonitorService(config, net.session("monitor"), record=False)
    task = asyncio.get_running_loop().create_task(monitor.run())
    try:
        await asyncio.sleep(0.01)
        agents, t = trained_agents(config, net)
        t = (t // config.state_every) * config.state_every  # a W-sample tick
        for a in agents:
            await a.bus.publish(a.keys.agent_state(a.id), a.state_message(t))
        await asyncio.sleep(0.05)
        restarted = make_agent(config, net.session("4-restarted"), 4)
        states = await fetch_states(restarted.bus, config.run_id, timeout=1.0)
        assert sorted(states) == list(range(config.n_agents))
        assert restore_brains(restarted.brains, 4, states) == t
        assert restarted.state_message(t).w_row == agents[4].state_message(t).w_row
    finally:
        monitor.stop()
        await asyncio.wait_for(task, 5)
