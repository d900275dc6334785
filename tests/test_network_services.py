"""The services under a network profile (``--network``): the Wi-Fi model is judged in every process's fault layer in
virtual time, hand-overs are in the run record and on the monitor's streams, and the run is reproducible — the same
``metrics.csv`` from ``morph-sim run`` twice and from ``morph-sim up``."""

from __future__ import annotations

import asyncio
import csv
import json
import subprocess
import sys

import pytest

from morph_sim.local import run_local
from services.bus import LocalNetwork
from services.faults.network import NetworkModel, load_profile
from services.faults.runtime import FaultRuntime
from services.runconfig import RunConfig
from services.world.layout import LayoutConfig, layout_for


def config(tmp_path, network: str | None, run_id: str = "net", **kw) -> RunConfig:
    values = dict(run_id=run_id, scale="tiny", policy="full", seed=3, steps=120, state_every=10,
                  snapshot_every=50, output_dir=tmp_path / run_id, network=network)
    values.update(kw)
    return RunConfig(**values)


def handovers_from_positions(cfg: RunConfig) -> list[tuple[int, int, int, int, float]]:
    """The hand-overs a pure model computes from the trajectories the monitor recorded."""
    model = NetworkModel(load_profile(cfg.network), layout_for(LayoutConfig.named(cfg.scale)), seed=cfg.seed)
    n = cfg.n_agents
    with open(cfg.record_dir / "positions.csv") as f:
        for row in csv.reader(f):
            t, xs, ys = int(row[0]), row[1:1 + n], row[1 + n:1 + 2 * n]
            model.observe_tick(t, cfg.dt, [(int(x), int(y)) for x, y in zip(xs, ys)])
    return [(round(e.time / cfg.dt), e.robot, e.from_ap, e.to_ap, round(e.outage, 6)) for e in model.events]


def recorded_handovers(cfg: RunConfig) -> list[tuple[int, int, int, int, float]]:
    out = []
    for line in (cfg.record_dir / "events.jsonl").read_text().splitlines():
        event = json.loads(line)
        if event["kind"] == "net.handover":
            d = event["details"]
            out.append((event["t"], d["robot"], d["from_ap"], d["to_ap"], d["outage"]))
    return out


STREAMED = ("net/handovers", "net/in_outage", "net/outage_seconds")


@pytest.fixture(scope="module")
def legacy(tmp_path_factory):
    """One recorded tiny run under legacy roaming (Full-Graph, 120 steps), shared by the tests that read it, with a
    probe on the bus that kept the last value of each of the monitor's :data:`STREAMED` metrics: (config, the sim's
    fault runtime, the run, {metric: last value})."""
    from schemas import MetricSample, RunKeys

    cfg = config(tmp_path_factory.mktemp("legacy"), "wifi-legacy-roaming")
    rt = FaultRuntime.for_service(cfg, "sim")
    seen: dict[str, float] = {}

    def on_metric(sample):
        msg = sample.decode(MetricSample)
        seen[msg.name] = msg.value

    async def main():
        net = LocalNetwork()
        probe = net.session("probe")
        for name in STREAMED:
            await probe.subscribe(RunKeys(cfg.run_id).metric(name), on_metric)
        run = await run_local(cfg, faults=rt, network=net)
        await asyncio.sleep(0.1)
        await probe.close()
        return run

    return cfg, rt, asyncio.run(main()), seen


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    """The same run without a network profile (the ideal network), shared by the tests that compare with it."""
    cfg = config(tmp_path_factory.mktemp("ideal"), None, run_id="ideal")
    return cfg, asyncio.run(run_local(cfg))


async def test_legacy_roaming_costs_messages_reports_handovers_and_is_reproducible(tmp_path, legacy, ideal):
    cfg, rt, first, _ = legacy
    assert first.sim.steps == 120 and first.sim.absences == 0  # an outage is not an absence: the run goes on
    lost = rt.network.stats.lost
    # the sim's uplinks: commitments only (acks are synchronisation and never faulted, docs/decisions.md)
    assert lost["dead_zone"] + lost["loss"] > 0
    assert rt.layers[0].stats.dropped == sum(lost.values())
    # a robot in an outage loses the sim's Tick first (its downlink), so it skips the tick and sends nothing the
    # sim could lose: the hand-over losses are the agents'
    agents = [r.network.stats.lost for r in rt.likes]
    assert len(agents) == cfg.n_agents and sum(a["handover"] for a in agents) > 0
    total = rt.network_losses()
    assert total["handover"] == sum(a["handover"] for a in agents) and total["loss"] > lost["loss"]

    # every hand-over in the record is the one the model computes from the recorded trajectories (and one per
    # hand-over: the sim reports them, nobody else)
    events = recorded_handovers(cfg)
    assert events and events == handovers_from_positions(cfg)
    # the run's replay hands over beyond the last tick only through the sim's final Tick: all within the run
    assert all(t <= cfg.steps + 1 for t, *_ in events)

    again = config(tmp_path, "wifi-legacy-roaming", run_id="net")
    await run_local(again)
    assert (again.record_dir / "metrics.csv").read_bytes() == (cfg.record_dir / "metrics.csv").read_bytes()

    clean = ideal[1]
    assert clean.sim.commits_applied > first.sim.commits_applied  # the Wi-Fi costs dispatches


