"""The record is the truth for any run length: a long default ``up`` writes every row, its summary and the sim's
``run.finished``, the monitor's memory stays bounded and its record ends with the run (the lockstep sim stays within
MONITOR_WINDOW ticks of the rows the monitor has written, so there is no backlog to work off afterwards).

Before: at 50,000 steps the monitor fell behind (RSS 138 → 290 MB), was killed 20 s after the sim ended and the
record lost its last 5,587 rows and its summary, while ``up`` said ``completed``."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from services.monitor.recorder import read_metrics

from _procs import alive, descendants, kill_all, sample_rss

MONITOR_RSS_BOUND = 200 * 2**20  # measured: 141 MB after the start, 157 MB at 50,000 ticks (tiny)
END_LAG = 10.0  # seconds between the sim's end of run and the monitor's summary


# The reduced version of this check runs by default in tests/test_live_streams.py (every row, summary, run.finished,
# monitor memory bound, record ending with the run).
@pytest.mark.slow
@pytest.mark.parametrize("steps", [50_000])
def test_a_long_run_keeps_every_row_with_bounded_monitor_memory(tmp_path, steps):
    up = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny", "--steps",
                           str(steps), "--run-id", "long", "--output-dir", str(tmp_path)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: set[int] = set()
    rss: list[int] = []
    deadline = time.monotonic() + 60 + steps / 20  # 20 ticks/s at the very least
    try:
        while up.poll() is None and time.monotonic() < deadline:
            seen |= descendants(up.pid)
            sample_rss(up.pid, "monitor", rss)
            time.sleep(0.5)
        if up.poll() is None:
            up.kill()
        out, err = up.communicate(timeout=30)
    finally:
        kill_all(alive(seen | {up.pid}))
    assert up.returncode == 0, (out, err[-3000:])
    record = tmp_path / "long"
    rows = read_metrics(record)
    assert [int(r["t"]) for r in rows] == list(range(steps))
    summary = json.loads((record / "summary.json").read_text())
    events = [json.loads(ln) for ln in (record / "events.jsonl").read_text().splitlines()]
    finished = [e for e in events if e["kind"] == "run.finished"]
    assert len(finished) == 1 and finished[0]["details"]["steps"] == steps
    assert summary["steps"] == steps and summary["deliveries_total"] == int(rows[-1]["deliveries_total"]) \
        == finished[0]["details"]["deliveries"]
    assert (record / "summary.json").stat().st_mtime - finished[0]["wall_time"] < END_LAG
    assert rss and max(rss) < MONITOR_RSS_BOUND, f"monitor RSS peaked at {max(rss) / 2**20:.0f} MB"
    print(f"monitor RSS {rss[len(rss) // 10] / 2**20:.0f} → {rss[-1] / 2**20:.0f} MB (peak {max(rss) / 2**20:.0f})")
