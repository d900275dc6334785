"""A scripted lockstep exchange over real buses with faults in virtual time: each participant has its own
FaultRuntime (as separate processes would); the sim waits for every answer to *arrive* (the fault layer's ``on_fate``
hook, so a dropped one never makes it wait), closes the phase at t·Δ + Δ/2, and a late or lost answer misses it. The
answers travel on a protocol key (commitments): acks themselves are synchronisation and never faulted. Same seed and fault config give the same record twice, on LocalBus and on Zenoh alike."""

from __future__ import annotations

import asyncio
import time

from schemas import FaultCommand, FaultSpec, Latency, Loss, RunKeys, Scope
from services.bus import LocalNetwork
from services.faults.runtime import FaultRuntime
from services.faults.vtime import boundaries

RUN = "ls"
K = RunKeys(RUN)
SPEC = FaultSpec(id="net", loss=Loss(model="gilbert_elliott", percent=20, burst_length=3),
                 latency=Latency(delay=0.4, jitter=0.3, distribution="uniform"), scope=Scope(key_expr="agent/*/commit"))


async def lockstep(open_bus, *, agents: int = 4, ticks: int = 40, seed: int = 5, settle: float = 0.0):
    """Returns the sim's record: per tick, the agents whose ack counted, and the late ones (with release time)."""
    sim_bus = await open_bus("sim")
    sim_rt = FaultRuntime(RUN, seed=seed, dt=1.0, events=True)
    sim_layer = sim_rt.attach(sim_bus)
    await sim_rt.start()
    arrived: dict[int, int] = {}
    sim_layer.on_fate = lambda s, fate: arrived.__setitem__(int(s.payload), arrived.get(int(s.payload), 0) + 1)
    current = {"t": -1}
    record: list[tuple] = []
    on_time: dict[int, list[int]] = {}

    def on_ack(sample) -> None:
        t, who = int(sample.payload), int(sample.sender)
        if t == current["t"]:
            on_time.setdefault(t, []).append(who)
        else:
            record.append(("late", t, who, sim_rt.now()))  # stale: the protocol ignores it

    await sim_bus.subscribe(K.commits, on_ack)
    agent_buses, agent_rts = [], []
    for i in range(agents):
        bus = await open_bus(str(i))
        rt = FaultRuntime(RUN, seed=seed, dt=1.0)
        rt.attach(bus)
        await rt.start()

        def on_tick(sample, bus=bus, rt=rt, i=i) -> None:
            t = int(sample.payload)
            rt.advance(boundaries(t, 1.0)[0])  # an agent reaches the boundary when it sees the Tick
            bus.put(K.commit(i), str(t).encode())
        await bus.subscribe(K.tick, on_tick)
        agent_buses.append(bus)
        agent_rts.append(rt)
    await asyncio.sleep(settle)
    wall = time.monotonic() + 10
    while True:  # until every process's controller is discovered (re-setting the same id is idempotent)
        replies = await sim_bus.get(K.fault_queries, payload=FaultCommand(op="set", spec=SPEC))
        if len(replies) == agents + 1 or time.monotonic() > wall:
            break
        await asyncio.sleep(0.1)
    assert len(replies) == agents + 1 and all(r.ok for r in replies)
    for t in range(ticks):
        start, deadline, _ = boundaries(t, 1.0)
        sim_rt.advance(start)
        current["t"] = t
        sim_bus.put(K.tick, str(t).encode())
        wall = time.monotonic() + 10
        while arrived.get(t, 0) < agents:  # every ack physically in (delivered, held or dropped): never a hang
            assert time.monotonic() < wall, f"tick {t}: only {arrived.get(t, 0)} acks arrived"
            await asyncio.sleep(0.001)
        sim_rt.advance(deadline)  # TICK phase closes; acks due by now are released into on_ack
        record.append(("tick", t, tuple(sorted(on_time.get(t, ())))))
        current["t"] = -1
    sim_rt.advance(boundaries(ticks + 2, 1.0)[0])
    report = sim_rt.meters["sim"].report()["agent/*/commit"]
    for bus in (*agent_buses, sim_bus):
        await bus.close()
    return record, report, sim_rt.controller.log


async def test_lockstep_under_faults_is_live_and_reproducible_on_localbus() -> None:
    net = LocalNetwork()

    async def open_local(name):
        return net.session(name)

    first, report, events = await lockstep(open_local)
    net2 = LocalNetwork()

    async def open_local2(name):
        return net2.session(name)

    second, _, _ = await lockstep(open_local2)
    assert first == second
    ticks = [r for r in first if r[0] == "tick"]
    assert len(ticks) == 40  # no tick lost, none hung
    counted = sum(len(r[2]) for r in ticks)
    late = [r for r in first if r[0] == "late"]
    assert 0 < counted < 160 and late and report.dropped > 0
    # sent is read off sequence numbers (highest + 1 per agent): an agent's trailing losses are invisible
    assert report.late == len(late) and 150 <= report.sent <= 160 and report.delivered == counted + len(late)
    assert [e.kind for e in events] == ["fault.set"]


async def test_lockstep_same_record_on_zenoh_as_on_localbus() -> None:
    from services.bus.zenoh_bus import ZenohBus, endpoint, free_port

    net = LocalNetwork()

    async def open_local(name):
        return net.session(name)

    local, _, _ = await lockstep(open_local, agents=3, ticks=25)
    ep = endpoint(free_port())

    async def open_zenoh(name):
        if name == "sim":
            return await ZenohBus.open(name, listen=ep, mode="router")
        return await ZenohBus.open(name, connect=ep, mode="client")

    remote, _, _ = await lockstep(open_zenoh, agents=3, ticks=25, settle=0.5)
    assert remote == local
