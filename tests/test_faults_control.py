"""Runtime fault control: the ctl/faults controller in every process, the TOML schedule, the
``morph-sim faults`` command (over real Zenoh), events with sim time, and ``reset`` that always heals."""

from __future__ import annotations

import argparse
import asyncio
import json
import textwrap

import pytest

from morph_sim.commands import faults as faults_cmd
from schemas import Event, FaultCommand, FaultReply, FaultSpec, Latency, Loss, Partition, RunKeys
from schemas.faults import Crash, Scope
from services.bus import LocalNetwork
from services.faults.controller import FaultController
from services.faults.layer import FaultLayer, install
from services.faults.schedule import load_schedule, parse_schedule
from services.faults.vtime import VirtualTime

RUN = "fc"
K = RunKeys(RUN)


async def drain() -> None:
    for _ in range(5):
        await asyncio.sleep(0)


async def start_processes(net: LocalNetwork, vt: VirtualTime, names=("sim", "1", "2"), **kw):
    """One bus, fault layer and controller per participant, as separate processes would each have."""
    out = {}
    for name in names:
        bus = net.session(name)
        layer = install(bus, FaultLayer(RUN, base_seed=1, vtime=vt))
        ctl = FaultController(bus, RUN, [layer], clock=vt.now, dt=1.0, events=name == "sim", **kw)
        await ctl.start()
        out[name] = (bus, layer, ctl)
    return out


async def test_query_reaches_every_process_and_events_carry_sim_time() -> None:
    net, vt = LocalNetwork(), VirtualTime(dt=1.0)
    procs = await start_processes(net, vt)
    operator = net.session("operator")
    events: list[Event] = []
    await operator.subscribe(K.events, lambda s: events.append(s.decode(Event)))
    vt.advance(3.0)
    spec = FaultSpec(id="cut", partition=Partition(from_agents=[1], to_agents=["sim"], direction="to"), duration=2.0)
    replies = [r.decode(FaultReply) for r in await operator.get(K.fault_queries, payload=FaultCommand(op="set", spec=spec))]
    assert sorted(r.source for r in replies) == ["1", "2", "sim"] and all(r.ok for r in replies)
    assert all([s.id for s in layer.active()] == ["cut"] for _, layer, _ in procs.values())
    listed = await operator.get(K.fault_queries)  # a bare query lists
    assert all([s.id for s in r.decode(FaultReply).active] == ["cut"] for r in listed)
    for b in (3.5, 4.0, 4.5, 5.0):
        vt.advance(b)
    await drain()
    assert all(layer.active() == [] for _, layer, _ in procs.values())  # auto-healed in every process
    assert [(e.kind, e.t, e.sim_time, e.details["fault_id"]) for e in events] == [
        ("fault.set", 3, 3.0, "cut"), ("fault.healed", 5, 5.0, "cut")]  # from the sim only, once each
    for bus, _, _ in procs.values():
        await bus.close()
    await operator.close()


async def test_reset_always_heals_everything_even_under_a_total_partition() -> None:
    net, vt = LocalNetwork(), VirtualTime(dt=1.0)
    procs = await start_processes(net, vt)
    operator = net.session("operator")
    cmd = FaultCommand(op="set", spec=FaultSpec(id="dark", loss=Loss(percent=100)))
    await operator.get(K.fault_queries, payload=cmd)
    await operator.get(K.fault_queries, payload=FaultCommand(op="set", spec=FaultSpec(id="slow", latency=Latency(delay=9))))
    await operator.publish(K.faults, FaultCommand(op="reset"))  # a put: control traffic is never faulted
    await drain()
    assert all(layer.active() == [] for _, layer, _ in procs.values())
    bad = [r.decode(FaultReply) for r in await operator.get(K.fault_queries, payload=FaultCommand(op="reset",
                                                                                          fault_id="nope"))]
    assert all(not r.ok and "nope" in r.error for r in bad)
    junk = [r.decode(FaultReply) for r in await operator.get(K.fault_queries, payload=b"\x93garbage")]
    assert all(not r.ok and r.error.startswith("bad fault command") for r in junk)
    for bus, _, _ in procs.values():
        await bus.close()
    await operator.close()


