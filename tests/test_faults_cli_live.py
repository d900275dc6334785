"""``morph-sim faults`` against a live ``morph-sim up``, as an operator uses it: real CLI processes, their exit codes
and the lines they print, and the run record afterwards.

* a crash set ~70 ticks ahead is carried out at that tick (the supervisor kills and restarts the agent), is in the
  events once, and the report draws one crash line for it; the CLI exits 0 with the supervisor's verdict alone;
* a crash at a tick already past is refused with one line naming ``crash.at_tick`` (exit 1) and never happens;
* ``--agents 99`` on a 3-robot run is refused naming the field (exit 1);
* ``reset --id`` of a fault that was set succeeds (exit 0).

The run is paced (a CLI process needs one to two seconds to start and connect on a loaded machine, so "70 ticks
ahead" must be longer than that); the supervisor acts on the Tick itself, lock-step or paced alike. Every wait is
bounded; whatever the test started is killed by pid on failure.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time

from schemas.keys import RunKeys
from schemas.tick import decode_tick
from services.bus.zenoh_bus import endpoint, free_port
from services.monitor.recorder import read_metrics
from services.monitor.report import load

from _procs import FEW_ROBOTS, alive, descendants, kill_all

STEPS = 160  # the crash comes about tick 80, the last command ends by tick ~110 (12.8 s in all)
PERIOD = 0.08  # s per tick: 70 ticks = 5.6 s, more than a CLI process needs to answer on a loaded machine
AHEAD = 70
VICTIM = 1
# three robots: the commands' verdicts and the crash are the same whatever the fleet (robot ids 0..2, AGVs 0 and 1)
ROBOTS = 3
UP_TIMEOUT = 120


async def _cli(*argv: str, timeout: float = 30) -> tuple[int, list[str], str]:
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "morph_sim.cli", *argv,
                                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        out, err = await asyncio.wait_for(proc.communicate(), timeout)
    except asyncio.TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    return proc.returncode, out.decode().splitlines(), err.decode()


async def test_faults_cli_verdicts_and_a_crash_carried_out_at_its_tick(tmp_path):
    from services.process import open_bus

    port = free_port()
    ep = endpoint(port)
    run_id = "faultcli"
    argv = [sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny", "--run-id", run_id,
            "--output-dir", str(tmp_path), "--policy", "full", "--seed", "3", "--steps", str(STEPS),
            "--mode", "paced", "--period", str(PERIOD), "--phase-timeout", "3", *FEW_ROBOTS, "--listen", ep]
    up = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: set[int] = set()
    ticks: list[int] = []
    bus = None
    # a secured run: the CLI finds the operator's credentials in the run directory, this test's session uses them too
    ctl = ("--run", run_id, "--endpoint", ep, "--output-dir", str(tmp_path))
    operator = str(tmp_path / run_id / "credentials" / "operator.json5")
    try:
        deadline = time.monotonic() + 60
        while bus is None:
            seen |= descendants(up.pid)
            try:
                bus = await open_bus("test-operator", connect=ep, config_file=operator)
            except (ConnectionError, ValueError):  # (ValueError: up has not written the credentials yet)
                assert up.poll() is None and time.monotonic() < deadline, up.communicate(timeout=10)[1][-3000:]
                await asyncio.sleep(0.3)
        await bus.subscribe(RunKeys(run_id).tick, lambda s: ticks.append(decode_tick(s.payload).t))
        while not ticks or ticks[-1] < 5:
            seen |= descendants(up.pid)
            assert up.poll() is None and time.monotonic() < deadline, "the run did not start"
            await asyncio.sleep(0.1)

        at = ticks[-1] + AHEAD
        code, lines, err = await _cli("faults", "set", *ctl, "--spec",
                                      json.dumps({"crash": {"agent": VICTIM, "at_tick": at}}))
        assert ticks[-1] < at, f"the command took longer than {AHEAD} ticks; the test cannot judge it"
        assert code == 0 and len(lines) == 1, (code, lines, err)
        reply = json.loads(lines[0])
        assert reply["ok"] and reply["sources"] == ["supervisor"]  # no agent answers for a crash
        assert [s["crash"]["at_tick"] for s in reply["active"]] == [at]

        # the refusals and a loss window set and reset, side by side while the crash approaches
        async def loss_window() -> tuple:
            # (on agent states, which only the unfaulted monitor receives: the acks below stay the crash's alone)
            set_l1 = await _cli("faults", "set", *ctl, "--loss", "10", "--key", "agent/*/state", "--id", "L1")
            return set_l1, await _cli("faults", "reset", *ctl, "--id", "L1")

        past, too_many, (set_l1, reset_l1) = await asyncio.gather(
            _cli("faults", "set", *ctl, "--spec", json.dumps({"crash": {"agent": 2, "at_tick": 3}})),
            _cli("faults", "set", *ctl, "--loss", "10", "--agents", "99"),
            loss_window())
        code, lines, err = past
        assert code == 1 and len(lines) == 1, (code, lines, err)
        reply = json.loads(lines[0])
        assert not reply["ok"] and reply["error"].startswith("crash.at_tick: tick 3 has passed (the run is at tick ")

        code, lines, err = too_many
        # every process refuses it alike; the faults they list as active may differ by the loss window being set
        # meanwhile, and each such list is a line of its own
        refusals = [json.loads(line) for line in lines]
        assert code == 1 and 1 <= len(refusals) <= 2, (code, lines, err)
        refused = f"scope.agents: agent 99 is not in this run (robot ids 0..{ROBOTS - 1}"
        assert all(not r["ok"] and r["error"].startswith(refused) for r in refusals), refusals

        code, lines, err = set_l1
        assert code == 0 and json.loads(lines[0])["ok"], (code, lines, err)
        code, lines, err = reset_l1
        assert code == 0 and len(lines) == 1, (code, lines, err)
        reply = json.loads(lines[0])
        assert reply["ok"] and "supervisor" not in reply["sources"] and "sim" in reply["sources"]

        while ticks[-1] <= at + 2:  # the crash has happened: it is no longer listed as active
            assert up.poll() is None, "the run ended before the crash tick"
            await asyncio.sleep(0.1)
        assert ticks[-1] < STEPS - 20, "the run is about to end; the test cannot list its faults"
        code, lines, err = await _cli("faults", "list", *ctl)
        assert code == 0 and len(lines) == 1, (code, lines, err)
        reply = json.loads(lines[0])
        assert reply["ok"] and reply["active"] == [] and "supervisor" in reply["sources"], reply

        deadline = time.monotonic() + UP_TIMEOUT
        while up.poll() is None and time.monotonic() < deadline:
            seen |= descendants(up.pid)
            await asyncio.sleep(0.1)
        out, err = up.communicate(timeout=10)
        assert up.returncode == 0, err[-3000:]
        assert "completed" in out and "1 restarts" in out, out
    finally:
        if bus is not None:
            await bus.close()
        if up.poll() is None:
            up.kill()
            up.communicate(timeout=10)
        left = alive(seen | {up.pid})
        kill_all(left)
    assert left == [], f"processes left behind: {left}"

    record = tmp_path / run_id
    events = [json.loads(line) for line in (record / "events.jsonl").read_text().splitlines() if line.strip()]
    crashes = [e for e in events if e["kind"] == "agent.crash"]
    assert [(e["t"], e["details"]["agent"], e["details"]["signal"]) for e in crashes] == [(at, VICTIM, "kill")]
    assert [e["details"]["agent"] for e in events if e["kind"] == "agent.restart"] == [VICTIM]
    assert not [e for e in events if e["kind"] == "agent.crash" and e["details"]["agent"] == 2]
    # the victim acked tick `at` or died in it; it is missing from the next tick on (one tick of slack for a
    # supervisor descheduled on a loaded machine) until it rejoins
    acks = {int(r["t"]): float(r["acks"]) for r in read_metrics(record)}
    # Before it, the fleet is whole — but paced: a robot descheduled past its period on a loaded machine (the three
    # CLI processes above start in these very ticks) misses that tick's ack, and the sim goes on without it
    before = [acks[t] for t in range(at - 20, at)]
    assert min(before) >= ROBOTS - 1 and sum(a == ROBOTS for a in before) >= 15, before
    assert min(acks[at + 1], acks[at + 2]) < ROBOTS, [acks[t] for t in range(at, at + 5)]
    assert load(record).crashes() == [(float(at), str(VICTIM))]  # the report draws this crash and no other
    windows = load(record).fault_windows()
    assert [label for _, _, label in windows] == ["L1"]  # the loss window closed by its reset
