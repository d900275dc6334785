"""The services (sim clock, agents, monitor) over LocalBus in one event loop: protocol, record, presence, config."""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest

from morph_sim.cli import build_parser
from morph_sim.lab.runner import EpisodeSpec, run_episode
from morph_sim.local import run_local
from schemas import Stop
from schemas.keys import RunKeys
from schemas.tick import observation_from_tick, tick_from_observation
from services.bus.local import LocalNetwork
from services.metrics.catalogue import COLUMNS
from services.monitor.recorder import read_metrics, read_snapshots
from services.runconfig import RunConfig, add_config_arguments, config_from_args
from services.sim.wire import make_controller, world_fields
from services.supervisor.graph import PROGRAM, process_graph


def cfg(tmp_path, **kw) -> RunConfig:
    base = dict(run_id="t", scale="tiny", policy="morph", steps=60, seed=42, output_dir=tmp_path)
    base.update(kw)
    return RunConfig(**base)


async def test_local_run_end_to_end_writes_the_record(tmp_path):
    config = cfg(tmp_path, steps=60, state_every=10, snapshot_every=20)
    before = time.monotonic()
    run = await run_local(config)
    after = time.monotonic()
    assert run.sim.steps == 60 and run.sim.rejected == 0 and run.monitor.rejected == 0
    rows = run.monitor.rows
    assert [r["t"] for r in rows] == list(range(60))
    # the monitor's deliveries, from Tick messages only, equal the sim's own per-step count
    assert [r["deliveries"] for r in rows] == run.sim.per_tick_deliveries
    assert rows[-1]["deliveries_total"] == run.sim.deliveries
    assert all(r["acks"] == config.n_agents for r in rows)
    # pickers committed exactly what the sim applied (two-phase protocol ran)
    assert sum(r["commits"] for r in rows) >= run.sim.commits_applied > 0
    d = config.record_dir
    manifest = json.loads((d / "manifest.json").read_text())
    assert manifest["config"]["seed"] == 42 and manifest["versions"]["numpy"] == np.__version__
    assert "command_line" in manifest and "git_revision" in manifest
    on_disk = read_metrics(d)
    assert list(on_disk[0]) == list(COLUMNS) and len(on_disk) == 60
    assert [int(r["deliveries"]) for r in on_disk] == run.sim.per_tick_deliveries
    snaps = read_snapshots(d)
    assert sorted(snaps) == [0, 20, 40, 60]
    assert snaps[60]["W"].shape == (config.n_agents, config.n_agents)
    events = [json.loads(line) for line in (d / "events.jsonl").read_text().splitlines()]
    assert events[0]["kind"] == "run.started" and events[-1]["kind"] == "run.finished"
    # when each tick started, on the host's monotonic clock: within this test's own readings, in order, and the final
    # tick last (an observer on the host places its readings among the ticks by it)
    clock = events[-1]["details"]["tick_clock"]
    assert [t for t, _ in clock] == list(range(61))
    assert before < clock[0][1] and all(a[1] <= b[1] for a, b in zip(clock, clock[1:])) and clock[-1][1] < after
    summary = json.loads((d / "summary.json").read_text())
    assert summary["deliveries_total"] == run.sim.deliveries and summary["steps"] == 60


async def test_local_run_is_deterministic(tmp_path):
    a = await run_local(cfg(tmp_path, run_id="a", policy="morph", preset="paper"), record=False)
    b = await run_local(cfg(tmp_path, run_id="b", policy="morph", preset="paper"), record=False)
    assert a.monitor.rows == b.monitor.rows
    assert sorted(a.monitor.snapshots) == sorted(b.monitor.snapshots)
    for t in a.monitor.snapshots:
        np.testing.assert_array_equal(a.monitor.snapshots[t][0], b.monitor.snapshots[t][0])


@pytest.mark.parametrize("policy,preset", [("morph", "reference"), ("morph", "paper"), ("full", "reference"),
                                           ("full-broadcast", "reference"),
                                           ("tsg", "reference"), ("proximity", "reference"), ("none", "reference"),
                                           ("constant", "reference")])
