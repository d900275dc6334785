"""The README's five-line subscriber example works as written against a live ``morph-sim up``; the README's table of
metric streams is the catalogue's."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

from pathlib import Path

from services.bus.zenoh_bus import free_port
from services.monitor import catalogue

from _procs import wait_for_port

README = Path(__file__).resolve().parents[1] / "README.md"


def _metrics_section() -> str:
    text = README.read_text(encoding="utf-8")
    start = text.index("## Metric streams")
    return text[start:text.index("\n## ", start + 1)]


def readme_example() -> str:
    """The README's subscriber example: the one python block of its metric streams section."""
    blocks = re.findall(r"```python\n(.*?)```", _metrics_section(), re.S)
    assert len(blocks) == 1, "the metric streams section shows one python example"
    return blocks[0]


def test_the_readme_table_of_streams_is_the_catalogue():
    section = _metrics_section()
    assert catalogue.markdown_table() in section, "README table != services.monitor.catalogue.markdown_table()"
    for name in catalogue.prometheus_names():
        assert f"`{name}" in section, f"Prometheus family {name} missing from the README"


def test_the_readme_example_is_five_lines():
    assert len(readme_example().strip().splitlines()) == 5


# ~15 s. It used to fail in 1 of 3 runs: express publishers on our lowlatency sessions starved a default-settings
# client (see tests/test_bus_zenoh.py::test_a_default_settings_client_receives_every_sample_through_the_endpoint).
def test_the_example_prints_metrics_of_a_live_up_run(tmp_path):
    port = free_port()
    code = readme_example().replace("7447", str(port))
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