async def test_only_the_processes_that_carry_a_fault_out_give_a_verdict() -> None:
    """A crash is judged by the supervisor alone (the agents stay silent instead of answering "no supervisor"); a
    network fault by the processes with layers alone; `reset --id` succeeds where the fault was removed."""
    net, vt = LocalNetwork(), VirtualTime(dt=1.0)
    seen: list[FaultSpec] = []
    forgotten: list[str | None] = []
    bus = net.session("supervisor")
    ctl = FaultController(bus, RUN, [], clock=vt.now, on_crash=lambda s: seen.append(s) or None,
                          on_crash_reset=forgotten.append, fleet=8)
    crash = FaultSpec(id="k", crash=Crash(agent=3, every=100))
    assert ctl.handle(FaultCommand(op="set", spec=crash)).ok and seen == [crash]
    plain = FaultController(net.session("1"), RUN, [FaultLayer(RUN)], clock=vt.now, fleet=8)
    assert plain.handle(FaultCommand(op="set", spec=crash)) is None  # not its to judge
    assert plain.handle(FaultCommand(op="reset", fault_id="k")) is None  # the supervisor's crash, not its fault
    loss = FaultSpec(id="L1", loss=Loss(percent=10))
    assert ctl.handle(FaultCommand(op="set", spec=loss)) is None  # the supervisor has no layer to apply it to
    assert plain.handle(FaultCommand(op="set", spec=loss)).ok
    assert ctl.handle(FaultCommand(op="reset", fault_id="L1")) is None
    assert plain.handle(FaultCommand(op="reset", fault_id="L1")).ok and plain.layers[0].active() == []
    unknown = plain.handle(FaultCommand(op="reset", fault_id="nope"))
    assert not unknown.ok and unknown.error == "fault_id: no active fault 'nope'"
    assert ctl.handle(FaultCommand(op="reset", fault_id="k")).ok and forgotten == ["k"]
    assert [s.id for s in ctl.handle(FaultCommand(op="list")).active] == []
    # both halves of a mixed spec: the crash to the supervisor, the loss to the layers
    mixed = FaultSpec(id="m", loss=Loss(percent=5), crash=Crash(agent=1, at_tick=40))
    assert ctl.handle(FaultCommand(op="set", spec=mixed)).ok and seen[-1] == mixed
    assert plain.handle(FaultCommand(op="set", spec=mixed)).ok
    assert plain.layers[0].active()[0].crash is None and plain.layers[0].active()[0].loss is not None


async def test_a_fault_naming_a_robot_outside_the_fleet_is_refused_naming_the_field() -> None:
    vt = VirtualTime(dt=1.0)
    plain = FaultController(LocalNetwork().session("1"), RUN, [FaultLayer(RUN)], clock=vt.now, fleet=8)
    reply = plain.handle(FaultCommand(op="set", spec=FaultSpec(loss=Loss(percent=10), scope=Scope(agents=[2, 99]))))
    assert not reply.ok and reply.error.startswith("scope.agents: agent 99 is not in this run (robot ids 0..7")
    reply = plain.handle(FaultCommand(op="set", spec=FaultSpec(
        partition=Partition(from_agents=["sim"], to_agents=[8]))))
    assert not reply.ok and reply.error.startswith("partition.to_agents: agent 8")
    assert plain.layers[0].active() == []
    assert plain.handle(FaultCommand(op="set", spec=FaultSpec(loss=Loss(percent=1), scope=Scope(agents=[7, "sim"])))).ok


SCHEDULE = textwrap.dedent("""
    [[at]]
    tick = 2
    [at.spec]
    id = "burst"
    duration = 3.0
    [at.spec.loss]
    model = "gilbert_elliott"
    percent = 20
    burst_length = 4

    [[at]]
    time = 1.5
    [at.spec]
    id = "slow"
    latency = { delay = 0.5, jitter = 0.1, distribution = "normal" }

    [[at]]
    tick = 8
    op = "reset"
""")


