"""Robot-id registration: the pure allocator, and the sim's registry queryable over LocalBus and ZenohBus."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from hypothesis import given, settings, strategies as st

from schemas.keys import RunKeys
from schemas.messages import Role
from services.bus import LocalNetwork
from services.bus.registry import claim_id, default_instance, mount_registry
from services.protocol.registry import (
    BUSY,
    FULL,
    INVALID,
    IdAllocator,
    Refusal,
    RegistrationError,
    reason_code,
)

A, P = 5, 3  # the tiny scale's fleet: ids 0..4 are AGVs, 5..7 pickers


# -- pure allocator ------------------------------------------------------------------------------------------------
def test_fills_agvs_first_then_pickers_with_distinct_ids():
    alloc = IdAllocator(A, P)
    grants = [alloc.allocate(f"c{i}", set(), now=0.0) for i in range(A + P)]
    assert [g.agent_id for g in grants] == list(range(A + P))
    assert [g.role for g in grants] == ["agv"] * A + ["picker"] * P
    with pytest.raises(Refusal) as full:
        alloc.allocate("c-extra", set(range(A + P)), now=1.0)
    assert full.value.code == FULL


def test_a_grant_reserves_its_id_until_the_token_shows_up_or_the_hold_expires():
    alloc = IdAllocator(1, 1, hold=10.0)
    assert alloc.allocate("a", set(), now=0.0).agent_id == 0
    assert alloc.allocate("b", set(), now=1.0).agent_id == 1  # 0 is held although no token is up yet
    with pytest.raises(Refusal) as busy:
        alloc.allocate("c", set(), now=2.0)
    assert busy.value.code == FULL
    # "a" never declared its token: after the hold its id is free again ("b" did declare one).
    assert alloc.allocate("c", {1}, now=11.0).agent_id == 0


def test_a_restarted_instance_gets_its_old_id_back_even_if_fresh_ids_exist():
    alloc = IdAllocator(3, 2, hold=5.0)
    for i in range(4):
        alloc.allocate(f"c{i}", set(), now=0.0)
    alive = {0, 1, 2, 3}
    with pytest.raises(Refusal) as busy:  # its old session's token is still there: retry later
        alloc.allocate("c2", alive, now=10.0)
    assert busy.value.code == BUSY
    alive.discard(2)  # the old container's session ended
    grant = alloc.allocate("c2", alive, now=11.0)
    assert (grant.agent_id, grant.returning) == (2, True)


def test_a_departed_robots_id_goes_to_a_newcomer_only_when_no_fresh_id_is_left():
    alloc = IdAllocator(2, 1, hold=1.0)
    assert alloc.allocate("a", set(), now=0.0).agent_id == 0
    assert alloc.allocate("b", set(), now=0.0).agent_id == 1
    alive = {1}  # "a" died
    assert alloc.allocate("c", alive, now=5.0).agent_id == 2  # fresh id first: 0 stays reserved for "a"
    alive.add(2)
    grant = alloc.allocate("d", alive, now=6.0)  # no fresh id left: the freed one
    assert (grant.agent_id, grant.role, grant.returning) == (0, "agv", False)
    alive.add(0)
    with pytest.raises(Refusal) as full:  # "a" comes back: its robot now belongs to "d"
        alloc.allocate("a", alive, now=7.0)
    assert full.value.code == FULL


def test_want_id_and_want_role():
    alloc = IdAllocator(A, P, hold=1.0)
    assert alloc.allocate("x", set(), now=0.0, want_role="picker").agent_id == A
    assert alloc.allocate("y", set(), now=0.0, want_id=3).agent_id == 3
    with pytest.raises(Refusal) as busy:
        alloc.allocate("z", {3}, now=5.0, want_id=3)
    assert busy.value.code == BUSY and "'y'" in busy.value.detail
    assert alloc.allocate("y", set(), now=0.5, want_id=3).agent_id == 3  # y retrying its own grant is no conflict
    for bad in ({"want_id": 8}, {"want_id": 0, "want_role": "picker"}, {"want_role": "forklift"}):
        with pytest.raises(Refusal) as invalid:
            alloc.allocate("w", set(), now=9.0, **bad)
        assert invalid.value.code == INVALID
    with pytest.raises(ValueError, match="fleet"):
        IdAllocator(0, 0)
    assert reason_code("busy: id 3 is held") == BUSY and reason_code(None) == ""


OPS = st.sampled_from(["claim", "claim", "declare", "die", "wait"])


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(OPS, st.integers(0, 4)), max_size=40))
def test_no_id_is_granted_while_a_live_token_or_anothers_fresh_grant_holds_it(ops):
    """Whatever the order of claims, token declarations, deaths and pauses, an id has at most one holder."""
    hold = 3.0
    alloc = IdAllocator(2, 1, hold=hold)
    alive: dict[int, str] = {}  # id -> instance whose token is up
    pending: dict[int, tuple[str, float]] = {}  # id -> (instance granted, when); token not up yet
    now = 0.0
    for op, who in ops:
        now += 1.0
        inst = f"i{who}"
        if op == "claim" and inst not in alive.values():
            try:
                grant = alloc.allocate(inst, set(alive), now)
            except Refusal:
                continue
            assert grant.agent_id not in alive, "granted an id whose token is live"
            holder = pending.get(grant.agent_id)
            assert holder is None or holder[0] == inst or now - holder[1] >= hold, "granted a freshly granted id"
            pending = {i: h for i, h in pending.items() if h[0] != inst}
            pending[grant.agent_id] = (inst, now)
        elif op == "declare":
            for i in [i for i, h in pending.items() if h[0] == inst]:
                del pending[i]
                alive[i] = inst
                alloc.seen_alive(i)
        elif op == "die":
            for i in [i for i, o in alive.items() if o == inst]:
                del alive[i]
            pending = {i: h for i, h in pending.items() if h[0] != inst}
        elif op == "wait":
            now += who


def test_default_instance_is_the_hostname_and_pid_unless_named():
    assert default_instance({"MORPH_INSTANCE": "robot-a"}) == "robot-a"
    assert default_instance({}) == f"{os.uname().nodename}-{os.getpid()}"
    assert default_instance({}, pid=7) != default_instance({}, pid=8)  # two processes on one host differ


# -- the queryable over LocalBus --------------------------------------------------------------------------------------
async def _join(bus, keys: RunKeys, instance: str, **kw):
    reply = await claim_id(bus, keys, instance, timeout=5.0, **kw)
    await bus.declare_token(keys.alive(reply.agent_id))
    return reply


async def _until(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


async def test_registry_over_localbus_eight_agents_then_kill_and_replace():
    net = LocalNetwork()
    keys = RunKeys("reg-local")
    sim = net.session("sim")
    registry = await mount_registry(sim, keys, A, P)
    buses = [net.session(f"c{i}") for i in range(A + P)]
    replies = await asyncio.gather(*(_join(b, keys, f"container-{i}") for i, b in enumerate(buses)))
    ids = [r.agent_id for r in replies]
    assert sorted(ids) == list(range(A + P))
    assert sum(r.role == "agv" for r in replies) == A and sum(r.role == "picker" for r in replies) == P
    assert all((r.role == "agv") == (r.agent_id < A) for r in replies)
    assert all((r.n_agvs, r.n_pickers) == (A, P) for r in replies)
    await _until(lambda: registry.alive == set(range(A + P)), 2.0, "all tokens")

    # A ninth agent finds the fleet full.
    spare = net.session("spare")
    with pytest.raises(RegistrationError, match="full"):
        await claim_id(spare, keys, "container-spare", timeout=0.3)

    # Kill the agent with id 6 (its session ends, its token goes) and start another container: it gets 6.
    victim = ids.index(6)
    await buses[victim].close()
    await _until(lambda: 6 not in registry.alive, 2.0, "the token of robot 6 to go")
    newcomer = await _join(net.session("new"), keys, "container-new")
    assert (newcomer.agent_id, newcomer.role) == (6, "picker")

    # A restarted container (same instance name) gets its old id back.
    await buses[ids.index(2)].close()
    await _until(lambda: 2 not in registry.alive, 2.0, "the token of robot 2 to go")
    back = await _join(net.session("again"), keys, f"container-{ids.index(2)}")
    assert back.agent_id == 2
    await registry.close()


async def test_claim_without_a_registry_times_out_naming_the_key():
    net = LocalNetwork()
    with pytest.raises(RegistrationError, match="morph/nobody/registry.*no reply"):
        await claim_id(net.session("a"), RunKeys("nobody"), "x", timeout=0.3)


async def test_a_bad_request_is_refused_as_invalid_and_the_registry_keeps_serving():
    net = LocalNetwork()
    keys = RunKeys("reg-bad")
    await mount_registry(net.session("sim"), keys, 2, 1)
    agent = net.session("a")
    replies = await agent.get(keys.registry, payload=b"not msgpack", timeout=1.0)
    assert len(replies) == 1 and replies[0].ok
    answer = replies[0].decode()
    assert not answer.ok and reason_code(answer.reason) == INVALID
    with pytest.raises(RegistrationError, match="invalid: want_id 7"):
        await claim_id(agent, keys, "x", want_id=7, timeout=2.0)
    assert (await claim_id(agent, keys, "x", timeout=2.0)).agent_id == 0


# -- the queryable over ZenohBus (real sessions on 127.0.0.1, one agent a real process killed with SIGKILL) --------
_AGENT_PROCESS = textwrap.dedent("""
    import asyncio, sys
    from schemas.keys import RunKeys
    from schemas.messages import Role
    from services.bus.zenoh_bus import ZenohBus
    from services.bus.registry import claim_id

    async def main():
        endpoint, run, instance = sys.argv[1:4]
        keys = RunKeys(run)
        bus = await ZenohBus.open(instance, connect=endpoint, mode="client", connect_timeout=5.0)
        reply = await claim_id(bus, keys, instance, timeout=10.0)
        await bus.declare_token(keys.alive(reply.agent_id))
        print(reply.agent_id, Role(reply.role).value, flush=True)
        await asyncio.sleep(30)  # the test kills us long before; this bounds a leak if it does not
        await bus.close()

    asyncio.run(main())
