"""Fuzz: random and malformed payloads on every key the services subscribe to, during a run.

No service may crash, every service counts its rejects, and the run's result equals the clean run's.
"""

from __future__ import annotations

import asyncio
import random
import subprocess
import sys

import msgpack
import numpy as np

from morph_sim.local import run_local
from schemas import Ack, HelpRequest, Stop, encode
from schemas.keys import RunKeys
from services.bus.local import LocalNetwork
from services.monitor.recorder import read_metrics, read_snapshots
from services.runconfig import RunConfig

from _procs import FEW_ROBOTS, kill_tree


def fuzz_keys(keys: RunKeys, n_agvs: int, n: int) -> list[str]:
    """A concrete key for every subscription of the sim, the agents and the monitor."""
    out = [keys.tick, keys.fleet, keys.resolve, keys.stop, keys.faults, keys.event("sim"), keys.event("monitor"),
           keys.metric("deliveries"), keys.latest("metrics", "x")]
    for i in range(n):
        out += [keys.ack(i), keys.agent_state(i), keys.event(i), keys.onboard(i)]
    for p in range(n_agvs, n):
        out += [keys.commit(p)] + [keys.request(a, p) for a in range(n_agvs)]
    for a in range(n_agvs):
        out += [keys.reply(p, a) for p in range(n_agvs, n)]
    out += [keys.ack(n + 5), keys.commit(n + 5)]  # ids outside the fleet
    return out


def bad_payload(rng: random.Random) -> bytes:
    """Garbage, foreign msgpack, wrong kinds and versions, corrupted fields — never a well-formed message."""
    choice = rng.randrange(8)
    if choice == 0:
        return rng.randbytes(rng.randrange(0, 64))
    if choice == 1:
        return msgpack.packb([rng.random(), "x", None])
    if choice == 2:
        return msgpack.packb({"k": "tick", "v": 1, "t": -3})
    if choice == 3:
        return msgpack.packb({"k": "ack", "v": 99, "t": 1, "agent": 0})
    if choice == 4:
        return msgpack.packb({"k": "no_such_kind", "v": 1})
    if choice == 5:
        good = encode(HelpRequest(t=3, agv=0, picker=5, target_x=1, target_y=1))
        return good[: rng.randrange(1, len(good))]  # truncated
    if choice == 6:
        body = msgpack.unpackb(encode(Ack(t=1, agent=1)))
        body["agent"] = "one"  # wrong type
        return msgpack.packb(body)
    body = msgpack.unpackb(encode(Stop(reason="x")))
    body["extra_field"] = 1  # a Stop with a foreign field is rejected, never obeyed
    return msgpack.packb(body)


async def fuzzer(bus, keys: list[str], seed: int, stop: asyncio.Event, pause: float = 0.001) -> int:
    rng = random.Random(seed)
    sent = 0
    while not stop.is_set():
        for _ in range(20):
            await bus.publish(rng.choice(keys), bad_payload(rng))
            sent += 1
        await asyncio.sleep(pause)
    return sent


async def test_fuzzed_local_run_equals_the_clean_run(tmp_path):
    config = RunConfig(run_id="fz", scale="tiny", policy="morph", steps=120, seed=3, output_dir=tmp_path,
                       snapshot_every=40)
    clean = await run_local(config, record=False)

    net = LocalNetwork()
    buses = {}
    intruder = net.session("intruder")
    keys = RunKeys(config.run_id)
    stop = asyncio.Event()
    token = await intruder.declare_token(keys.alive(999))  # a robot id the fleet does not have
    task = asyncio.create_task(fuzzer(intruder, fuzz_keys(keys, config.n_agvs, config.n_agents), 11, stop))
    fuzzed = await asyncio.wait_for(run_local(config, network=net, record=False,
                                              on_bus=lambda name, bus: buses.setdefault(name, bus)), 120)
    stop.set()
    sent = await task
    await token.close()
    await intruder.close()

    assert sent > 1000
    assert fuzzed.monitor.rows == clean.monitor.rows
    assert sorted(fuzzed.monitor.snapshots) == sorted(clean.monitor.snapshots)
    for t, (W, A) in clean.monitor.snapshots.items():
        np.testing.assert_array_equal(fuzzed.monitor.snapshots[t][0], W)
        np.testing.assert_array_equal(fuzzed.monitor.snapshots[t][1], A)
    # everyone saw garbage, counted it and carried on; no handler crashed
    assert fuzzed.sim.rejected > 0 and fuzzed.monitor.rejected > 0
    assert all(a.rejected > 0 for a in fuzzed.agents)
    assert all(bus.counters.handler_errors == 0 for bus in buses.values())


def test_fuzzed_distributed_run_equals_the_clean_run(tmp_path):
    """The same over Zenoh: ``morph-sim up --insecure`` (an open endpoint: the services' own checks are all that
    stands) while an intruder session floods every key. Three robots: every kind of service and key is there (the
    sim, the monitor, AGVs and a picker, every request and reply key between them)."""
    from services.bus.zenoh_bus import ZenohBus, endpoint, free_port

    steps = 250
    ep = endpoint(free_port())
    argv = [sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny", "--policy", "morph",
            "--steps", str(steps), "--seed", "3", "--run-id", "fz", "--output-dir", str(tmp_path / "up"),
            "--listen", ep, "--insecure", *FEW_ROBOTS]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    keys = RunKeys("fz")
    config = RunConfig(run_id="fz", scale="tiny", agvs=2, pickers=1, policy="morph", steps=steps, seed=3)

    async def flood() -> int:
        # The intruder connects as soon as the sim's endpoint is open, before the run's processes are ready: a
        # Zenoh connect to an endpoint not yet open retries only a second later, by which time a run this short can
        # be over.
        deadline = asyncio.get_running_loop().time() + 60
        while True:
            try:
                _, writer = await asyncio.open_connection("127.0.0.1", int(ep.rsplit(":", 1)[1]))
                writer.close()
                break
            except OSError:
                if asyncio.get_running_loop().time() > deadline or proc.poll() is not None:
                    raise
                await asyncio.sleep(0.02)
        bus = await ZenohBus.open("intruder", connect=ep, mode="client", connect_timeout=5)
        stop = asyncio.Event()
        # ~2000 bad messages a second: every key is hit many times per run without starving the 2 cores
        task = asyncio.create_task(fuzzer(bus, fuzz_keys(keys, config.n_agvs, config.n_agents), 5, stop, 0.01))
        while proc.poll() is None:
            await asyncio.sleep(0.1)
        stop.set()
        sent = await task
        await bus.close()
        return sent

    try:
        sent = asyncio.run(asyncio.wait_for(flood(), 180))
        _, err = proc.communicate(timeout=30)
    finally:
        kill_tree(proc)
    assert proc.returncode == 0, err
    assert sent > 100
    asyncio.run(run_local(config.model_copy(update={"output_dir": tmp_path / "local"})))
    up, local = tmp_path / "up" / "fz", tmp_path / "local" / "fz"
    assert (up / "metrics.csv").read_bytes() == (local / "metrics.csv").read_bytes()
    for t, snap in read_snapshots(local).items():
        np.testing.assert_array_equal(read_snapshots(up)[t]["W"], snap["W"])
    # the services counted what they rejected (their logs carry the reasons)
    summary = (up / "summary.json").read_text()
    assert '"rejected": 0' not in summary.split('"finished"')[0]
    logs = "".join(p.read_text() for p in (up / "logs").glob("agent-*.log"))
    assert "rejected" in logs
    assert len(read_metrics(up)) == steps