async def test_services_equal_the_lab(tmp_path, policy, preset):
    """The lab drives the pure core directly; it must give the services' trajectories."""
    steps = 80
    spec = EpisodeSpec(scale="tiny", condition=policy, seed=7, steps=steps, preset=preset,
                       radius=4 if policy == "proximity" else None)
    lab = run_episode(spec)
    run = await run_local(cfg(tmp_path, policy=policy, preset=preset, seed=7, steps=steps, radius=4), record=False)
    cum = np.array([r["deliveries_total"] for r in run.monitor.rows], dtype=float)
    np.testing.assert_array_equal(cum, lab.ticks["deliveries_total"])
    np.testing.assert_array_equal(run.monitor.snapshots[steps][0], lab.final_weights)
    links = np.array([r["links"] for r in run.monitor.rows], dtype=float)
    np.testing.assert_array_equal(links, lab.ticks["links"])
    if policy == "morph":
        eta = np.array([r["eta"] for r in run.monitor.rows], dtype=float)
        np.testing.assert_allclose(eta, lab.ticks["eta"], rtol=0, atol=1e-12)


def test_tick_message_round_trips_the_observation():
    config = RunConfig(run_id="x", scale="tiny", steps=5)
    ctl = make_controller(config)
    for _ in range(3):
        obs = ctl.begin_tick()
        ctl.commit([])
        ctl.finish_tick()
    obs = ctl.begin_tick()
    names = ("cells", "mission", "target", "task", "needs_picker", "free_picker", "request_order",
             "prev_mission", "prev_target", "prev_task", "delivered", "reward", "loader", "handled")
    handled_seen = 0
    for _ in range(120):  # until loads and unloads have happened, so `handled` is exercised
        back = observation_from_tick(tick_from_observation(obs, obs.t * 1.0, world_fields(ctl, obs)), 1000)
        for name in names:
            np.testing.assert_array_equal(getattr(back, name), getattr(obs, name), err_msg=name)
        handled_seen += int(obs.handled.sum())
        ctl.commit([(p, a) for a, p in zip(obs.requesters().tolist(), np.flatnonzero(obs.free_picker).tolist())])
        ctl.finish_tick()
        obs = ctl.begin_tick()
    assert handled_seen > 0
    final = ctl.final_observation()
    assert observation_from_tick(tick_from_observation(final, 0.0, world_fields(ctl, final)), final.t).final
    back = observation_from_tick(tick_from_observation(obs, 3.0, world_fields(ctl, obs)))
    for name in names:
        np.testing.assert_array_equal(getattr(back, name), getattr(obs, name), err_msg=name)
    assert (back.t, back.n_agvs, back.n_pickers, back.grid_shape, back.has_previous) == \
        (obs.t, obs.n_agvs, obs.n_pickers, obs.grid_shape, obs.has_previous)


async def test_absent_agent_does_not_stall_the_run(tmp_path):
    """An agent that leaves (its liveliness token goes) is absent: the sim stops waiting for it and goes on."""
    config = cfg(tmp_path, steps=40, phase_timeout=30.0)
    net = LocalNetwork()
    from services.agent.roles import make_agent
    from services.monitor.service import MonitorService
    from services.sim.service import SimService

    monitor = MonitorService(config, net.session("monitor"), record=False)
    agents = [make_agent(config, net.session(f"agent-{i}"), i) for i in range(config.n_agents)]
    ticks_seen = []
    sim = SimService(config, net.session("sim"), on_tick=lambda t, obs: ticks_seen.append(t))
    tasks = [asyncio.create_task(s.run()) for s in (monitor, *agents)]

    async def leave():
        while len(ticks_seen) < 10:
            await asyncio.sleep(0)
        agents[1].stop()  # AGV 1 leaves mid-run

    leaver = asyncio.create_task(leave())
    result = await asyncio.wait_for(sim.run(), 20)
    await asyncio.wait_for(asyncio.gather(*tasks, leaver), 10)
    assert result.steps == 40 and result.absences == 1
    assert 1 not in sim.present()
    assert sim.ctl.idle == {1} and sim.ctl.actions()[1] == 0  # its robot gets no new target
    assert agents[1].counters.ticks < 40 <= agents[0].counters.ticks


