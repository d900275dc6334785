"""A killed agent restores its state in a default (lockstep, full speed) ``morph-sim up``; one that starts cold says so.

Before: the monitor answered ``state/**`` only after working through its whole inbox (1-3 s under full-speed
lockstep load) and the restore gave up after 1 s, silently: every restart was cold and nothing said so.
"""

from __future__ import annotations

import json
import os
import signal
import sys

import psutil
import pytest

from _procs import agent_pids, run_processes

# the monitor must answer the restarted agent within its RESTORE_TIMEOUT (services/agent/restore.py) under the run's
# own full-speed load, not under the other pytest workers' too: they wait meanwhile
pytestmark = pytest.mark.alone

VICTIM = 3
KILL_AFTER_ROWS = 110  # mid-run at full speed, after agent 1's cold restart at tick 100
# The run goes on at full speed (~265 ticks/s, the sim up to 200 ticks ahead of the record) while the restarted
# process starts, restores and rejoins: a few seconds, more on a loaded machine. A run of fixed length raced that
# (killed after row 150 of 900, one restore came too late); this one has steps to spare and is stopped (SIGTERM)
# once the record holds both restarts' events, however long they took.
STEPS = 100_000
EVENTS_TIMEOUT = 120  # seconds from the kill to both events in the record


def _thread_kinds(pid: int) -> set[str]:
    """The names of a process's threads without their numbers (Zenoh's runtime threads are "app-3", "tx-0" …)."""
    kinds = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/comm") as f:
                kinds.add(f.read().strip().rsplit("-", 1)[0])
        except OSError:
            pass
    return kinds


def _events_so_far(up) -> list[dict]:
    """The events in the record of a run still going (the monitor may be in the middle of writing a line)."""
    path = up.record / "events.jsonl"
    events = []
    for line in path.read_text().splitlines() if path.exists() else ():
        try:
            events.append(json.loads(line))
        except ValueError:
            pass
    return events


def test_sigkilled_agent_restores_its_state_in_a_lockstep_run_and_a_cold_one_says_so(tmp_path, live_run):
    schedule = tmp_path / "cold.toml"  # agent 1 is killed at tick 100 and restarted cold, for comparison
    schedule.write_text('[[at]]\ntick = 0\nspec = { id = "cold-1", crash = { agent = 1, at_tick = 100, '
                        'cold_restart = true } }\n')
    up = live_run("lockkill", "--policy", "morph", "--steps", str(STEPS), "--fault-schedule", str(schedule))
    up.wait_for_endpoint()
    up.wait_for_rows(KILL_AFTER_ROWS, timeout=120)
    pids = agent_pids(up.pid, VICTIM)
    assert pids
    pid = pids[0]
    # the run's processes come from a fork server forked from `up` itself (after it made room for their command
    # lines, which does not show in its own)
    supervisor = psutil.Process(up.pid).cmdline()
    assert supervisor[: len(up.argv)] == up.argv and not any(supervisor[len(up.argv):]), supervisor
    # the sim hosts the endpoint and routes the agents' messages: its sends have a Zenoh runtime thread of their
    # own (services/bus/zenoh_bus.py, RUNTIME_ENDPOINT); an agent's session runs on one thread
    ((_, sim),) = run_processes(up.pid, "sim")
    assert "tx" in _thread_kinds(sim.pid) and "tx" not in _thread_kinds(pid), (_thread_kinds(sim.pid), _thread_kinds(pid))
    server = psutil.Process(pid).parent()
    # (an exec'd server's command line ends with its own padding)
    assert server.cmdline()[:3] == [sys.executable, "-m", "services.supervisor.forkserver"], server.cmdline()
    assert not any(server.cmdline()[3:]), server.cmdline()
    assert server.ppid() == up.pid
    killed_at_row = up.rows()
    os.kill(pid, signal.SIGKILL)  # at full speed, mid-run

    def restarted() -> bool:  # both restarts in the record (or the victim's cold start: the assertions below fail)
        kinds = {(e["kind"], e["source"]) for e in _events_so_far(up)}
        both = {("agent.cold_start", 1), ("agent.restored", VICTIM)} <= kinds
        return both or ("agent.cold_start", VICTIM) in kinds

    up.wait_until(restarted, EVENTS_TIMEOUT, f"restart events of agents 1 and {VICTIM} in the record", poll=0.2)
    # what is judged here is the restore; that a run with restarts completes is tests/test_faults_up.py's
    up.signal(signal.SIGTERM)
    assert up.wait(60) == 143, (up.stdout(), up.stderr()[-3000:])  # interrupted, as a user's Ctrl-C or SIGTERM
    out = up.stdout()
    assert "2 restarts" in out, out
    events = [json.loads(ln) for ln in (up.record / "events.jsonl").read_text().splitlines()]
    restored = [e for e in events if e["kind"] == "agent.restored" and e["source"] == VICTIM]
    assert len(restored) == 1, [e for e in events if e["kind"].startswith("agent.")]
    # the state of a tick shortly before the kill (states every 10 ticks; the monitor is at most 200 ticks behind)
    assert killed_at_row - 10 <= restored[0]["t"] <= killed_at_row + 250, (killed_at_row, restored[0]["t"])
    assert len(restored[0]["details"]["w_row"]) == 8
    cold = [e for e in events if e["kind"] == "agent.cold_start"]
    assert [(e["source"], e["details"]["reason"]) for e in cold] == [(1, "cold restart requested")], cold
    assert not [e for e in events if e["kind"] == "agent.restored" and e["source"] == 1]
    assert up.left_behind() == []
