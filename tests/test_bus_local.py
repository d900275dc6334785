"""The bus contract: ONE behavioural suite run over LocalBus and over ZenohBus (two sessions over 127.0.0.1).

Plus LocalBus-only checks of deterministic delivery order.
"""

from __future__ import annotations

import asyncio
import time

import pytest
from hypothesis import given, settings, strategies as st

from schemas import Ack, RegistrationReply, RegistrationRequest, RunKeys, Stop, decode, intersects
from services.bus import Bus, LivelinessEvent, LocalNetwork, Sample, wait_for_alive

from _procs import until

K = RunKeys("t1")


class LocalEnv:
    name = "local"

    def __init__(self) -> None:
        self.net = LocalNetwork()
        self.buses: list[Bus] = []

    async def open(self, identity: str) -> Bus:
        bus = self.net.session(identity)
        self.buses.append(bus)
        return bus

    async def settle(self, bus: Bus | None = None, *keys: str) -> None:
        for key in keys:
            await bus.wait_for_subscribers(key, timeout=5.0)
        for _ in range(3):
            await asyncio.sleep(0)


class ZenohEnv:
    name = "zenoh"

    def __init__(self) -> None:
        from services.bus.zenoh_bus import endpoint, free_port

        self.endpoint = endpoint(free_port())
        self.buses: list[Bus] = []

    async def open(self, identity: str) -> Bus:
        from services.bus.zenoh_bus import ZenohBus

        if not self.buses:  # the first session hosts the endpoint, the others connect to it
            bus = await ZenohBus.open(identity, listen=self.endpoint)
        else:
            bus = await ZenohBus.open(identity, connect=self.endpoint, connect_timeout=5.0)
        self.buses.append(bus)
        return bus

    async def settle(self, bus: Bus | None = None, *keys: str) -> None:
        # Zenoh declarations propagate asynchronously: wait until the publisher knows the subscribers of ``keys``
        # (services do the same with a liveliness handshake), plus a margin for declarations without a probe.
        for key in keys:
            await bus.wait_for_subscribers(key, timeout=5.0)
        await asyncio.sleep(0.1)


@pytest.fixture(params=["local", "zenoh"])
async def env(request):
    e = LocalEnv() if request.param == "local" else ZenohEnv()
    yield e
    for bus in reversed(e.buses):
        await asyncio.wait_for(bus.close(), 5.0)


async def get_until(bus: Bus, selector: str, n: int, timeout: float = 5.0, **kw) -> list:
    """Repeat a get until it returns ``n`` replies (a new queryable's declaration propagates asynchronously)."""
    deadline = time.monotonic() + timeout
    while True:
        replies = await bus.get(selector, timeout=2.0, **kw)
        if len(replies) >= n or time.monotonic() > deadline:
            return replies
        await asyncio.sleep(0.02)


async def test_publish_subscribe_message(env) -> None:
    sim, agent = await env.open("sim"), await env.open("3")
    got: list[Sample] = []
    await sim.subscribe(K.acks, got.append)
    await env.settle(agent, K.ack(3))
    await agent.publish(K.ack(3), Ack(t=7, agent=3, requests_sent=[5]))
    await until(lambda: len(got) == 1)
    sample = got[0]
    assert sample.key == K.ack(3)
    assert sample.sender == "3" and sample.seq == 0 and sample.sent_at <= time.time()
    assert sample.decode(Ack) == Ack(t=7, agent=3, requests_sent=[5])


async def test_malformed_payloads_are_counted_not_fatal(env) -> None:
    sim, agent = await env.open("sim"), await env.open("3")
    acks: list[Ack] = []

    def on_ack(sample: Sample) -> None:
        ack = sim.decode(sample, Ack)
        if ack is not None:
            acks.append(ack)

    await sim.subscribe(K.acks, on_ack)
    await env.settle(agent, K.ack(3))
    for payload in (b"\xc1garbage", Stop(reason="wrong kind"), Ack(t=1, agent=3), b"", Ack(t=2, agent=3)):
        await agent.publish(K.ack(3), payload)
    await until(lambda: len(acks) == 2 and sim.counters.rejected == 3)
    assert [a.t for a in acks] == [1, 2]
    assert sim.counters.per_key_rejects == {K.ack(3): 3} and sim.counters.handler_errors == 0