async def test_stop_on_ctl_stop(tmp_path):
    config = cfg(tmp_path, steps=100_000)
    net = LocalNetwork()
    operator = net.session("operator")

    under_way = asyncio.Event()
    await operator.subscribe(RunKeys(config.run_id).tick, lambda sample: under_way.set())

    async def stop_soon():
        await under_way.wait()  # the first tick is out: the run is under way
        await operator.publish(RunKeys(config.run_id).stop, Stop(reason="operator"))

    stopper = asyncio.create_task(stop_soon())
    run = await asyncio.wait_for(run_local(config, network=net), 30)
    await stopper
    assert run.sim.stopped_early == "operator" and 0 < run.sim.steps < 100_000
    assert len(run.monitor.rows) == run.sim.steps  # every completed step is in the record
    summary = json.loads((config.record_dir / "summary.json").read_text())
    assert summary["finished"]["stopped_early"] == "operator"
    await operator.close()


async def test_paced_mode_runs_at_the_period(tmp_path):
    config = cfg(tmp_path, steps=10, mode="paced", period=0.05)
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    run = await run_local(config, record=False)
    assert run.sim.steps == 10 and loop.time() - t0 >= 9 * 0.05


async def test_paced_agvs_act_on_what_they_have_while_answers_are_on_their_way(tmp_path):
    """Paced (a real-time fleet): replies delayed by three periods (wall time) never hold an AGV's decision point or
    its ack; every agent acks every tick and the answers take effect when they arrive. (An AGV that waited for its
    answer, as in lockstep, missed its ack in about a quarter of the ticks.)"""
    sched = tmp_path / "slow.toml"
    sched.write_text('[[at]]\ntick = 0\n[at.spec]\nscope = { key_expr = "agent/*/reply/*" }\nlatency = { delay = 0.3 }\n')
    config = cfg(tmp_path, policy="full", steps=30, mode="paced", period=0.1, fault_time="wall", fault_schedule=sched)
    run = await run_local(config, record=False)
    assert run.sim.steps == 30 and run.sim.protocol["requests"] > 5
    missing = [r["t"] for r in run.monitor.rows if r["acks"] < config.n_agents]
    assert len(missing) <= 2, missing  # (a loaded machine may miss the 45 ms ack deadline once or twice)


async def test_a_paced_sim_that_stalled_starts_its_schedule_again_instead_of_running_missed_ticks(tmp_path):
    """A stall of twenty periods (the machine froze) costs the fleet that time once: the next ticks keep the period,
    no burst of missed ticks back to back, and ``run.finished`` says so (``pace``)."""
    import time

    period, starts = 0.1, {}

    def stall(t: int, _deliveries: int) -> None:
        starts[t] = time.monotonic()  # at the start of tick t
        if t == 10:
            time.sleep(20 * period)

    config = cfg(tmp_path, policy="full", steps=25, mode="paced", period=period)
    run = await run_local(config, record=False, progress=stall)
    pace = run.sim.pace.summary()
    assert run.sim.steps == 25 and pace["rescheduled"] >= 1, pace
    assert pace["worst"][0][0] == 11 and pace["worst"][0][1] >= 20 * period
    # the ten ticks after it keep the period (a tick after one that overran on a loaded machine may start early);
    # the missed ticks run back to back would be a few milliseconds apart
    burst = [t for t in range(12, 22) if starts[t] - starts[t - 1] < period / 4]
    assert len(burst) <= 2, (burst, pace)
    assert run.monitor.finished["pace"] == pace