async def test_schedule_applies_commands_at_their_sim_time(tmp_path) -> None:
    path = tmp_path / "faults.toml"
    path.write_text(SCHEDULE)
    schedule = load_schedule(path)
    assert [(at, c.op) for at, c in schedule.timeline(1.0)] == [(1.5, "set"), (2.0, "set"), (8.0, "reset")]
    net, vt = LocalNetwork(), VirtualTime(dt=1.0)
    bus = net.session("sim")
    layer = install(bus, FaultLayer(RUN, vtime=vt))
    ctl = FaultController(bus, RUN, [layer], clock=vt.now, events=True, schedule=schedule)
    vt.on_advance(ctl.advance)
    active = []
    for k in range(20):
        vt.advance(k * 0.5)
        active.append((k * 0.5, sorted(s.id for s in layer.active())))
    assert active[2] == (1.0, []) and active[3] == (1.5, ["slow"]) and active[4] == (2.0, ["burst", "slow"])
    assert active[10] == (5.0, ["slow"]) and active[16] == (8.0, [])
    assert [(e.kind, e.sim_time) for e in ctl.log] == [
        ("fault.set", 1.5), ("fault.set", 2.0), ("fault.healed", 5.0), ("fault.reset", 8.0)]
    await bus.close()


@pytest.mark.parametrize(("text", "names"), [
    ("[[at]]\ntick = 1\n[at.spec.loss]\npercent = 120\n", "at[0].spec.loss.percent"),
    ("[[at]]\ntick = 1\ntime = 2.0\nop = 'reset'\n", "at[0]"),
    ("[[at]]\ntick = 1\n[at.spec]\nlatency = { delay = -1 }\n", "at[0].spec.latency.delay"),
    ("[[at]]\ntick = 1\nop = 'set'\n", "spec"),
    ("[[at]]\ntik = 1\nop = 'reset'\n", "at[0].tik"),
])
def test_schedule_errors_name_the_field(text: str, names: str) -> None:
    import tomllib

    with pytest.raises(ValueError, match=r"schedule: .*" + names.replace("[", r"\[").replace("]", r"\]")):
        parse_schedule(tomllib.loads(text))


def cli_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    faults_cmd.add_arguments(parser)
    return parser.parse_args(argv)


def test_cli_builds_commands_and_rejects_bad_specs_naming_the_field() -> None:
    cmd = faults_cmd.build_command(cli_args("set", "--run", RUN, "--loss", "20", "--burst", "4", "--key",
                                            "agent/*/ack", "--agents", "1,2", "--id", "b", "--duration", "10"))
    assert cmd.spec.loss.model == "gilbert_elliott" and cmd.spec.loss.burst_length == 4
    assert cmd.spec.scope.agents == [1, 2] and cmd.spec.id == "b" and cmd.spec.duration == 10
    cmd = faults_cmd.build_command(cli_args("set", "--run", RUN, "--spec", '{"latency": {"delay": 0.5}}'))
    assert cmd.spec.latency.delay == 0.5 and cmd.spec.id  # an id is always assigned, the same in every process
    assert faults_cmd.build_command(cli_args("reset", "--run", RUN)).fault_id is None
    for argv, field in [(("--loss", "150"), "spec.loss.percent"), (("--delay", "-1"), "spec.latency.delay"),
                        (("--burst", "3"), "burst"), (("--key", "a/**/**"), "spec.scope.key_expr"),
                        (("--spec", '{"loss": {"percent": 5}, "bogus": 1}'), "spec.bogus"),
                        (("--spec", "{"), "spec"), ((), "spec")]:
        with pytest.raises(ValueError, match=field.replace(".", r"\.")):
            faults_cmd.build_command(cli_args("set", "--run", RUN, *argv))