async def test_wildcards_follow_zenoh_rules(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    one, many, narrow = [], [], []
    await b.subscribe("morph/t1/agent/*/ack", lambda s: one.append(s.key))
    await b.subscribe("morph/t1/**", lambda s: many.append(s.key))
    await b.subscribe(K.requests_to(7), lambda s: narrow.append(s.key))
    await env.settle(a, K.ack(1), K.request(1, 7))
    for key in (K.ack(1), K.ack(2), K.agent_state(1), K.request(1, 7), K.request(1, 8), K.tick,
                "morph/t2/sim/tick"):
        await a.publish(key, b"x")
    await until(lambda: len(many) == 6)
    await asyncio.sleep(0.05 if env.name == "zenoh" else 0)
    assert sorted(one) == [K.ack(1), K.ack(2)]
    assert sorted(many) == sorted([K.ack(1), K.ack(2), K.agent_state(1), K.request(1, 7), K.request(1, 8), K.tick])
    assert narrow == [K.request(1, 7)]


async def test_wait_for_subscribers(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    with pytest.raises(TimeoutError, match="no subscriber"):
        await a.wait_for_subscribers(K.tick, timeout=0.2)
    got = []
    await b.subscribe("morph/t1/sim/*", got.append)
    await a.wait_for_subscribers(K.tick, timeout=5.0)
    await a.publish(K.tick, b"first")  # no settle(): the wait is the readiness handshake
    await until(lambda: len(got) == 1)


async def test_order_and_sequence_numbers_per_publisher(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    sub = await b.subscribe(K.tick)
    await env.settle(a, K.tick)
    for t in range(50):
        await a.publish(K.tick, Stop(reason=str(t)))
    got = [await sub.next(timeout=3.0) for _ in range(50)]
    assert [s.seq for s in got] == list(range(50))
    assert [decode(s.payload, Stop).reason for s in got] == [str(t) for t in range(50)]


async def test_async_handler_sees_samples_one_at_a_time_in_order(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    seen: list[int] = []
    busy = False

    async def handler(sample: Sample) -> None:
        nonlocal busy
        assert not busy  # never re-entered
        busy = True
        await asyncio.sleep(0.001)
        seen.append(sample.seq)
        busy = False

    await b.subscribe(K.tick, handler)
    await env.settle(a, K.tick)
    for _ in range(20):
        await a.publish(K.tick, b"t")
    await until(lambda: len(seen) == 20)
    assert seen == list(range(20))


async def test_session_receives_its_own_publications(env) -> None:
    a = await env.open("a")
    got = []
    await a.subscribe(K.events, got.append)
    await env.settle(a, K.event("a"))
    await a.publish(K.event("a"), b"e")
    await until(lambda: len(got) == 1)
    assert got[0].sender == "a"


async def test_handler_failure_is_counted_and_delivery_continues(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    got = []

    def handler(sample: Sample) -> None:
        if sample.seq == 0:
            raise RuntimeError("boom")
        got.append(sample.seq)

    await b.subscribe(K.tick, handler)
    await env.settle(a, K.tick)
    for _ in range(3):
        await a.publish(K.tick, b"t")
    await until(lambda: len(got) == 2)
    assert got == [1, 2]
    assert b.counters.handler_errors == 1


async def test_closed_subscription_stops_and_iterator_ends(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    sub = await b.subscribe(K.tick)
    await env.settle(a, K.tick)
    await a.publish(K.tick, b"1")
    first = await sub.next(timeout=3.0)
    assert first.payload == b"1"
    await sub.close()
    await a.publish(K.tick, b"2")
    await asyncio.sleep(0.1)
    assert [s async for s in sub] == []
    with pytest.raises(EOFError):
        await sub.next(timeout=1.0)


async def test_query_reply(env) -> None:
    monitor, client = await env.open("monitor"), await env.open("client")
    calls = []

    async def latest(query) -> None:
        calls.append((query.key_expr, query.params))
        for agent in (1, 2):
            key = K.latest("agent", str(agent))
            if intersects(key, query.key_expr):
                query.reply(key, Stop(reason=f"state of {agent}"))

    await monitor.declare_queryable(K.latest_all, latest)
    await env.settle()
    replies = await get_until(client, K.latest_all + "?since=5", 2)
    assert sorted((r.key, r.decode(Stop).reason) for r in replies) == [
        (K.latest("agent", "1"), "state of 1"), (K.latest("agent", "2"), "state of 2")]
    one = await client.get(K.latest("agent", "2"), timeout=2.0)
    assert [r.key for r in one] == [K.latest("agent", "2")]
    assert calls[-2] == (K.latest_all, {"since": "5"})
    assert await client.get(K.registry, timeout=0.3) == []  # nobody answers: empty, no hang


async def test_query_with_payload_registration(env) -> None:
    sim, agent = await env.open("sim"), await env.open("agent")

    def register(query) -> None:
        req = decode(query.payload, RegistrationRequest)
        query.reply(K.registry, RegistrationReply(ok=True, agent_id=req.want_id or 0, role="picker", n_agvs=5,
                                                  n_pickers=3))

    await sim.declare_queryable(K.registry, register)
    await env.settle()
    replies = await get_until(agent, K.registry, 1, payload=RegistrationRequest(instance="host-a", want_id=6))
    assert len(replies) == 1 and replies[0].ok
    assert replies[0].decode(RegistrationReply).agent_id == 6


async def test_failing_queryable_gives_an_error_reply(env) -> None:
    server, client = await env.open("server"), await env.open("client")

    def bad(query) -> None:
        query.reply("morph/t1/elsewhere", b"x")  # not matching the query: refused

    await server.declare_queryable(K.registry, bad)
    await env.settle()
    replies = await get_until(client, K.registry, 1)
    assert len(replies) == 1 and not replies[0].ok
    assert server.counters.handler_errors >= 1


async def test_liveliness_tokens(env) -> None:
    watcher, agent = await env.open("watcher"), await env.open("agent")
    events: list[LivelinessEvent] = []
    pre = await agent.declare_token(K.alive(1))
    await env.settle()
    await watcher.subscribe_liveliness(K.alive_all, events.append, history=True)
    await until(lambda: LivelinessEvent(K.alive(1), True) in events)
    later = await agent.declare_token(K.alive(2))
    await until(lambda: LivelinessEvent(K.alive(2), True) in events)
    assert await watcher.alive(K.alive_all) == {K.alive(1), K.alive(2)}
    await later.close()
    await until(lambda: LivelinessEvent(K.alive(2), False) in events)
    assert await watcher.alive(K.alive_all) == {K.alive(1)}
    assert pre.key_expr == K.alive(1)
    await agent.close()  # a closed session's tokens disappear
    await until(lambda: LivelinessEvent(K.alive(1), False) in events)
    assert await watcher.alive(K.alive_all) == set()


async def test_wait_for_alive(env) -> None:
    sim = await env.open("sim")
    agents = [await env.open(str(i)) for i in range(3)]
    for i, bus in enumerate(agents[:2]):
        await bus.declare_token(K.alive(i))
    with pytest.raises(TimeoutError, match="only 2 of 3"):
        await wait_for_alive(sim, K.alive_all, 3, timeout=0.5)
    waiter = asyncio.create_task(wait_for_alive(sim, K.alive_all, 3, timeout=5.0))
    await asyncio.sleep(0.05)
    await agents[2].declare_token(K.alive(2))
    assert await waiter == {K.alive(0), K.alive(1), K.alive(2)}


async def test_bad_keys_are_rejected_and_closed_bus_refuses(env) -> None:
    bus = await env.open("a")
    with pytest.raises(ValueError, match="wildcard"):
        await bus.publish(K.acks, b"x")
    with pytest.raises(ValueError, match="canonical"):
        await bus.subscribe("morph/t1/**/*")
    with pytest.raises(TypeError):
        await bus.publish(K.tick, "not bytes")  # type: ignore[arg-type]
    await bus.close()
    await bus.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        await bus.publish(K.tick, b"x")


class DropOddDuplicateEven:
    """A minimal interposer exercising the fault-layer seam on both hook points."""

    def __init__(self) -> None:
        self.egress = 0
        self.ingress = 0

    def on_publish(self, sample: Sample, send) -> None:
        self.egress += 1
        send(sample)
        if sample.seq % 2 == 0:
            send(sample)  # duplicate

    def on_deliver(self, sample: Sample, receiver: str, deliver) -> None:
        self.ingress += 1
        assert receiver == "b"
        if sample.seq % 2 == 1:
            return  # drop
        deliver(sample)


async def test_interposer_seam(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    fa, fb = DropOddDuplicateEven(), DropOddDuplicateEven()
    a.set_interposer(fa)
    b.set_interposer(fb)
    got = []
    await b.subscribe(K.tick, lambda s: got.append(s.seq))
    await env.settle(a, K.tick)
    for _ in range(4):
        await a.publish(K.tick, b"t")
    await until(lambda: len(got) == 4)
    await asyncio.sleep(0.05)
    assert got == [0, 0, 2, 2]  # seq 1, 3 dropped at ingress; 0, 2 duplicated at egress
    assert fa.egress == 4 and fb.ingress == 6


async def test_inline_handlers_are_serialized_and_ordered(env) -> None:
    a, b = await env.open("a"), await env.open("b")
    seen: dict[str, list[int]] = {K.tick: [], K.resolve: []}
    running = [0]
    overlaps = [0]

    def handler(sample: Sample) -> None:
        running[0] += 1
        if running[0] > 1:
            overlaps[0] += 1
        time.sleep(0.0002)  # widen the window a concurrent call would hit
        seen[sample.key].append(sample.seq)
        b.put(K.ack(1), b"ack")  # publishing from an inline handler is allowed
        running[0] -= 1

    await b.subscribe(K.tick, handler, inline=True)
    await b.subscribe(K.resolve, handler, inline=True)
    acks = []
    await a.subscribe(K.acks, acks.append)
    await env.settle(a, K.tick, K.resolve)
    await env.settle(b, K.ack(1))
    for _ in range(40):
        await a.publish(K.tick, b"t")
        await a.publish(K.resolve, b"r")
    await until(lambda: len(acks) == 80)
    assert seen[K.tick] == list(range(40)) and seen[K.resolve] == list(range(40))
    assert overlaps[0] == 0
    with pytest.raises(TypeError, match="plain"):
        async def coro(sample: Sample) -> None: ...
        await b.subscribe(K.tick, coro, inline=True)


async def test_inline_subscription_with_delaying_fault_layer(env) -> None:
    from schemas import FaultSpec, Latency
    from services.faults.layer import FaultLayer

    a, b = await env.open("a"), await env.open("b")
    layer = FaultLayer("t1", loop=asyncio.get_running_loop())
    layer.set(FaultSpec(latency=Latency(delay=0.05)))
    b.set_interposer(layer)
    lags: list[float] = []
    await b.subscribe(K.tick, lambda s: lags.append(time.time() - s.sent_at), inline=True)
    await env.settle(a, K.tick)
    for _ in range(10):
        await a.publish(K.tick, b"t")
    await until(lambda: len(lags) == 10)
    assert min(lags) >= 0.05


class CountEgress:
    """An interposer that counts what passes the egress seam, per key, and lets everything through."""

    def __init__(self) -> None:
        self.egress: dict[str, int] = {}

    def on_publish(self, sample, send) -> None:
        self.egress[sample.key] = self.egress.get(sample.key, 0) + 1
        send(sample)

    def on_deliver(self, sample, receiver, deliver) -> None:
        deliver(sample)


async def test_put_together_gives_each_receiver_the_shared_sample_and_its_own_once(env) -> None:
    """The sim's tick start: each robot takes its own sample and the shared broadcast, each exactly once, with the
    headers separate puts would have; the shared sample passes the egress seam once per call, not once per robot."""
    sim = await env.open("sim")
    seam = CountEgress()
    sim.set_interposer(seam)
    robots = [await env.open(f"agent-{i}") for i in range(3)]
    got: dict[int, list[tuple[str, str, int, bytes]]] = {i: [] for i in range(3)}
    for i, bus in enumerate(robots):
        def take(s: Sample, i=i) -> None:
            got[i].append((s.key, s.sender, s.seq, s.payload))
        await bus.subscribe(K.fleet, take, inline=True)
        await bus.subscribe(K.onboard(i), take, inline=True)
    # a second subscription to a robot's own key (not inline): the carrier reaches it too, the samples still come
    # once to each subscription they match
    second: list[int] = []
    await robots[2].subscribe(K.onboard(2), lambda s: second.append(s.seq))
    for i in range(3):
        await env.settle(sim, K.onboard(i))
    for n in range(4):
        sim.put_together((K.fleet, f"fleet {n}".encode()), [(K.onboard(i), f"own {i} {n}".encode()) for i in range(3)])
    await until(lambda: all(len(v) == 8 for v in got.values()) and len(second) == 4)
    await asyncio.sleep(0.05)
    for i in range(3):
        assert sorted(got[i]) == sorted(
            [(K.fleet, "sim", n, f"fleet {n}".encode()) for n in range(4)]
            + [(K.onboard(i), "sim", n, f"own {i} {n}".encode()) for n in range(4)])
    assert second == [0, 1, 2, 3]
    assert seam.egress == {K.fleet: 4, **{K.onboard(i): 4 for i in range(3)}}
    assert all(bus.counters.rejected == 0 for bus in robots)


async def test_zenoh_carries_the_shared_sample_inside_each_own_one() -> None:
    """Over Zenoh the shared sample travels only inside the own ones: a session subscribed to the shared key alone
    (a tool on ``sim/fleet``) gets nothing, one that takes an own key gets both."""
    e = ZenohEnv()
    try:
        sim, robot, tool = await e.open("sim"), await e.open("agent-0"), await e.open("tool")
        robot_got, tool_got = [], []
        await robot.subscribe(K.fleet, lambda s: robot_got.append(s.key))
        await robot.subscribe(K.onboard(0), lambda s: robot_got.append(s.key))
        await tool.subscribe(K.fleet, lambda s: tool_got.append(s.key))
        await e.settle(sim, K.onboard(0))
        await e.settle(sim, K.fleet)
        sim.put_together((K.fleet, b"f"), [(K.onboard(0), b"o")])
        await until(lambda: len(robot_got) == 2)
        await asyncio.sleep(0.2)
        assert sorted(robot_got) == sorted([K.fleet, K.onboard(0)]) and tool_got == []
    finally:
        for bus in reversed(e.buses):
            await asyncio.wait_for(bus.close(), 5.0)


@pytest.mark.parametrize("forged, field", [
    # another author's message inside the sim's carrier
    (lambda: [(K.ack(3), 0, 0.0, b"a"), (K.onboard(0), 0, 0.0, b"o")], "bundle[0].key"),
    # the carrier's own sample missing: a bundle is always its carrier's sample plus what rides with it
    (lambda: [(K.fleet, 0, 0.0, b"f")], "its last sample is not the carrier's own"),
    (lambda: [(K.fleet, 0, 0.0, b"f")] * 5 + [(K.onboard(0), 0, 0.0, b"o")], "expected 1..4 samples"),
    (lambda: [(K.fleet, "zero", 0.0, b"f"), (K.onboard(0), 0, 0.0, b"o")], "bundle[0]: expected [key, seq"),
    (lambda: [("morph/t1/sim/*", 0, 0.0, b"f"), (K.onboard(0), 0, 0.0, b"o")], "wildcard"),
])
async def test_a_forged_bundle_is_refused_counted_and_harmless(forged, field) -> None:
    """A bundle that breaks the rules is one counted refusal naming what is wrong; nothing in it is delivered and
    the session keeps receiving."""
    import msgpack

    e = ZenohEnv()
    try:
        sim, robot = await e.open("sim"), await e.open("agent-0")
        got, why = [], []
        robot.reject_hook = lambda key, reason: why.append((key, str(reason)))
        for key in (K.fleet, K.onboard(0), K.ack(3)):
            await robot.subscribe(key, lambda s: got.append((s.key, s.payload)), inline=True)
        await e.settle(sim, K.onboard(0))
        sim.put(K.onboard(0), msgpack.packb(forged(), use_bin_type=True))
        await until(lambda: why)
        assert why == [(K.onboard(0), why[0][1])] and field in why[0][1] and robot.counters.rejected == 1
        sim.put_together((K.fleet, b"f"), [(K.onboard(0), b"o")])
        await until(lambda: len(got) == 2)
        assert sorted(got) == sorted([(K.fleet, b"f"), (K.onboard(0), b"o")])
    finally:
        for bus in reversed(e.buses):
            await asyncio.wait_for(bus.close(), 5.0)


# ---------------------------------------------------------------------------------------------------------------
# LocalBus only: deterministic delivery
# ---------------------------------------------------------------------------------------------------------------
async def test_local_delivery_order_is_deterministic() -> None:
    async def run() -> list[tuple[str, str, int]]:
        net = LocalNetwork()
        buses = [net.session(str(i)) for i in range(4)]
        log: list[tuple[str, str, int]] = []
        for bus in buses:
            await bus.subscribe("morph/t1/**", lambda s, me=bus.identity: log.append((me, s.sender, s.seq)))
        for _round in range(3):
            for bus in reversed(buses):
                await bus.publish(K.ack(int(bus.identity)), b"x")
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        for bus in buses:
            await bus.close()
        return log

    first, second = await run(), await run()
    assert first == second and len(first) == 4 * 4 * 3
    # publication order, then subscriber declaration order
    assert first[:4] == [("0", "3", 0), ("1", "3", 0), ("2", "3", 0), ("3", "3", 0)]


async def test_local_reply_after_timeout_is_dropped() -> None:
    net = LocalNetwork()
    server, client = net.session("s"), net.session("c")
    late = asyncio.Event()

    async def slow(query) -> None:
        await asyncio.sleep(0.2)
        query.reply(K.registry, b"late")
        late.set()

    await server.declare_queryable(K.registry, slow)
    assert await client.get(K.registry, timeout=0.05) == []
    await server.close()
    await client.close()


_CHUNKS = ("morph", "t1", "agent", "7", "12", "ack", "@onboard", "reply")
_EXPR_CHUNKS = (*_CHUNKS, "*", "**")


@settings(max_examples=60, deadline=None)
@given(exprs=st.lists(st.lists(st.sampled_from(_EXPR_CHUNKS), min_size=1, max_size=5), min_size=1, max_size=30),
       keys=st.lists(st.lists(st.sampled_from(_CHUNKS), min_size=1, max_size=6), min_size=1, max_size=30),
       dropped=st.sets(st.integers(0, 29), max_size=10))
async def test_local_routes_are_every_matching_subscription_in_declaration_order(exprs, keys, dropped) -> None:
    """The in-process network finds a key's subscribers by the shape of their expressions; what it finds is what
    matching the key against every subscription finds, in the order they were declared, also after some leave."""
    net = LocalNetwork()
    bus = net.session("s")
    subs = []
    for chunks in exprs:
        expr = "/".join(chunks)
        if any(a == "**" and b in ("*", "**") for a, b in zip(chunks, chunks[1:])):  # not canonical: refused
            continue
        subs.append(await bus.subscribe(expr, lambda s: None))
    for i in sorted(dropped):
        if i < len(subs):
            await subs[i].close()
    for chunks in keys:
        key = "/".join(chunks)
        expected = [entry for entry in net.subscribers if intersects(entry[1].key_expr, key)]
        assert net.routes.reach(key) == expected, key
        assert net.routes.reach(key) == expected, key  # and again from the table
    await bus.close()
    assert all(not net.routes.reach("/".join(chunks)) for chunks in keys)
