"""A killed agent restores its state in a default (lockstep, full speed) ``morph-sim up``; one that starts cold says so.

Before: the monitor answered ``state/**`` only after working through its whole inbox (1-3 s under full-speed
lockstep load) and the restore gave up after 1 s, silently: every restart was cold and nothing said so.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import psutil

from services.bus.zenoh_bus import endpoint, free_port

from _procs import alive, descendants, kill_all, wait_for_port

VICTIM = 3
STEPS = 2400  # the restarted process needs a few seconds to start, restore and rejoin


def _agent_pid(up_pid: int, agent: int) -> int | None:
    for p in psutil.Process(up_pid).children(recursive=True):
        try:
            cmd = p.cmdline()
        except psutil.Error:
            continue
        if "agent" in cmd and "--id" in cmd and cmd[cmd.index("--id") + 1] == str(agent):
            return p.pid
    return None


def test_sigkilled_agent_restores_its_state_in_a_lockstep_run_and_a_cold_one_says_so(tmp_path):
    schedule = tmp_path / "cold.toml"  # agent 1 is killed at tick 100 and restarted cold, for comparison
    schedule.write_text('[[at]]\ntick = 0\nspec = { id = "cold-1", crash = { agent = 1, at_tick = 100, '
                        'cold_restart = true } }\n')
    port = free_port()
    run = "lockkill"
    up = subprocess.Popen(
        [sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny", "--policy", "morph",
         "--steps", str(STEPS), "--run-id", run, "--output-dir", str(tmp_path), "--listen", endpoint(port),
         "--fault-schedule", str(schedule)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    seen: set[int] = set()
    killed_at_row = None
    try:
        wait_for_port(port, up, time.monotonic() + 60, 0.05)
        metrics = tmp_path / run / "metrics.csv"
        deadline = time.monotonic() + 120
        while not metrics.exists() or metrics.read_text().count("\n") < 300:
            assert up.poll() is None and time.monotonic() < deadline, up.communicate(timeout=10)
            seen |= descendants(up.pid)
            time.sleep(0.05)
        pid = _agent_pid(up.pid, VICTIM)
        assert pid is not None
        killed_at_row = metrics.read_text().count("\n") - 1
        os.kill(pid, signal.SIGKILL)  # at full speed, mid-run
        while up.poll() is None and time.monotonic() < deadline:
            seen |= descendants(up.pid)
            time.sleep(0.1)
        out, err = up.communicate(timeout=30)
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.communicate(timeout=10)
        kill_all(alive(seen))
    assert up.returncode == 0, (out, err[-3000:])
    assert "2 restarts" in out, out
    events = [json.loads(ln) for ln in (tmp_path / run / "events.jsonl").read_text().splitlines()]
    restored = [e for e in events if e["kind"] == "agent.restored" and e["source"] == VICTIM]
    assert len(restored) == 1, [e for e in events if e["kind"].startswith("agent.")]
    # the state of a tick shortly before the kill (states every 10 ticks; the monitor is at most 200 ticks behind)
    assert killed_at_row - 10 <= restored[0]["t"] <= killed_at_row + 250, (killed_at_row, restored[0]["t"])
    assert len(restored[0]["details"]["w_row"]) == 8
    cold = [e for e in events if e["kind"] == "agent.cold_start"]
    assert [(e["source"], e["details"]["reason"]) for e in cold] == [(1, "cold restart requested")], cold
    assert not [e for e in events if e["kind"] == "agent.restored" and e["source"] == 1]