@pytest.mark.parametrize("back_after", [0.3, None], ids=["restarted", "gone"])
async def test_a_lockstep_sim_waits_for_a_monitor_that_left_until_it_is_back_or_a_phase_timeout(tmp_path, back_after,
                                                                                               monkeypatch):
    """The monitor's liveliness token goes at tick 20 (a killed monitor; its supervisor restarts it). The sim starts
    no tick while it is away: a run at full speed would otherwise end before the restarted monitor is back and close
    the endpoint on it, and the record would not even declare what it lost. One that stays away is waited for one
    phase timeout; then the run goes on without it. Judged by the sim's own waits for the monitor (which tick, how
    long), not by the intervals between ticks, which a loaded machine stretches whatever the sim does."""
    import time

    from services.bus.base import Declared
    from services.sim.presence import Presence

    config = cfg(tmp_path, policy="full", steps=40, phase_timeout=3.0)
    key, buses, left_at = RunKeys(config.run_id).alive("monitor"), {}, {}
    waits: dict[int, float] = {}  # tick -> seconds the sim waited for the monitor before starting it
    ended: dict[int, float] = {}  # tick -> when that wait ended
    keep_window = Presence._keep_monitor_window

    async def timed(self, t: int) -> None:
        started = time.monotonic()
        await keep_window(self, t)
        ended[t] = time.monotonic()
        waits[t] = ended[t] - started

    monkeypatch.setattr(Presence, "_keep_monitor_window", timed)

    async def leave_and_return(bus) -> None:
        token = next(e for e in bus._entities if isinstance(e, Declared) and e.key_expr == key)
        await token.close()
        left_at["t"] = time.monotonic()
        if back_after is not None:
            await asyncio.sleep(back_after)
            back = await bus.declare_token(key)
            left_at["back"] = time.monotonic()
            # the returned monitor leaves at the end of the run, as the restarted process would (otherwise the sim
            # waits its whole leave timeout for the token at the end)
            await bus.subscribe(RunKeys(config.run_id).stop, lambda _: asyncio.get_running_loop().create_task(
                back.close()))

    def at_tick(t: int, _deliveries: int) -> None:
        if t == 20:
            asyncio.get_running_loop().create_task(leave_and_return(buses["monitor"]))

    run = await run_local(config, record=False, progress=at_tick,
                          on_bus=lambda name, bus: buses.__setitem__(name, bus))
    assert run.sim.steps == config.steps and run.sim.stopped_early is None
    waited = {t: w for t, w in waits.items() if w >= 0.1}
    assert len(waited) == 1 and 20 < min(waited) <= 25, waits  # one tick, after it left, waited for it
    ((tick, waited),) = waited.items()
    if back_after is None:
        assert waited >= config.phase_timeout, waits
    else:
        # it waited until the token came back, however late the machine let that be, and not for the timeout
        assert ended[tick] >= left_at["back"] and waited < config.phase_timeout, (waits, left_at)


# -- configuration -------------------------------------------------------------------------------------------------
def test_runconfig_env_flags_and_argv_agree():
    c = RunConfig(run_id="r1", scale="small", policy="proximity", radius=3, seed=5, steps=77, mode="paced")
    assert RunConfig.from_env(c.to_env()) == c
    import argparse

    p = argparse.ArgumentParser()
    add_config_arguments(p)
    assert config_from_args(p.parse_args(c.to_argv()), environ={}) == c
    # flags override the environment, the environment overrides the defaults
    env = {"MORPH_SEED": "9", "MORPH_STEPS": "12", "MORPH_RUN_ID": "e"}
    got = config_from_args(p.parse_args(["--steps", "13"]), environ=env)
    assert (got.seed, got.steps, got.run_id) == (9, 13, "e")
    assert c.n_agvs == 8 and c.n_pickers == 4 and c.role_of(0) == "agv" and c.role_of(11) == "picker"


@pytest.mark.parametrize("field,value", [("scale", "huge"), ("policy", "magic"), ("seed", "-1"), ("steps", "0"),
                                         ("run_id", "a/b"), ("endpoint", "127.0.0.1:7447"), ("mode", "fast"),
                                         ("ablation", "nope")])
def test_runconfig_rejects_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        RunConfig.from_env({"MORPH_RUN_ID": "ok", RunConfig.env_name(field): value})