async def test_lan_profile_is_the_ideal_network(tmp_path, ideal):
    lan, none = config(tmp_path, "lan", run_id="lan"), ideal[0]
    await run_local(lan)
    assert (lan.record_dir / "metrics.csv").read_bytes() == (none.record_dir / "metrics.csv").read_bytes()
    assert recorded_handovers(lan) == []  # lan: no roaming events (the default placement still has 4 APs ...)


def test_monitor_streams_handovers(legacy):
    """The shared run's probe (see ``legacy``) saw the monitor stream the hand-overs it recorded."""
    cfg, _, _, seen = legacy
    events = recorded_handovers(cfg)
    assert seen["net/handovers"] == pytest.approx(len([e for e in events if e[0] <= cfg.steps]), abs=3)
    assert seen["net/outage_seconds"] > 0


def test_cli_rejects_bad_network_values_with_one_line(capsys):
    from morph_sim.cli import main

    for value, expect, extra in (("wifi", "unknown profile 'wifi'", []), ("/nonexistent/net.toml", "cannot read", []),
                                 ("congested", "use --mode lockstep", ["--mode", "paced"])):
        assert main(["run", "--no-record", "--steps", "2", "--network", value, *extra]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "network" in lines[0] and expect in lines[0], lines


def check_up_equals_run(tmp_path, scale: str, steps: int, profile: str = "wifi-legacy-roaming",
                        policy: str = "morph"):
    """``up`` and ``run`` of one configuration write the same record; returns the in-process run's (config, LocalRun)."""
    run_up_args = dict(scale=scale, policy=policy, preset="reference", steps=steps, seed=42)
    argv_extra = ["--network", profile]
    _run_up(tmp_path / "up", "eq", argv_extra, **run_up_args)
    cfg = RunConfig(run_id="eq", scale=scale, policy=policy, preset="reference", steps=steps, seed=42,
                    state_every=10, snapshot_every=50, output_dir=tmp_path / "local", network=profile)
    run = asyncio.run(run_local(cfg))
    up, local = tmp_path / "up" / "eq", tmp_path / "local" / "eq"
    assert (up / "metrics.csv").read_bytes() == (local / "metrics.csv").read_bytes()
    assert recorded_handovers(cfg) == recorded_handovers(cfg.model_copy(update={"output_dir": tmp_path / "up"}))
    # runs long enough to compare something: robots delivered and handed over
    assert json.loads((local / "summary.json").read_text())["deliveries_total"] > 0 and recorded_handovers(cfg)
    return cfg, run


def _run_up(out, run_id, extra, *, scale, policy, preset, steps, seed, timeout=600):
    import morph_sim.cli  # noqa: F401  (the module run below)

    from _procs import kill_tree

    argv = [sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", scale, "--policy", policy,
            "--preset", preset, "--steps", str(steps), "--seed", str(seed), "--run-id", run_id,
            "--output-dir", str(out), "--state-every", "10", "--snapshot-every", "50", *extra]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        kill_tree(proc)
    assert proc.returncode == 0, err
    assert f"completed; {steps} rows" in out.strip().splitlines()[-1], out


# MORPH's up == run under the profile with -m slow: its twin by default is the broadcast Full-Graph's below (the same
# check_up_equals_run at Tiny, 120 steps), whose several requests per AGV a tick over Zenoh only it shows; MORPH's
# fleet broadcast under faults over up is tests/test_equivalence.py's lab == run == up.
@pytest.mark.slow
@pytest.mark.parametrize("steps", [120, 200])
def test_up_equals_run_under_legacy_roaming_tiny(tmp_path, steps):
    check_up_equals_run(tmp_path, "tiny", steps)


def test_up_equals_run_for_full_broadcast_under_legacy_roaming_tiny(tmp_path):
    """The broadcast Full-Graph over Zenoh (one process per robot, several requests per AGV a tick) writes the
    record the in-process run writes: the run under the Wi-Fi profile is reproducible. And it resolves its
    conflicts: every request to every free picker is a real, faultable message; the sim applies one commitment per
    AGV and refuses the others."""
    cfg, run = check_up_equals_run(tmp_path, "tiny", 120, policy="full-broadcast")
    assert run.sim.protocol["refused_stale"] > 0 and run.sim.commits_applied > 0
    summary = json.loads((cfg.record_dir / "summary.json").read_text())
    # more requests than AGV decisions that asked: each asked several pickers at once
    assert summary["messages"]["request"] > summary["messages"]["commit"]


@pytest.mark.slow
def test_up_equals_run_under_legacy_roaming_medium(tmp_path):
    check_up_equals_run(tmp_path, "medium", 400)


def test_report_draws_access_points_and_dead_zones(tmp_path, legacy):
    """The report's warehouse GIF of a run under a profile shows the profile's APs (on top) and dead zones (floor)."""
    from PIL import Image

    from services.monitor.report import load, warehouse_gif
    from services.world.render import COLORS, Frame, render_frame

    cfg = legacy[0]
    path = tmp_path / "w.gif"
    assert warehouse_gif(load(cfg.record_dir), path) is not None
    frame = Image.open(path).convert("RGB")
    colours = {c for _, c in frame.getcolors(1 << 16)}
    assert COLORS["access_point"] in colours and COLORS["dead_zone"] in colours

    lay = layout_for(LayoutConfig.named("tiny"))
    plain = dict(height=lay.H, width=lay.W, highway=lay.highway, goals=lay.goals, shelves=~lay.highway * 0,
                 requested=lay.highway * 0, agent_x=[0], agent_y=[0], agent_dir=[0], is_agv=[True], carrying=[False])
    img = render_frame(Frame(**plain, access_points=[(3.0, 3.0)]), cell_px=24)
    cx = 3 * 25 + 1 + 23 / 2
    assert img.getpixel((round(cx) + 3, round(cx) + 3)) == COLORS["access_point"]
    assert COLORS["access_point"] not in {c for _, c in render_frame(Frame(**plain), cell_px=24).getcolors(1 << 16)}


def test_communication_cost_is_counted_in_messages_and_bytes(legacy):
    """Every protocol message is real: the run record counts what the dispatch protocol sent, per kind, in messages
    and payload bytes, and per delivery and per agent per tick."""
    cfg, _, run, _ = legacy
    summary = json.loads((cfg.record_dir / "summary.json").read_text())
    comm = summary["communication"]
    kinds = comm["kinds"]
    assert set(kinds) == {"sim", "ack", "request", "reply", "commit", "policy"}
    assert comm["messages"] == sum(summary["messages"].get(k, 0) for k in kinds) > 0
    assert comm["bytes"] == sum(summary["bytes"].get(k, 0) for k in kinds) > comm["messages"]
    assert summary["messages"]["sim"] >= cfg.steps  # one Tick per step at least (the monitor is not faulted)
    assert comm["messages_per_agent_tick"] == pytest.approx(comm["messages"] / (cfg.steps * cfg.n_agents))
    if run.sim.deliveries:
        assert comm["bytes_per_delivery"] == pytest.approx(comm["bytes"] / run.sim.deliveries)


def test_a_robot_silent_past_silence_stop_stays_where_it_is(legacy):
    """AGV software stops a robot after silence_stop (0.1 s) of silence: under legacy roaming (outages 1.2–4.7 s) a
    robot stands still in every step that starts inside [outage start + 0.1 s, outage end) (fast roaming's outages
    never stop one: tests/test_network_model.py)."""
    cfg, rt, run, _ = legacy
    assert run.sim.network_stops > 0
    n = cfg.n_agents
    pos = {}
    with open(cfg.record_dir / "positions.csv") as f:
        for row in csv.reader(f):
            pos[int(row[0])] = [(int(x), int(y)) for x, y in zip(row[1:1 + n], row[1 + n:1 + 2 * n])]
    held = 0
    for t in range(cfg.steps):
        for robot in rt.network.silenced(t * cfg.dt, 0.1):
            assert pos[t + 1][robot] == pos[t][robot], (t, robot)
            held += 1
    assert held == run.sim.network_stops


# -- the lab under the same profile ------------------------------------------------------------------------------------
def _fate_log(monkeypatch):
    """Every judgement of a protocol or fleet message the fault layers make: (send time, key, sender, receiver,
    identity) -> delivered or lost."""
    from morph_sim.lab.network import FLEET_KEY
    from services.faults import layer as fault_layer

    log: dict[tuple, bool] = {}
    judge, judge_copies = fault_layer.FaultLayer.fate, fault_layer.FaultLayer.fate_copies

    def note(key, sender, receiver, at, msg, out) -> None:
        rel = key.split("/", 2)[2]
        if at is not None and receiver != "monitor" and (rel == FLEET_KEY or "/request/" in rel or "/reply/" in rel
                                                          or rel.endswith("/commit") or "refusal" in rel):
            log[(round(at, 6), rel, sender, receiver, msg)] = bool(out)

    def fate(self, key, sender, receiver, at=None, *, msg=None, size=0, radio=None):
        out = judge(self, key, sender, receiver, at, msg=msg, size=size, radio=radio)
        note(key, sender, receiver, at, msg, out)
        return out

    def fate_copies(self, key, sender, receivers, at, *, msg=None, size=0):  # the lab's fleet broadcast
        out = judge_copies(self, key, sender, receivers, at, msg=msg, size=size)
        for receiver, copy in zip(receivers, out):
            note(key, sender, receiver, at, msg, copy)
        return out

    monkeypatch.setattr(fault_layer.FaultLayer, "fate", fate)
    monkeypatch.setattr(fault_layer.FaultLayer, "fate_copies", fate_copies)
    return log


def test_lab_judges_each_message_as_the_services_do(tmp_path, monkeypatch):
    """The lab's event network asks the services' fault layer with the same message identities (publisher, sequence
    number per key) and the same positions, so every radio draw is the services' one: both send the same messages
    and lose the same ones, up to the first tick where their semantics part, if any (since the fleet broadcast is
    its own message in both, none: tests below check the whole runs equal)."""
    import math

    from morph_sim.lab.network import FLEET_KEY, EventNetwork
    from morph_sim.lab.runner import EpisodeSpec, run_episode
    from services.faults.runtime import NETWORK_LATENCY

    log = _fate_log(monkeypatch)
    cfg = config(tmp_path, "wifi-legacy-roaming", run_id="judge", steps=60)
    asyncio.run(run_local(cfg, record=False))
    services = dict(log)
    log.clear()
    init = EventNetwork.__init__

    def as_the_services(self, *a, **kw):  # the profile's delays count in the lab iff they count in the services
        init(self, *a, **kw)
        if self.layer is not None:
            self.layer.network_latency = NETWORK_LATENCY

    monkeypatch.setattr(EventNetwork, "__init__", as_the_services)
    run_episode(EpisodeSpec(scale="tiny", condition="full", seed=cfg.seed, steps=cfg.steps,
                            network="wifi-legacy-roaming"))
    lab = dict(log)
    # the runs part at the first message one of them sends and the other does not
    first = min((k[0] for k in set(services) ^ set(lab)), default=math.inf)
    assert first >= 10  # a stretch long enough to mean something
    before = {k: v for k, v in services.items() if k[0] < first}
    assert before == {k: v for k, v in lab.items() if k[0] < first}
    assert sum(1 for k in before if k[1] != FLEET_KEY) > 20
    # messages were lost on the way (hand-overs, dead zones, per-leg loss), fleet broadcasts among them: the draws
    # agree
    assert not all(v for k, v in before.items() if k[1] == FLEET_KEY)
    assert not all(v for k, v in before.items() if k[1] != FLEET_KEY)


def check_lab_equals_run(tmp_path, scale: str, steps: int, policy: str = "morph") -> None:
    import numpy as np

    from morph_sim.lab.runner import EpisodeSpec, run_episode

    cfg = RunConfig(run_id="labeq", scale=scale, policy=policy, preset="reference", steps=steps, seed=42,
                    state_every=10, snapshot_every=50, output_dir=tmp_path, network="wifi-legacy-roaming")
    asyncio.run(run_local(cfg))
    lab = run_episode(EpisodeSpec(scale=scale, condition=policy, seed=42, steps=steps,
                                  network="wifi-legacy-roaming"))
    with open(cfg.record_dir / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    np.testing.assert_array_equal([float(r["deliveries_total"]) for r in rows], lab.ticks["deliveries_total"])
    np.testing.assert_array_equal([float(r["links"]) for r in rows], lab.ticks["links"])


def test_lab_equals_run_under_legacy_roaming_tiny(tmp_path):
    check_lab_equals_run(tmp_path, "tiny", 200)


@pytest.mark.slow
def test_lab_equals_run_under_legacy_roaming_medium(tmp_path):
    check_lab_equals_run(tmp_path, "medium", 400)
