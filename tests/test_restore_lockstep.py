"""A killed agent restores its state in a default (lockstep, full speed) ``morph-sim up``; one that starts cold says so.

Before: the monitor answered ``state/**`` only after working through its whole inbox (1-3 s under full-speed
lockstep load) and the restore gave up after 1 s, silently: every restart was cold and nothing said so.
"""

from __future__ import annotations

import json
import os
import signal

import psutil
import pytest

from services.supervisor.graph import role_of

# a full-speed lockstep run whose restart races the record: the other pytest worker waits meanwhile
pytestmark = pytest.mark.alone

VICTIM = 3
KILL_AFTER_ROWS = 110  # mid-run at full speed, after agent 1's cold restart at tick 100
# the sim runs up to 200 ticks ahead of the record, and on without the victim while it restarts (~265 ticks/s
# then): the restarted process needs a few seconds to start, restore and rejoin. Killed after row 150 of 900 it
# once had 2.1 s left, and came too late; after row 110 of 1400 it has about 4 s.
STEPS = 1400


def _agent_pid(up_pid: int, agent: int) -> int | None:
    for p in psutil.Process(up_pid).children(recursive=True):
        try:
            cmd = p.cmdline()
        except psutil.Error:
            continue
        if role_of(cmd) == "agent" and "--id" in cmd and cmd[cmd.index("--id") + 1] == str(agent):
            return p.pid
    return None


def test_sigkilled_agent_restores_its_state_in_a_lockstep_run_and_a_cold_one_says_so(tmp_path, live_run):
    schedule = tmp_path / "cold.toml"  # agent 1 is killed at tick 100 and restarted cold, for comparison
    schedule.write_text('[[at]]\ntick = 0\nspec = { id = "cold-1", crash = { agent = 1, at_tick = 100, '
                        'cold_restart = true } }\n')
    up = live_run("lockkill", "--policy", "morph", "--steps", str(STEPS), "--fault-schedule", str(schedule))
    up.wait_for_endpoint()
    up.wait_for_rows(KILL_AFTER_ROWS, timeout=120)
    pid = _agent_pid(up.pid, VICTIM)
    assert pid is not None
    killed_at_row = up.rows()
    os.kill(pid, signal.SIGKILL)  # at full speed, mid-run
    assert up.wait(120) == 0, (up.stdout(), up.stderr()[-3000:])
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