def test_process_graph_is_real_cli_invocations():
    config = RunConfig(run_id="g", scale="tiny", policy="morph", steps=10)
    specs = process_graph(config, "tcp/127.0.0.1:7447")
    assert [s.name for s in specs] == ["sim"] + [f"agent-{i}" for i in range(8)] + ["monitor"]
    parser = build_parser()
    for spec in specs:
        assert spec.argv[0] == PROGRAM
        args = parser.parse_args(list(spec.argv[1:]))  # every flag is real
        assert args.command == spec.role
        assert config_from_args(args, environ={}).run_id == "g"
        assert spec.env["ZENOH_RUNTIME"].startswith("(rx:")
    assert specs[0].argv[-2:] == ("--listen", "tcp/127.0.0.1:7447")
    assert all(s.argv[-2:] == ("--endpoint", "tcp/127.0.0.1:7447") for s in specs[1:])
    assert [s.restart for s in specs] == ["never"] + ["on-failure"] * 8 + ["on-failure"]  # the monitor restarts too
    external = process_graph(config.model_copy(update={"endpoint": "tcp/127.0.0.1:9000"}), "tcp/127.0.0.1:9000")
    assert external[0].argv[-2:] == ("--endpoint", "tcp/127.0.0.1:9000")


async def test_monitor_answers_late_joiners_with_the_latest_state(tmp_path):
    from schemas import AgentState, MetricSample

    # the joiner takes its answers once the first metrics are out (a few ticks in); the run's remaining ticks only
    # keep it going meanwhile (on a loaded machine as well: a hundred ticks and more after those first ones)
    config = cfg(tmp_path, steps=150)
    net = LocalNetwork()
    joiner = net.session("late-joiner")
    keys = RunKeys(config.run_id)
    answers = {}

    async def join_late():
        while True:
            replies = await joiner.get(keys.latest_all, timeout=1.0)
            if any("/metrics/" in r.key for r in replies):
                answers.update({r.key: r for r in replies})
                return
            await asyncio.sleep(0.05)

    task = asyncio.create_task(join_late())
    run = await asyncio.wait_for(run_local(config, network=net, record=False), 60)
    await asyncio.wait_for(task, 5)
    metric = answers[keys.latest("metrics", "deliveries_total")].decode(MetricSample)
    assert 0 <= metric.t < config.steps and metric.value <= run.sim.deliveries
    states = [k for k in answers if "/state/agent/" in k]
    assert len(states) == config.n_agents
    assert answers[keys.latest("agent", "3")].decode(AgentState).agent == 3
    await joiner.close()


async def test_the_record_s_last_row_waits_for_final_acks_the_end_of_run_overtook(tmp_path):
    """The sim ends the run once it has every robot's final ack, but its end of run (``run.finished``, then its stop)
    can reach the monitor before acks it routed on: the record's last row still holds every robot's final links and
    η, as it does when the acks come first."""
    from schemas import Ack
    from schemas.codec import decode
    from services.agent.roles import make_agent
    from services.monitor.service import MonitorService
    from services.sim.service import SimService

    steps = 30

    async def last_row(overtaken: bool) -> dict:
        config = cfg(tmp_path, steps=steps, run_id=f"overtaken-{overtaken}")
        net = LocalNetwork()
        monitor = MonitorService(config, net.session("monitor"), record=False, max_rate=0.0)
        keys = RunKeys(config.run_id)
        handle, held = monitor.on_sample, []

        def arriving(sample) -> None:
            # the final tick's acks held back until the sim's stop has been handled, then handed in one by one
            if overtaken and sample.key.endswith("/ack") and decode(sample.payload, Ack).t == steps:
                held.append(sample)
                return
            handle(sample)
            if sample.key == keys.stop:
                loop = asyncio.get_running_loop()
                for i, late in enumerate(held):
                    loop.call_later(0.05 * (i + 1), handle, late)

        monitor.on_sample = arriving  # (before run() subscribes it)
        agents = [make_agent(config, net.session(f"agent-{i}"), i) for i in range(config.n_agents)]
        tasks = [asyncio.create_task(s.run()) for s in (monitor, *agents)]
        await asyncio.wait_for(SimService(config, net.session("sim")).run(), 30)
        result, *_ = await asyncio.wait_for(asyncio.gather(*tasks), 10)
        if overtaken:
            assert len(held) == config.n_agents  # every final ack came after the end of run
        assert len(result.rows) == steps
        return result.rows[-1]

    in_order, overtaken = await last_row(False), await last_row(True)
    assert {k: overtaken[k] for k in ("t", "links", "eta", "lambda2")} == \
        {k: in_order[k] for k in ("t", "links", "eta", "lambda2")}