async def test_cli_over_zenoh_sets_lists_and_resets(capsys) -> None:
    from services.bus.zenoh_bus import ZenohBus, endpoint, free_port

    ep = endpoint(free_port())
    vt = VirtualTime(dt=1.0)
    sim = await ZenohBus.open("sim", listen=ep, mode="router")
    agent = await ZenohBus.open("4", connect=ep, mode="client")
    layers = {}
    try:
        for bus in (sim, agent):
            layers[bus.identity] = layer = install(bus, FaultLayer(RUN, vtime=vt))
            await FaultController(bus, RUN, [layer], clock=vt.now, events=bus is sim).start()
        for _ in range(100):  # declarations propagate: wait until both controllers answer
            if len(await sim.get(K.fault_queries, timeout=0.5)) == 2:
                break
            await asyncio.sleep(0.05)
        code = await asyncio.to_thread(faults_cmd.run, cli_args(
            "set", "--run", RUN, "--endpoint", ep, "--delay", "0.5", "--id", "slow"))
        lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
        assert code == 0 and [x["sources"] for x in lines] == [["4", "sim"]]  # processes that agree: one line
        code = await asyncio.to_thread(faults_cmd.run, cli_args("list", "--run", RUN, "--endpoint", ep, "--each"))
        lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
        assert code == 0 and [x["source"] for x in lines] == ["4", "sim"]  # --each: one line per process
        assert all([s.id for s in layer.active()] == ["slow"] for layer in layers.values())
        code = await asyncio.to_thread(faults_cmd.run, cli_args("list", "--run", RUN, "--endpoint", ep))
        assert code == 0 and all(json.loads(x)["active"][0]["id"] == "slow"
                                 for x in capsys.readouterr().out.splitlines())
        code = await asyncio.to_thread(faults_cmd.run, cli_args("reset", "--run", RUN, "--endpoint", ep, "--id",
                                                                "nope"))
        assert code == 1 and "nope" in capsys.readouterr().out
        code = await asyncio.to_thread(faults_cmd.run, cli_args("reset", "--run", RUN, "--endpoint", ep))
        assert code == 0 and all(layer.active() == [] for layer in layers.values())
    finally:
        await agent.close()
        await sim.close()


def test_reset_by_id_succeeds_when_the_fault_is_gone_everywhere() -> None:
    """A process that never held the fault (an agent restarted after it was set) does not fail a reset that removed
    it everywhere else; a fault nobody held is still an error."""
    from schemas.messages import FaultReply

    command = FaultCommand(op="reset", fault_id="L1")
    absent = "fault_id: no active fault 'L1'"
    mixed = [FaultReply(ok=True, source="sim"), FaultReply(ok=False, error=absent, source="agent-1")]
    assert all(r.ok for r in faults_cmd.verdict(command, mixed, "r", "e"))
    nobody = [FaultReply(ok=False, error=absent, source="sim"), FaultReply(ok=False, error=absent, source="agent-1")]
    assert not any(r.ok for r in faults_cmd.verdict(command, nobody, "r", "e"))
    crash = FaultCommand(op="set", spec=FaultSpec(crash=Crash(agent=1, at_tick=9)))
    unserved = faults_cmd.verdict(crash, [FaultReply(ok=True, source="sim")], "r", "e")
    assert [r.ok for r in unserved] == [True, False] and "nobody would carry the crash out" in unserved[-1].error
    alone = faults_cmd.verdict(crash, [], "r", "e")
    assert len(alone) == 1 and alone[0].error.startswith("crash: no supervisor of run 'r' answered on e")


async def test_an_answer_counts_only_under_the_key_of_the_process_it_names(capsys) -> None:
    """A robot answering fault queries under its own key but naming the sim as its source (on a secured endpoint it
    can answer nowhere else) is left out of what `morph-sim faults` prints, and a line says so."""
    net, vt = LocalNetwork(), VirtualTime(dt=1.0)
    await start_processes(net, vt, names=("sim",))
    robot = net.session("agent-3")
    forged = FaultReply(ok=False, error="the sim is down", active=[], source="sim")
    await robot.declare_queryable(K.fault_answers("agent-3"), lambda q: q.reply(K.fault_answers("agent-3"), forged))
    replies = await faults_cmd.send("unused", RUN, FaultCommand(op="list"), timeout=0.2, bus=net.session("operator"))
    assert [(r.source, r.ok) for r in replies] == [("sim", True)]
    assert capsys.readouterr().err.strip() == ("morph-sim faults: ignored 1 answer(s) not given under the key of the "
                                               f"process they name ({K.fault_answers('agent-3')})")