""")


async def _read_line(proc: subprocess.Popen, timeout: float) -> str:
    loop = asyncio.get_running_loop()
    return await asyncio.wait_for(loop.run_in_executor(None, proc.stdout.readline), timeout)


async def test_registry_over_zenoh_eight_agents_kill_one_and_restart():
    from services.bus.zenoh_bus import ZenohBus, endpoint, free_port

    keys = RunKeys("reg-zenoh")
    where = endpoint(free_port())
    sim = await ZenohBus.open("sim", listen=where, mode="router")
    opened = [sim]
    proc = None
    try:
        registry = await mount_registry(sim, keys, A, P)
        # Agent "container-7" is a separate OS process; the other seven are sessions of this process.
        proc = subprocess.Popen([sys.executable, "-c", _AGENT_PROCESS, where, keys.run, "container-7"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        agents = [await ZenohBus.open(f"c{i}", connect=where, mode="client", connect_timeout=5.0)
                  for i in range(A + P - 1)]
        opened += agents
        replies = await asyncio.gather(*(_join(b, keys, f"container-{i}") for i, b in enumerate(agents)))
        line = (await _read_line(proc, 20.0)).split()
        assert line, f"agent process said nothing; stderr: {proc.stderr.read() if proc.poll() is not None else ''}"
        proc_id, proc_role = int(line[0]), line[1]
        ids = [r.agent_id for r in replies] + [proc_id]
        roles = [Role(r.role).value for r in replies] + [proc_role]
        assert sorted(ids) == list(range(A + P))
        assert sorted(roles) == sorted(["agv"] * A + ["picker"] * P)
        assert all((role == "agv") == (i < A) for i, role in zip(ids, roles))
        await _until(lambda: registry.alive == set(range(A + P)), 10.0, "all eight tokens at the sim")

        # SIGKILL the agent process: no goodbye, the router sees its link close and drops its token.
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=5)
        await _until(lambda: proc_id not in registry.alive, 15.0, f"robot {proc_id}'s token to go after SIGKILL")
        # The container restarts (same hostname): it gets its robot back.
        again = await ZenohBus.open("again", connect=where, mode="client", connect_timeout=5.0)
        opened.append(again)
        assert (await _join(again, keys, "container-7")).agent_id == proc_id

        # Another agent stops and a new container (new name) takes the freed id.
        gone = ids.index(0)
        await agents[gone].close()
        await _until(lambda: 0 not in registry.alive, 10.0, "robot 0's token to go")
        newcomer = await ZenohBus.open("new", connect=where, mode="client", connect_timeout=5.0)
        opened.append(newcomer)
        reply = await _join(newcomer, keys, "container-new")
        assert (reply.agent_id, Role(reply.role).value) == (0, "agv")
        assert registry.grants[-1] == ("container-new", 0)
    finally:
        if proc is not None and proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=5)
        for bus in reversed(opened):
            await bus.close()
