"""``morph-sim up``: real OS processes over Zenoh on loopback. Every pid is checked gone afterwards (psutil).

Each test bounds every wait and kills whatever it started by pid if something goes wrong.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import signal
import time

import pytest

from services.monitor.recorder import read_metrics
from services.runconfig import RunConfig

from _procs import FEW_ROBOTS, agent_pids, alive, descendants, kill_all

UP_TIMEOUT = 120
FEW = {"agvs": 2, "pickers": 1}  # FEW_ROBOTS, for a RunConfig


def test_up_runs_to_completion_and_leaves_no_process(shared_default_up):
    """The shared default ``up`` run (tests/conftest.py): it completes, every tick acked by all 8 agents, and none of
    its processes is alive once ``up`` has ended."""
    shared = shared_default_up.finished()
    up = shared.run
    steps = int(up.argv[up.argv.index("--steps") + 1])
    assert up.proc.returncode == 0, up.stderr()[-3000:]
    assert "completed" in up.stdout()
    assert len(up.seen) >= 10  # sim + 8 agents + monitor
    rows = read_metrics(up.record)
    assert [int(r["t"]) for r in rows] == list(range(steps))
    assert all(int(r["acks"]) == 8 for r in rows)
    assert shared.left_behind == [], f"processes left behind: {shared.left_behind}"


# The endless run the restart test acts on and the SIGTERM test ends (tests/conftest.py, endless_run: the run the
# tests of other files may have used before, or a run of its own): three robots, paced.
FLEET = 3


def _first_rows(up) -> None:
    metrics = up.record / "metrics.csv"
    up.wait_until(lambda: metrics.exists() and metrics.stat().st_size > 200, UP_TIMEOUT, "the first rows")


def test_up_restarts_an_agent_that_dies(endless_run):
    up = endless_run()
    _first_rows(up)

    victim = agent_pids(up.pid, 2)
    assert len(victim) == 1
    before = up.rows()  # (rows on disk lag the run: the first rows without its ack may come later)
    os.kill(victim[0], signal.SIGKILL)
    restarted: list[int] = []

    def rejoined() -> bool:
        restarted[:] = [p for p in agent_pids(up.pid, 2) if p != victim[0]]
        if not restarted:
            return False
        rows = read_metrics(up.record)[before:]
        return len(rows) > 5 and int(rows[-1]["acks"]) == FLEET and any(int(r["acks"]) == FLEET - 1 for r in rows)

    up.wait_until(rejoined, 60, "agent 2 restarted and rejoined")
    events = up.record / "events.jsonl"

    def recorded() -> bool:  # the restart is in the run record
        return any(e["kind"] == "agent.restart" and e["details"]["agent"] == 2
                   for e in map(json.loads, events.read_text().splitlines()))

    up.wait_until(recorded, 30, "the agent.restart event in the record")


def test_sigterm_ends_every_process_within_5s(endless_run):
    up = endless_run()
    try:
        _first_rows(up)
        up.seen |= descendants(up.pid)
        t0 = time.monotonic()
        up.signal(signal.SIGTERM)
        up.proc.wait(timeout=10)
        elapsed = time.monotonic() - t0
        assert elapsed < 5.0, f"up took {elapsed:.1f} s to end"  # the documented bound of Ctrl-C/SIGTERM
        assert up.proc.returncode != 0  # interrupted, not completed
        deadline = time.monotonic() + 1.0
        while alive(up.seen) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        left = up.left_behind()
        kill_all(left)
    assert len(up.seen) >= FLEET + 2  # the sim, the agents and the monitor
    assert left == [], f"processes left behind: {left}"
    # the record of the interrupted run is complete up to where it stopped
    summary = (up.record / "summary.json").read_text()
    assert "stopped_early" in summary


def test_up_fails_clearly_when_nothing_listens_on_the_endpoint(live_run):
    from services.bus.zenoh_bus import free_port

    up = live_run("nolisten", "--steps", "5", "--endpoint", f"tcp/127.0.0.1:{free_port()}", listen=False)
    assert up.wait(30) == 1
    assert "nothing listens on the Zenoh endpoint" in up.stderr()


async def test_supervisor_reports_a_process_that_cannot_start(tmp_path):
    """A child that exits before the run starts makes the supervisor fail with its name and log; nothing is left.
    (Three robots, as FEW_ROBOTS: one broken agent among any number of them.)"""
    from services.supervisor.launcher import StartError, Supervisor

    config = RunConfig(run_id="broken", scale="tiny", steps=5, output_dir=tmp_path, ready_timeout=60, **FEW)
    sup = Supervisor(config)
    child = sup.children["agent-2"]
    child.spec = dataclasses.replace(child.spec, argv=(*child.spec.argv, "--no-such-flag"))
    try:
        with pytest.raises(StartError, match="agent-2 exited with status 2") as info:
            await asyncio.wait_for(sup.run(), UP_TIMEOUT)
        assert "--no-such-flag" in str(info.value)  # the log tail shows argparse's complaint
    finally:
        left = alive(sup.all_pids)
        kill_all(left)
    assert sup.all_pids and left == []


def test_up_joins_an_existing_router_with_endpoint(live_run, tmp_path):
    """``--endpoint``: every process, the sim included, is a client of a router that is already running."""
    from services.bus.zenoh_bus import endpoint, free_port, zenoh, zenoh_config

    ep = endpoint(free_port())
    router = zenoh.open(zenoh_config(listen=ep, mode="router"))
    try:
        up = live_run("ext", "--policy", "tsg", "--steps", "30", "--endpoint", ep, *FEW_ROBOTS, listen=False)
        assert up.wait(UP_TIMEOUT) == 0, up.stderr()
        sim_log = (tmp_path / "ext" / "logs" / "sim.log").read_text()
        assert f"--endpoint {ep}" in sim_log and "--listen" not in sim_log
        assert len(read_metrics(tmp_path / "ext")) == 30
    finally:
        router.close()
        left = up.left_behind()
        kill_all(left)
    assert left == [], f"processes left behind: {left}"


async def test_a_stalled_run_fails_clearly_instead_of_hanging(tmp_path):
    """If ticks stop inside Zenoh (seen once: the sim's router blocked on a full socket, where no phase deadline can
    fire), the supervisor fails after its stall timeout with the tick it stalled at, and nothing is left. Here the
    sim is frozen with SIGSTOP (in a fleet of three robots, as FEW_ROBOTS: a stall is the sim's, whatever the fleet)."""
    import os
    import signal

    from services.supervisor.launcher import RunStalled, Supervisor

    config = RunConfig(run_id="stall", scale="tiny", steps=100000, output_dir=tmp_path, ready_timeout=60, **FEW)
    sup = Supervisor(config, stall_timeout=3.0)

    async def freeze_the_sim() -> None:
        while sup.progress.t < 20:
            await asyncio.sleep(0.05)
        os.kill(sup.children["sim"].pid, signal.SIGSTOP)

    freezer = asyncio.create_task(freeze_the_sim())
    try:
        with pytest.raises(RunStalled, match=r"the run stalled: no tick after tick \d+ for 3 s"):
            await asyncio.wait_for(sup.run(), UP_TIMEOUT)
    finally:
        freezer.cancel()
        left = alive(sup.all_pids)
        kill_all(left)
    assert sup.all_pids and left == []
    assert len(read_metrics(tmp_path / "stall")) >= 15  # the record up to the stall is kept (tick 20 was seen)
