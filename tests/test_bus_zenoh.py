"""ZenohBus with real OS processes: a second process publishes, sessions close in bounded time, callback
subscribers never keep an interpreter alive, a killed process's liveliness token disappears.

(The behavioural suite shared with LocalBus is in test_bus_local.py, parametrized over both buses.)
Every child process has its own timeout and is killed by pid if the test fails.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from schemas import Ack, RunKeys, encode
from services.bus import LivelinessEvent, wait_for_alive
from services.bus.zenoh_bus import (
    RUNTIME_ENDPOINT,
    RUNTIME_SINGLE_THREAD,
    ZenohBus,
    configure_runtime_env,
    endpoint,
    free_port,
    open_endpoint_bus,
    use_endpoint_runtime,
)

K = RunKeys("zt")


def spawn(code: str, *args: str) -> subprocess.Popen:
    env = dict(os.environ)
    env.pop("ZENOH_RUNTIME", None)  # the child sets the project's runtime itself on import
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code), *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def reap(proc: subprocess.Popen, timeout: float) -> tuple[int, str, str]:
    """Wait for the child; kill it by pid if it overstays (and fail)."""
    try:
        out, err = proc.communicate(timeout=timeout)
        return proc.returncode, out, err
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        raise AssertionError(f"child {proc.pid} did not exit within {timeout} s; stderr:\n{err}") from None
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()


PUBLISHER = """
    import asyncio, sys
    from schemas import Ack, RunKeys
    from services.bus import wait_for_alive
    from services.bus.zenoh_bus import ZenohBus

    async def main():
        k = RunKeys("zt")
        bus = await ZenohBus.open("9", connect=sys.argv[1], connect_timeout=5)
        try:
            await bus.declare_token(k.alive(9))
            await wait_for_alive(bus, k.alive("sim"), 1, timeout=5)   # the receiver is there
            await bus.wait_for_subscribers(k.ack(9), timeout=5)       # and its subscriber is known here
            # close() may discard unflushed data: wait for the receiver's go-ahead (its token going away), watched
            # from before the first ack (the receiver may take its token away as soon as the last one arrives)
            sub = await bus.subscribe_liveliness(k.alive("sim"))
            for t in range(int(sys.argv[2])):
                await bus.publish(k.ack(9), Ack(t=t, agent=9, seq=t))
            while True:
                ev = await sub.next(timeout=8)
                if not ev.alive:
                    break
        finally:
            await bus.close()

    asyncio.run(main())
"""


async def test_second_os_process_publishes() -> None:
    ep = endpoint(free_port())
    sim = await ZenohBus.open("sim", listen=ep)
    proc = None
    try:
        got: list[Ack] = []
        await sim.subscribe(K.acks, lambda s: got.append(s.decode(Ack)))
        token = await sim.declare_token(K.alive("sim"))
        proc = spawn(PUBLISHER, ep, "200")
        await wait_for_alive(sim, K.alive(9), 1, timeout=10)
        deadline = time.monotonic() + 10
        while len(got) < 200 and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        assert [a.t for a in got] == list(range(200)), (len(got), [a.t for a in got][:10])
        await token.close()  # tell the child it may close
        code, _, err = await asyncio.to_thread(reap, proc, 10)
        assert code == 0, err
    finally:
        if proc is not None and proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        await sim.close()


HOLDER = """
    import asyncio, sys
    from schemas import RunKeys
    from services.bus.zenoh_bus import ZenohBus

    async def main():
        bus = await ZenohBus.open("5", connect=sys.argv[1], connect_timeout=5)
        await bus.subscribe(RunKeys("zt").tick, lambda s: None)
        await bus.declare_token(RunKeys("zt").alive(5))
        print("ready", flush=True)
        await asyncio.sleep(60)

    asyncio.run(main())
"""


async def test_killed_process_token_disappears() -> None:
    ep = endpoint(free_port())
    sim = await ZenohBus.open("sim", listen=ep)
    proc = spawn(HOLDER, ep)
    try:
        events: list[LivelinessEvent] = []
        await sim.subscribe_liveliness(K.alive_all, events.append)
        await wait_for_alive(sim, K.alive(5), 1, timeout=10)
        t0 = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        while LivelinessEvent(K.alive(5), False) not in events:
            assert time.monotonic() - t0 < 5, "token of a killed process still present after 5 s"
            await asyncio.sleep(0.01)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        await sim.close()


EXITER = """
    import asyncio, sys, time
    from schemas import RunKeys
    from services.bus.zenoh_bus import ZenohBus, endpoint, free_port

    async def main():
        bus = await ZenohBus.open("x", listen=endpoint(free_port()))
        k = RunKeys("zt")
        await bus.subscribe(k.tick, lambda s: None)          # a callback subscriber: a non-daemon zenoh thread
        await bus.subscribe_liveliness(k.alive_all, lambda e: None)
        await bus.declare_queryable(k.registry, lambda q: None)
        await bus.declare_token(k.alive("x"))
        await bus.publish(k.tick, b"t")
        if sys.argv[1] == "close":
            t0 = time.monotonic()
            await bus.close()
            print(f"closed in {time.monotonic() - t0:.3f}", flush=True)
        # "forget": return without closing; the shutdown safety net must close the session

    asyncio.run(main())
