"""The README's five-line subscriber example works as written against a live ``morph-sim up`` (issue 6)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from pathlib import Path

from services.bus.zenoh_bus import free_port
from services.monitor.streams import README_EXAMPLE, STREAM_NAMES

from _procs import wait_for_port

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_readme_shows_the_tested_example():
    text = README.read_text(encoding="utf-8")
    assert "## Metric streams" in text
    assert README_EXAMPLE.strip() in text
    for name in STREAM_NAMES:
        assert f"`{name}`" in text


# ~15 s. It used to fail in 1 of 3 runs: express publishers on our lowlatency sessions starved a default-settings
# client (see tests/test_bus_zenoh.py::test_a_default_settings_client_receives_every_sample_through_the_endpoint).
def test_the_example_prints_metrics_of_a_live_up_run(tmp_path):
    assert len(README_EXAMPLE.strip().splitlines()) == 5
    port = free_port()
    # the example's run id is "demo" under runs/: here the run is "readme" under tmp_path
    code = README_EXAMPLE.replace("7447", str(port)).replace("runs/demo/", f"{tmp_path}/readme/")
    # up's output goes to a file (an unread pipe can fill and stall the supervisor), and the example runs with the
    # environment a user has: no Zenoh settings inherited from this test process.
    up_log = tmp_path / "up.log"
    user_env = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH_")}
    up = subprocess.Popen(
        [sys.executable, "-m", "morph_sim.cli", "up", "--scale", "tiny", "--steps", "100000", "--quiet",
         "--run-id", "readme", "--listen", f"tcp/127.0.0.1:{port}", "--output-dir", str(tmp_path)],
        stdout=up_log.open("wb"), stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        wait_for_port(port, up, deadline, 0.2)  # the README runs the example after `up` has started
        metrics = tmp_path / "readme" / "metrics.csv"
        while not metrics.exists() or metrics.read_text().count("\n") < 5:  # the run is under way
            assert up.poll() is None and time.monotonic() < deadline + 60, "up did not start its run"
            time.sleep(0.2)
        example = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                                 env=user_env)
        up_alive = up.poll() is None
    finally:
        try:
            os.killpg(up.pid, signal.SIGTERM)
            up.wait(timeout=15)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(up.pid, signal.SIGKILL)
            up.wait(timeout=5)
    lines = [ln for ln in example.stdout.splitlines() if ln.startswith("morph/readme/metrics/")]
    assert example.returncode == 0, example.stderr[-2000:]
    assert up_alive, up_log.read_text(errors="replace")[-3000:]
    assert len(lines) > 10, (example.stdout[-2000:], example.stderr[-2000:], up_log.read_text(errors="replace")[-3000:])
    names = {ln.split()[0].rsplit("/", 1)[1] for ln in lines}
    assert {"deliveries_total", "links", "messages_total"} <= names
    assert re.search(r"'t': \d+, 'sim_time': [\d.]+", lines[-1])
