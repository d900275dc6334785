"""Long work is never silent: ``run`` prints progress; ``sim``, ``agent`` and ``monitor`` started by hand say where
they are and what they wait for, in one line, as soon as their session is open."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from services.bus.zenoh_bus import endpoint, free_port

from _procs import kill_tree

CLI = [sys.executable, "-m", "morph_sim.cli"]


def _first_line(proc: subprocess.Popen, timeout: float = 60.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if line.startswith("morph-sim ") and ": warning: " not in line:
            return line.strip()
        assert line or proc.poll() is None, "ended without a start line"
    raise AssertionError("no start line")


def test_services_started_by_hand_say_where_they_are_and_what_they_wait_for(tmp_path):
    where = endpoint(free_port())
    common = ["--run-id", "hand", "--scale", "tiny", "--steps", "5", "--output-dir", str(tmp_path)]
    procs: list[subprocess.Popen] = []
    try:
        sim = subprocess.Popen(CLI + ["sim", *common, "--listen", where], stderr=subprocess.PIPE, text=True,
                               stdout=subprocess.DEVNULL)
        procs.append(sim)
        assert _first_line(sim) == (f"morph-sim sim: run hand, listening on {where}; waiting for 8 agents and the "
                                    "monitor (5 steps)")
        monitor = subprocess.Popen(CLI + ["monitor", *common, "--endpoint", where], stderr=subprocess.PIPE,
                                   text=True, stdout=subprocess.DEVNULL)
        procs.append(monitor)
        assert _first_line(monitor) == (f"morph-sim monitor: run hand, connected to {where}; recording to "
                                        f"{tmp_path / 'hand'}")
        agent = subprocess.Popen(CLI + ["agent", "--id", "6", *common, "--endpoint", where], stderr=subprocess.PIPE,
                                 text=True, stdout=subprocess.DEVNULL)
        procs.append(agent)
        assert _first_line(agent) == (f"morph-sim agent: agent 6 (picker) of run hand, connected to {where}; "
                                      "waiting for the sim's ticks")
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGTERM)
        for proc in procs:
            try:
                proc.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                kill_tree(proc)


def test_run_prints_progress_while_it_works(tmp_path, monkeypatch, capsys):
    """The CLI in this process, with a line every 0.02 s instead of every PROGRESS_EVERY (2 s): a short run (100
    ticks, about a second here) prints several, each naming the tick of the run it has reached."""
    import re

    from morph_sim.cli import main
    from morph_sim.commands import run

    monkeypatch.setattr(run, "PROGRESS_EVERY", 0.02)
    assert main(["run", "--scale", "tiny", "--steps", "100", "--run-id", "prog", "--output-dir", str(tmp_path)]) == 0
    out = capsys.readouterr()
    lines = [ln for ln in out.err.splitlines() if ln.startswith("tick ")]
    line = re.compile(r"tick \d+/100  deliveries \d+  \d+ ticks/s")
    assert len(lines) >= 2 and all(line.fullmatch(ln) for ln in lines), out.err
    ticks = [int(ln.split()[1].split("/")[0]) for ln in lines]
    assert ticks == sorted(ticks) and ticks[-1] < 100, ticks
    assert "100 ticks" in out.out