"""


@pytest.mark.parametrize("how", ["close", "forget"])
def test_callback_subscriber_does_not_keep_interpreter_alive(how: str) -> None:
    proc = spawn(EXITER, how)
    code, out, err = reap(proc, 15)
    assert code == 0, err
    if how == "close":
        assert float(out.split()[-1]) < 1.0


async def test_close_is_bounded_and_idempotent() -> None:
    port = free_port()
    a = await open_endpoint_bus("a", port, host=True)
    b = await open_endpoint_bus("b", endpoint(port), host=False)
    for bus in (a, b):
        await bus.subscribe(K.tick, lambda s: None)
        await bus.declare_queryable(K.registry, lambda q: None)
        await bus.declare_token(K.alive(bus.identity))
        await bus.subscribe_liveliness(K.alive_all, lambda e: None)
    for i in range(100):
        await a.publish(K.tick, Ack(t=i, agent=0))
    t0 = time.monotonic()
    await asyncio.wait_for(b.close(), 5)
    await asyncio.wait_for(a.close(), 5)
    assert time.monotonic() - t0 < 2.0
    await a.close()


async def test_open_fails_clearly_when_nothing_listens() -> None:
    t0 = time.monotonic()
    ep = endpoint(free_port())
    with pytest.raises(ConnectionError, match=ep.replace(".", r"\.")):
        await ZenohBus.open("lonely", connect=ep, connect_timeout=0.5)
    assert time.monotonic() - t0 < 5


def test_runtime_environment_setting() -> None:
    env = {"ZENOH_RUNTIME": ""}  # set-but-empty makes zenoh panic: replaced by the project's setting
    configure_runtime_env(env)
    assert env["ZENOH_RUNTIME"] == RUNTIME_SINGLE_THREAD and env["OPENBLAS_NUM_THREADS"] == "1"
    mine = {"ZENOH_RUNTIME": "(app: (worker_threads: 2))"}
    assert configure_runtime_env(mine)["ZENOH_RUNTIME"] == "(app: (worker_threads: 2))"  # the user's choice wins
    with pytest.raises(ValueError, match="port"):
        endpoint(70000)
    # the endpoint's host sends from a thread of its own (a process started as a run's sim has one: see
    # tests/test_restore_lockstep.py); a runtime the user chose stays there too
    use_endpoint_runtime(env)
    assert env["ZENOH_RUNTIME"] == RUNTIME_ENDPOINT and "tx: (handover" not in RUNTIME_ENDPOINT
    use_endpoint_runtime(mine)
    assert mine["ZENOH_RUNTIME"] == "(app: (worker_threads: 2))"


def test_barrier_bench_smoke() -> None:
    from services.bus.barrier_bench import run_barrier

    result = run_barrier(n_agents=2, ticks=100, warmup=10, mode="raw", timeout=30)
    assert result.ticks == 100 and result.ticks_per_s > 0 and result.n_agents == 2
    assert result.p50_ms > 0 and result.p99_ms >= result.p50_ms
    two = run_barrier(n_agents=2, ticks=50, warmup=5, mode="raw", phases=2, timeout=30)
    assert two.phases == 2 and two.ticks == 50 and two.ticks_per_s > 0
    inline = run_barrier(n_agents=2, ticks=50, warmup=5, mode="inline", timeout=30)
    assert inline.mode == "inline" and inline.ticks_per_s > 0
    with pytest.raises(ValueError, match="phases"):
        run_barrier(n_agents=2, mode="bus", phases=2)


@pytest.mark.parametrize("droppable", [False, True])
async def test_a_default_settings_client_receives_every_sample_through_the_endpoint(droppable: bool) -> None:
    """A user's Zenoh client with default settings (no lowlatency) joins a run through its endpoint and
    subscribes to streams one of our sessions publishes, one of which the endpoint's own session consumes too (as the
    sim consumes acks). With express publishers on our lowlatency sessions that client got 0-3 of 120 samples
    (zenoh 1.10.2); every sample must arrive."""
    import threading

    import zenoh

    ep = endpoint(free_port())
    hub = await ZenohBus.open("sim", listen=ep)
    publisher = await ZenohBus.open("monitor", connect=ep, connect_timeout=5)
    at_hub = await hub.subscribe(K.ack(1))
    await publisher.wait_for_subscribers(K.ack(1), timeout=5)
    client = zenoh.open(zenoh.Config.from_json5('{mode: "client", connect: {endpoints: ["%s"]}}' % ep))
    got: list[str] = []
    lock = threading.Lock()

    def on_sample(s) -> None:
        with lock:
            got.append(str(s.key_expr))

    sub = client.declare_subscriber("morph/**", on_sample)
    try:
        await publisher.wait_for_subscribers(K.metric("links"), timeout=5)  # the client's subscription is known
        n = 40
        for t in range(n):
            await publisher.publish(K.metric("links"), Ack(t=t, agent=1, seq=t), droppable=droppable)
            await publisher.publish(K.metric("deliveries"), Ack(t=t, agent=1, seq=t), droppable=droppable)
            await publisher.publish(K.ack(1), Ack(t=t, agent=1, seq=t))
            await asyncio.sleep(0.01)
        deadline = time.monotonic() + 5
        while len(got) < 3 * n and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        assert len(got) == 3 * n, f"{len(got)} of {3 * n} samples"
    finally:
        sub.undeclare()
        client.close()
        await at_hub.close()
        await publisher.close()
        await hub.close()


def test_a_free_port_lies_below_the_range_outgoing_connections_draw_from_and_can_be_listened_on() -> None:
    import socket

    from services.bus.zenoh_bus import LISTEN_PORTS_FROM, ephemeral_ports

    low, high = ephemeral_ports()
    ports = {free_port() for _ in range(20)}
    assert all(LISTEN_PORTS_FROM <= p < low for p in ports), (sorted(ports), low, high)
    with socket.socket() as s:
        s.bind(("127.0.0.1", ports.pop()))
        s.listen()


async def test_one_robots_flood_gets_its_share_of_the_inbox_and_the_rest_is_refused() -> None:
    """While a session's loop is busy, what arrives waits in its inbox: a robot's samples beyond its share are refused
    on arrival (and counted), so a robot publishing as fast as it can does not fill the receiver's memory; another
    robot's samples still all arrive."""
    from services.bus.zenoh_bus import INBOX_PER_ROBOT

    ep = endpoint(free_port())
    hub = await ZenohBus.open("monitor", listen=ep)
    robots = await ZenohBus.open("agent-3", connect=ep, connect_timeout=5)
    refused: list[str] = []
    hub.inbox_author = K.sender_of  # what the services' intake sets
    hub.reject_hook = lambda key, why: refused.append(why)
    got: dict[int, int] = {}
    sub = await hub.subscribe(K.acks, lambda s: got.__setitem__(K.sender_of(s.key), got.get(K.sender_of(s.key), 0) + 1))
    try:
        await robots.wait_for_subscribers(K.ack(3), timeout=5)
        flood = INBOX_PER_ROBOT + 2000
        payload = encode(Ack(t=0, agent=3))
        for _ in range(flood):
            robots.put(K.ack(3), payload)
        for _ in range(10):
            robots.put(K.ack(1), encode(Ack(t=0, agent=1)))
        # the loop is busy (blocked here) while everything arrives on Zenoh's threads
        deadline = time.monotonic() + 10
        while len(hub._inbox) + len(refused) < flood + 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(hub._inbox) <= INBOX_PER_ROBOT + 10
        deadline = time.monotonic() + 10
        while sum(got.values()) < INBOX_PER_ROBOT + 10 and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        assert got == {3: INBOX_PER_ROBOT, 1: 10}, got
        assert len(refused) == flood - INBOX_PER_ROBOT and hub.counters.rejected == len(refused)
        assert refused[0] == f"robot 3 has {INBOX_PER_ROBOT} messages waiting to be read: over its share"
        assert hub._waiting == {}  # every share given back once read
    finally:
        await sub.close()
        await robots.close()
        await hub.close()


def test_a_session_opens_without_waiting_for_scouting():
    """Scouting is off, so a session waits for nobody when it opens: Zenoh's default scouting delay held every
    router's open 500 ms, and the sim's endpoint is a router."""
    import json

    from services.bus.zenoh_bus import endpoint, free_port, zenoh_config

    for mode, where in (("router", "listen"), ("peer", "listen"), ("client", "connect")):
        cfg = zenoh_config(mode=mode, **{where: endpoint(free_port())})
        assert json.loads(cfg.get_json("scouting/delay")) == 0, mode
        assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
        assert json.loads(cfg.get_json("scouting/gossip/enabled")) is False
