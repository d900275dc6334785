"""Test kinds and the shared live run.

Every test file has one kind (``pytest -m unit``, ``-m "not e2e"`` …), given here by file name so a new file must be
placed deliberately (collection fails for a file that is not listed):

* ``unit`` — pure code: models, codecs, dynamics, plasticity, metrics, one bus or fault layer in isolation;
* ``fidelity`` — our results against the original TA-RWARE and the reference MORPH code (digests, per-seed numbers)
  and the lab's experiments;
* ``services`` — services wired together in this process (LocalBus, or real Zenoh sessions on loopback);
* ``e2e`` — real ``morph-sim`` processes as a user starts them (``up``, the CLI, the compose graph, the wheel).

``slow`` (experiment-scale, excluded by default) is orthogonal and marked on the tests themselves. Every test has a
default timeout (pyproject.toml; slow tests get :data:`SLOW_TIMEOUT`), so a hang fails with a traceback.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from _procs import LiveRun

KINDS: dict[str, tuple[str, ...]] = {
    "unit": (
        "test_bus_faults", "test_bus_local", "test_dependencies", "test_deploy_manifests", "test_errors",
        "test_faults_vtime", "test_hot_codec", "test_keys", "test_layout", "test_metrics", "test_network_model",
        "test_plasticity", "test_protocol", "test_repo_text",
        "test_figures", "test_policies", "test_render", "test_schemas",
    ),
    "fidelity": (
        "test_astar", "test_audit", "test_cta", "test_faults_experiment", "test_heuristic", "test_lab", "test_morph_reference",
        "test_network_study",
        "test_movement", "test_shift_emergent", "test_warehouse_fidelity",
    ),
    "services": (
        "test_bus_zenoh", "test_faults_control", "test_faults_crash", "test_faults_lockstep", "test_faults_restore",
        "test_faults_services", "test_dispatch_outcomes", "test_metric_streams", "test_monitoring", "test_prometheus", "test_record_replay",
        "test_registry", "test_services_local", "test_zenoh_acl",
    ),
    "e2e": (
        "test_agent_claims", "test_api", "test_bench_distributed", "test_cli_messages", "test_compose",
        "test_dockerfile", "test_equivalence", "test_experiment_flags", "test_faults_at_tick", "test_faults_cli_live",
        "test_faults_distributed", "test_faults_up", "test_fuzz_services", "test_hostile", "test_network_services",
        "test_readme_example", "test_report", "test_secure_defaults", "test_sweep", "test_up", "test_warehouse_cli", "test_watch",
        "test_live_streams", "test_long_run", "test_no_run", "test_outcome_streams", "test_realtime_fleet", "test_restore_lockstep", "test_start_lines", "test_up_exit",
    ),
}
KIND_OF = {name: kind for kind, names in KINDS.items() for name in names}
SLOW_TIMEOUT = 1800  # seconds: an experiment-scale test may take many minutes on 2 cores


def pytest_configure(config):
    for kind, what in (("unit", "pure code"), ("fidelity", "against the original and the reference code"),
                       ("services", "services wired in this process"), ("e2e", "real morph-sim processes")):
        config.addinivalue_line("markers", f"{kind}: {what} (set by tests/conftest.py from the file name)")


def pytest_collection_modifyitems(config, items):
    unknown = set()
    for item in items:
        name = Path(str(item.fspath)).stem
        kind = KIND_OF.get(name)
        if kind is None:
            unknown.add(name)
            continue
        item.add_marker(getattr(pytest.mark, kind))
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT))
    if unknown:
        raise pytest.UsageError(f"tests/conftest.py: give these test files a kind in KINDS: {sorted(unknown)}")


@pytest.fixture
def live_run(tmp_path):
    """Start ``morph-sim up`` runs (:class:`_procs.LiveRun`); whatever is still running at the end is killed."""
    runs: list[LiveRun] = []

    def start(run_id: str, *flags: str, **options) -> LiveRun:
        run = LiveRun(tmp_path, run_id, *flags, **options)
        runs.append(run)
        return run.start()

    yield start
    for run in runs:
        run.kill()


# -- shared live runs ---------------------------------------------------------------------------------------------------
# One definition per kind of live run a test needs, built on _procs.LiveRun like `live_run` above; tests that only
# read a finished run of one kind share it (a session fixture) instead of each starting `morph-sim up`.
ENDLESS_PERIOD = 0.1  # seconds per tick: a run that waits for a test to finish with it costs little CPU meanwhile


@pytest.fixture
def endless_run(live_run):
    """``endless_run()``: a secure ``morph-sim up --scale tiny`` listening on a loopback port that runs until someone
    stops it (``--steps 100000``), paced at :data:`ENDLESS_PERIOD` so it idles between ticks while the test works (a
    lockstep run would take both cores the whole time). Killed at the end of the test if it still runs."""

    def start() -> LiveRun:
        return live_run("endless", "--steps", "100000", "--mode", "paced", "--period", str(ENDLESS_PERIOD))

    return start


class RecordedRun:
    """A finished ``morph-sim up`` and the ``morph-sim record`` process that followed it (see ``recorded_run``)."""

    def __init__(self, up: LiveRun, code: int, record, recording, steps: int, seed: int):
        self.up, self.code, self.record, self.recording = up, code, record, recording
        self.steps, self.seed = steps, seed


@pytest.fixture(scope="session")
def recorded_run(tmp_path_factory):
    """A secure ``morph-sim up`` (tiny, MORPH with the reference preset, seed 42, 200 ticks, on-board states every
    10 ticks and W snapshots every 50) that ``morph-sim record`` followed from its start over its endpoint, both
    run to their end: the record equals the LocalBus run (tests/test_equivalence.py) and replays to the record
    (tests/test_record_replay.py)."""
    import subprocess
    import sys

    out = tmp_path_factory.mktemp("recorded")
    steps, seed = 200, 42
    up = LiveRun(out, "recorded", "--policy", "morph", "--preset", "reference", "--seed", str(seed), "--steps",
                 str(steps), "--state-every", "10", "--snapshot-every", "50").start()
    try:
        up.wait_for_endpoint()
        # no run flags: the recorder learns the run's configuration from the run; the operator's credentials are
        # found in the run directory (--output-dir) that `up` wrote them to
        record = subprocess.run([sys.executable, "-m", "morph_sim.cli", "record", "--run-id", up.run_id,
                                 "--endpoint", up.endpoint, "--out", str(out / "recorded.mbr"), "--timeout", "120",
                                 "--output-dir", str(out)], capture_output=True, text=True, timeout=180)
        code = up.wait(timeout=120)
    except BaseException:
        up.kill()
        raise
    yield RecordedRun(up, code, record, out / "recorded.mbr", steps, seed)
    up.kill()
