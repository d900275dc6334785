"""The README's five-line subscriber example works as written against a live ``morph-sim up``; the README's table of
metric streams is the catalogue's."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from services.metrics import catalogue

README = Path(__file__).resolve().parents[1] / "README.md"
EXAMPLE_SECONDS = 2  # how long the example listens here (the README: 10)


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
    assert catalogue.markdown_table() in section, "README table != services.metrics.catalogue.markdown_table()"
    for name in catalogue.prometheus_names():
        assert f"`{name}" in section, f"Prometheus family {name} missing from the README"


def test_the_readme_example_is_five_lines():
    assert len(readme_example().strip().splitlines()) == 5


# It used to fail in 1 of 3 runs: express publishers on our lowlatency sessions starved a default-settings client
# (see tests/test_bus_zenoh.py::test_a_default_settings_client_receives_every_sample_through_the_endpoint).
def test_the_example_prints_metrics_of_a_live_up_run(endless_run):
    # the example runs with the environment a user has: no Zenoh settings inherited from this test process
    user_env = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH_")}
    up = endless_run()  # until stopped, paced (tests/conftest.py)
    # the example's run id is "demo" under runs/: here the test run's id under its directory; it listens for
    # EXAMPLE_SECONDS instead of 10 (at the run's pace that is dozens of ticks)
    code = readme_example().replace("7447", str(up.port)).replace("runs/demo/", f"{up.record}/")
    assert "time.sleep(10)" in code
    code = code.replace("time.sleep(10)", f"time.sleep({EXAMPLE_SECONDS})")
    up.wait_for_endpoint()  # the README runs the example after `up` has started
    up.wait_for_rows(5)  # the run is under way
    example = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=user_env)
    up_alive = up.running()
    lines = [ln for ln in example.stdout.splitlines() if ln.startswith(f"morph/{up.run_id}/metrics/")]
    assert example.returncode == 0, example.stderr[-2000:]
    assert up_alive, up.stderr()[-3000:]
    assert len(lines) > 10, (example.stdout[-2000:], example.stderr[-2000:], up.stderr()[-3000:])
    names = {ln.split()[0].rsplit("/", 1)[1] for ln in lines}
    assert {"deliveries_total", "links", "messages_total"} <= names
    assert re.search(r"'t': \d+, 'sim_time': [\d.]+", lines[-1])
