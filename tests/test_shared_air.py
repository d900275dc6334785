"""The shared air in the services: a network profile whose access points and radios have rate-limited queues runs in
``morph-sim run`` and ``morph-sim up`` through the air process, and gives the lab's answer — the same record, tick
for tick, the same queue drops, the same messages per delivery and view ages."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from morph_sim.lab.runner import EpisodeSpec, run_episode
from morph_sim.local import run_local
from services.faults.runtime import FaultRuntime
from services.metrics import catalogue
from services.monitor.recorder import read_metrics
from services.runconfig import RunConfig

SATURATED = str(Path(__file__).parent / "data" / "saturated.toml")
SEED = 42


def _lab(scale: str, policy: str, steps: int, network: str):
    return run_episode(EpisodeSpec(scale=scale, condition=policy, seed=SEED, steps=steps, network=network,
                                   fiedler_every=1))


def _shared_columns(lab, rows, steps: int, atol: float = 0.0) -> list[str]:
    """Every column the lab's table and a run's rows share, checked equal: exactly for the monitor's own rows, to the
    12 decimals metrics.csv writes (``atol``) for a record read back."""
    run = {c: np.array([np.nan if r[c] in ("", None) else float(r[c]) for r in rows]) for c in rows[0]}
    table = {"t": np.arange(steps, dtype=float), **lab.ticks}
    shared = [c for c in table if c in run]
    for c in shared:
        np.testing.assert_allclose(run[c], np.asarray(table[c], dtype=float), rtol=0, atol=atol, err_msg=c)
    return shared


# MORPH with -m slow: by default the broadcast Full-Graph, whose queues overflow (MORPH's learning under the air is
# checked at small by the up == run == lab test below)
@pytest.mark.parametrize("policy", ["full-broadcast", pytest.param("morph", marks=pytest.mark.slow)])
def test_run_gives_the_labs_episode_and_queue_drops_on_a_saturated_air(policy, tmp_path):
    """In one process (``morph-sim run``): every service's radio messages judged by the air service, each receiver
    holding what reaches it until the air's verdict; the record equals the lab's table column by column, and the
    network lost the same messages to the same causes."""
    steps = 120
    cfg = RunConfig(run_id=f"air-{policy}", scale="tiny", policy=policy, preset="reference", seed=SEED, steps=steps,
                    output_dir=tmp_path, network=SATURATED)
    rt = FaultRuntime.for_service(cfg, "sim")
    drops: dict[str, float] = {}  # the air's per access point drops, as the monitor streams them

    async def main():
        from schemas import MetricSample, RunKeys
        from services.bus import LocalNetwork

        net = LocalNetwork()
        probe = net.session("probe")
        await probe.subscribe(RunKeys(cfg.run_id).metric("net/ap_drops"), lambda sample: drops.__setitem__(
            sample.decode(MetricSample).labels["ap"], sample.decode(MetricSample).value))
        run = await run_local(cfg, faults=rt, network=net)
        await asyncio.sleep(0.1)
        await probe.close()
        return run

    result = asyncio.run(main())
    lab = _lab("tiny", policy, steps, SATURATED)
    shared = _shared_columns(lab, result.monitor.rows, steps)  # the values metrics.csv was written from
    assert {"deliveries_total", "requests", "commits", "links", "view_age_mean", "view_age_max"} <= set(shared)
    lost = rt.network_losses()
    assert {c: n for c, n in lost.items() if n} == {
        c.removeprefix("network_lost_"): n for c, n in lab.summary.items() if c.startswith("network_lost_") and n}
    if policy == "full-broadcast":  # its requests to every free picker overflow the queues: their order mattered
        assert lost["link_queue"] + lost["ap_queue"] > 0, lost
    # the air's own count of each access point's drops, streamed: every copy an access point dropped, once
    assert drops and sum(drops.values()) == lost["ap_queue"], (drops, lost)
    assert lab.summary["deliveries"] > 0


def check_up_run_and_lab(tmp_path, scale: str, policy: str, steps: int, network: str = "congested"):
    """``up`` (one process per robot, the air its own process) writes ``run``'s metrics.csv byte for byte (the
    network services' check: tests/test_network_services.py), and both are the lab's episode; returns (lab episode,
    up's record directory)."""
    from test_network_services import check_up_equals_run

    check_up_equals_run(tmp_path, scale, steps, profile=network, policy=policy)
    up = tmp_path / "up" / "eq"
    lab = _lab(scale, policy, steps, network)
    _shared_columns(lab, read_metrics(up), steps, atol=1e-12)
    return lab, up


def test_up_gives_the_labs_messages_per_delivery_and_view_ages_under_congested_tiny(tmp_path):
    """The broadcast Full-Graph (the talkiest policy) over Zenoh under ``congested``: the air process judges every
    radio message, and up's record equals run's and the lab's; its dispatch messages per delivery and its agents'
    view ages are the lab's."""
    lab, up = check_up_run_and_lab(tmp_path, "tiny", "full-broadcast", 120)
    summary = json.loads((up / "summary.json").read_text())
    rows = read_metrics(up)
    messages = summary["messages"]
    refusals = summary["finished"]["protocol"]["refused_stale"] * 2  # the sim tells both sides
    sent = messages.get("request", 0) + messages.get("reply", 0) + messages.get("commit", 0) + refusals
    deliveries = summary["deliveries_total"]
    assert deliveries == lab.summary["deliveries"] > 0
    assert sent / deliveries == lab.summary["messages_sent"] / lab.summary["deliveries"]
    ages = np.array([float(r["view_age_mean"]) for r in rows if r["view_age_mean"] != ""])
    assert ages.mean() == pytest.approx(lab.summary["view_age_mean"], rel=1e-9)
    assert list(rows[0]) == list(catalogue.COLUMNS)
    # the air was a process of its own, and it lost the lab's messages to the lab's causes (its last line: what it
    # judged)
    air = json.loads((up / "logs" / "air.log").read_text().strip().splitlines()[-1])
    assert air["lost"] == {c.removeprefix("network_lost_"): n for c, n in lab.summary.items()
                           if c.startswith("network_lost_")}, air
    assert sum(air["ap_drops"]) == air["lost"]["ap_queue"] and air["strays"] == 0 and air["rejected"] == 0
    # ... and it carried the lab's dispatch messages and bytes (the protocol's sizes: docs/faults.md)
    assert (air["messages"], air["bytes"]) == (lab.summary["messages_sent"], lab.summary["bytes_sent"])


# small at 400 ticks and medium with -m slow; by default small's first 60 ticks (robots start to deliver and roam)
@pytest.mark.parametrize(("scale", "steps"), [("small", 60), pytest.param("small", 400, marks=pytest.mark.slow),
                                              pytest.param("medium", 400, marks=pytest.mark.slow)])
def test_up_equals_run_and_the_lab_under_congested(tmp_path, scale, steps):
    lab, _ = check_up_run_and_lab(tmp_path, scale, "morph", steps)
    assert lab.summary["deliveries"] > 0


def test_a_run_whose_air_dies_stops_and_says_why(tmp_path, live_run):
    """The air's queues are the run's radio so far: killed mid-run it cannot be restarted, so `up` stops the run and
    its last line says why (exit 1), instead of a fleet waiting on verdicts that never come."""
    import os
    import signal

    from _procs import FEW_ROBOTS, run_processes

    up = live_run("airdies", "--network", "congested", "--steps", "100000", *FEW_ROBOTS, output_dir=tmp_path)
    up.wait_for_rows(5, timeout=60)
    ((_, air),) = run_processes(up.pid, "air")
    os.kill(air.pid, signal.SIGKILL)
    assert up.wait(timeout=60) == 1, up.stderr()[-2000:]
    last = (up.stdout() + up.stderr()).strip().splitlines()[-1]
    assert "the air process ended mid-run" in last and "the run was stopped" in last, last


# -- airtime faults: `morph-sim faults set --rate`, a schedule's rate specs --------------------------------------------
RATE_AT = 30


def _airtime_run(tmp_path, *, schedule: bool, runtime_command: bool, steps: int = 60):
    """A tiny run under `congested` in one process whose access points get 600 B/s of airtime (queues of 4) from
    tick RATE_AT: by a schedule file, or by an operator's `faults set --rate … --at-tick` sent at its first tick."""
    from schemas import FaultSpec, RunKeys
    from schemas.faults import Airtime
    from schemas.messages import FaultCommand
    from services.bus import LocalNetwork

    spec = FaultSpec(id="crowded", rate=Airtime(rate=600.0, limit=4))
    path = None
    if schedule:
        tmp_path.mkdir(parents=True, exist_ok=True)
        path = tmp_path / "rate.toml"
        path.write_text(f'[[at]]\ntick = {RATE_AT}\n[at.spec]\nid = "crowded"\nrate = {{ rate = 600.0, limit = 4 }}\n')
    cfg = RunConfig(run_id="rate", scale="tiny", policy="full-broadcast", seed=SEED, steps=steps, network="congested",
                    output_dir=tmp_path, fault_schedule=str(path) if path else None)
    rt = FaultRuntime.for_service(cfg, "sim")

    async def main():
        net = LocalNetwork()
        operator = net.session("operator")
        sent = asyncio.Event()

        def on_tick(sample):
            if runtime_command and not sent.is_set():
                sent.set()
                operator.put(RunKeys(cfg.run_id).faults, FaultCommand(op="set", spec=spec, at_tick=RATE_AT))

        await operator.subscribe(RunKeys(cfg.run_id).tick, on_tick)
        try:
            return await run_local(cfg, record=False, network=net, faults=rt)
        finally:
            await operator.close()

    return asyncio.run(main()), rt


def test_an_airtime_fault_at_a_tick_is_the_same_from_the_operator_and_from_a_schedule(tmp_path):
    """The air carries out `faults set --rate` from the tick it names, and the sim records it: the run equals the
    one with the same fault in its schedule, equals the clean run before that tick, and loses more to the queues
    after it."""
    clean, rt_clean = _airtime_run(tmp_path / "clean", schedule=False, runtime_command=False)
    scheduled, rt_s = _airtime_run(tmp_path / "scheduled", schedule=True, runtime_command=False)
    live, rt_l = _airtime_run(tmp_path / "live", schedule=False, runtime_command=True)
    assert live.sim.per_tick_deliveries == scheduled.sim.per_tick_deliveries
    assert rt_l.network_losses() == rt_s.network_losses()
    assert [(e.kind, e.t, e.details["fault_id"], e.details["spec"]["rate"]) for e in rt_l.controller.log
            if e.kind.startswith("fault.")] == [("fault.set", RATE_AT, "crowded", {"rate": 600.0, "limit": 4})]
    queued = lambda rt: rt.network_losses()["ap_queue"]  # noqa: E731
    assert queued(rt_l) > queued(rt_clean), (rt_l.network_losses(), rt_clean.network_losses())
    assert live.sim.per_tick_deliveries[:RATE_AT] == clean.sim.per_tick_deliveries[:RATE_AT]


def test_an_airtime_fault_is_refused_where_no_air_judges_the_radio(tmp_path):
    """A run without shared capacity has nobody to carry `--rate` out: its record owner (the sim) refuses it in one
    line naming the field; a robot's process gives no verdict on it."""
    from schemas import FaultSpec
    from schemas.faults import Airtime
    from schemas.messages import FaultCommand
    from services.bus import LocalNetwork
    from services.faults.controller import FaultController
    from services.faults.layer import FaultLayer

    command = FaultCommand(op="set", spec=FaultSpec(rate=Airtime(rate=500.0)))
    bus = LocalNetwork().session("sim")
    sim = FaultController(bus, "r", [FaultLayer("r")], clock=lambda: 3.0, events=True, air_run=False)
    reply = sim.handle(command)
    assert not reply.ok and reply.error.startswith("rate: this run has no shared air")
    agent = FaultController(bus, "r", [FaultLayer("r")], clock=lambda: 3.0, events=False, air_run=True)
    assert agent.handle(command) is None
    with pytest.raises(ValueError, match="give it alone"):
        FaultSpec(rate=Airtime(rate=500.0), loss={"percent": 5})


@pytest.mark.slow  # a long `up` so that the operator's command comes well before its tick (reduced: the test above)
def test_faults_set_rate_at_a_tick_on_a_live_up_run_equals_the_scheduled_run(tmp_path, live_run):
    import subprocess
    import sys

    steps, at = 1500, 1000
    up = live_run("airtime", "--network", "congested", "--policy", "full-broadcast", "--seed", str(SEED), "--steps",
                  str(steps), output_dir=tmp_path / "up")
    up.wait_for_rows(2, timeout=60)
    cli = subprocess.run([sys.executable, "-m", "morph_sim.cli", "faults", "set", "--run", "airtime", "--endpoint",
                          up.endpoint, "--output-dir", str(up.output_dir), "--rate", "600", "--limit", "4", "--id",
                          "crowded", "--at-tick", str(at), "--each"], capture_output=True, text=True, timeout=60)
    replies = [json.loads(line) for line in cli.stdout.splitlines()]
    assert cli.returncode == 0 and {r["source"] for r in replies} >= {"sim", "air"}, (cli.stdout, cli.stderr)
    assert up.wait(timeout=300) == 0, up.stderr()[-2000:]
    schedule = tmp_path / "rate.toml"
    schedule.write_text(f'[[at]]\ntick = {at}\n[at.spec]\nid = "crowded"\nrate = {{ rate = 600.0, limit = 4 }}\n')
    local = subprocess.run([sys.executable, "-m", "morph_sim.cli", "run", "--network", "congested", "--policy",
                            "full-broadcast", "--seed", str(SEED), "--steps", str(steps), "--run-id", "airtime",
                            "--fault-schedule", str(schedule), "--output-dir", str(tmp_path / "local")],
                           capture_output=True, text=True, timeout=300)
    assert local.returncode == 0, local.stderr[-2000:]
    assert read_metrics(tmp_path / "up" / "airtime") == read_metrics(tmp_path / "local" / "airtime")
    events = [json.loads(x) for x in (tmp_path / "up" / "airtime" / "events.jsonl").read_text().splitlines()]
    assert [(e["t"], e["details"]["fault_id"]) for e in events if e["kind"] == "fault.set"] == [(at, "crowded")]
