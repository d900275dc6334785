"""The real services (sim clock, agents, monitor on a LocalBus) under faults in virtual time: requests, replies and
commitments are lost or late (acks are synchronisation and never faulted), late commitments are applied late rather
than dropped, the run never hangs or loses a tick, and the same seed and fault config give the same run twice."""

from __future__ import annotations

import pytest

from morph_sim.local import run_local
from schemas import FaultSpec, Latency, Loss, Scope
from services.faults.runtime import FaultRuntime
from services.faults.schedule import parse_schedule
from services.runconfig import RunConfig

SPEC = FaultSpec(id="agents", loss=Loss(model="gilbert_elliott", percent=25, burst_length=3),
                 latency=Latency(delay=0.3, jitter=0.3), scope=Scope(key_expr="agent/*/**"))


async def faulty_run(config: RunConfig, spec: FaultSpec | None):
    schedule = parse_schedule({"at": [{"tick": 0, "spec": spec.model_dump(exclude_none=True)}]}) if spec else None
    rt = FaultRuntime(config.run_id, seed=config.seed, dt=config.dt, events=True, schedule=schedule)
    run = await run_local(config, record=False, faults=rt)
    return run, rt


async def test_services_under_dispatch_faults_are_live_reproducible_and_late_not_lost() -> None:
    config = RunConfig(run_id="fs", scale="tiny", policy="full", seed=4, steps=120, phase_timeout=5.0)
    clean, _ = await faulty_run(config, None)
    first, rt = await faulty_run(config, SPEC)
    second, _ = await faulty_run(config, SPEC)
    for run in (first, second):
        assert run.sim.steps == 120 and len(run.sim.per_tick_deliveries) == 120  # no tick lost
        assert run.sim.absences == 0  # a lost message is not an absence
    assert first.sim.per_tick_deliveries == second.sim.per_tick_deliveries
    assert first.sim.commits_applied == second.sim.commits_applied
    assert first.sim.protocol == second.sim.protocol
    assert clean.sim.protocol["late_applied"] == 0 and clean.sim.protocol["on_time"] == clean.sim.commits_applied
    assert first.sim.protocol["late_applied"] > 0  # a commitment past its step boundary is applied late, not dropped
    commits = rt.meters["sim"].report()["agent/*/commit"]
    assert commits.late > 0 and commits.delivered > 0
    assert "agent/*/ack" not in rt.meters["sim"].report() or rt.meters["sim"].report()["agent/*/ack"].dropped == 0
    assert [e.kind for e in rt.controller.log] == ["fault.set"] and rt.controller.log[0].t == 0


# The same crash-and-restore cycle runs end to end in the default suite: tests/test_faults_up.py kills a real agent
# process every 80 ticks under `morph-sim up`, and asserts every tick is in the record, each restarted agent resumed
# with the W row its predecessor published last (a learnt one) and took part again. This in-process run takes ~30 s
# of a worker's wall time.
@pytest.mark.slow
async def test_agent_killed_every_100_ticks_rejoins_with_its_state_and_no_tick_is_lost() -> None:
    """In-process crash: the agent's task is cancelled and its session closed (its liveliness token goes, as with
    SIGKILL); a new agent with the same id starts at once, restores its state from the real monitor and rejoins."""
    import asyncio

    from services.agent.roles import make_agent
    from services.bus import LocalNetwork
    from services.monitor.service import MonitorService
    from services.sim.service import SimService

    config = RunConfig(run_id="kill", scale="tiny", policy="morph", preset="paper", seed=5, steps=320,
                       phase_timeout=2.0, state_every=10)
    net = LocalNetwork()
    victim = 6
    monitor = MonitorService(config, net.session("monitor"), record=False)
    agents = {i: make_agent(config, net.session(f"agent-{i}"), i) for i in range(config.n_agents)}
    tasks = {i: asyncio.create_task(a.run()) for i, a in agents.items()}
    mon_task = asyncio.create_task(monitor.run())
    kills: list[tuple[int, object]] = []  # (tick, last state the monitor held for the victim)
    restarted: list = []
    pending: list[asyncio.Task] = []

    async def kill_and_restart(t: int) -> None:
        old, task = agents[victim], tasks[victim]
        task.cancel()
        await old.bus.close()  # the token goes: the sim marks the agent absent, its robot idles
        kills.append((t, monitor.latest_state.get(victim)))
        new = make_agent(config, net.session(f"agent-{victim}-r{len(kills)}"), victim)
        agents[victim], tasks[victim] = new, asyncio.create_task(new.run())
        restarted.append(new)

    def on_tick(t: int, _obs) -> None:
        if t > 0 and t % 100 == 0:
            pending.append(asyncio.get_running_loop().create_task(kill_and_restart(t)))

    sim = SimService(config, net.session("sim"), on_tick=on_tick)
    try:
        result = await asyncio.wait_for(sim.run(), 120)
        await asyncio.wait_for(asyncio.gather(*tasks.values(), mon_task, *pending), 10)
    finally:
        for task in (*tasks.values(), mon_task):
            task.cancel()
    assert result.steps == 320 and len(result.per_tick_deliveries) == 320  # every tick ran, none lost
    assert [t for t, _ in kills] == [100, 200, 300]
    assert len(monitor.result.rows) == 320  # and every tick is in the record
    for (_t, last), new in zip(kills, restarted):
        assert last is not None and new.restored_from is not None
        assert new.restored_from.t == last.t and new.restored_from.w_row == last.w_row  # W row = last published
    assert any(any(new.restored_from.w_row) for new in restarted)  # a learnt state came back, not zeros
    assert all(new.counters.ticks > 0 for new in restarted[:-1])  # it rejoined (liveliness, probe) and took part
