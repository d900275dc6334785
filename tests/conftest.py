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

import contextlib
import fcntl
import os

# as morph_sim/cli.py does for the tool's processes, for the Python processes the tests start themselves (a user's
# client, a CLI run with `python -m`) and these workers: one BLAS thread, not a tenth of a CPU-second of start-up each
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import tempfile
from pathlib import Path

import pytest
from hypothesis import settings as hypothesis_settings

from _procs import FEW_ROBOTS, OPERATOR_CLIENT, LiveRun, Observer, SharedRun

KINDS: dict[str, tuple[str, ...]] = {
    "unit": (
        "test_air", "test_bus_faults", "test_bus_local", "test_dependencies", "test_deploy_manifests", "test_errors",
        "test_faults_vtime", "test_hot_codec", "test_keys", "test_layout", "test_metrics", "test_network_model",
        "test_fleet_brain", "test_plasticity", "test_policy_interface", "test_protocol", "test_readiness", "test_repo_text", "test_rows", "test_supervisor_units",
        "test_figures", "test_layers", "test_policies", "test_render", "test_schemas", "test_tick_step",
    ),
    "fidelity": (
        "test_astar", "test_audit", "test_cta", "test_faults_experiment", "test_heuristic", "test_lab", "test_morph_reference",
        "test_network_study",
        "test_movement", "test_shift_emergent", "test_warehouse_fidelity",
    ),
    "services": (
        "test_bus_zenoh", "test_faults_control", "test_faults_crash", "test_faults_lockstep", "test_faults_restore",
        "test_faults_services", "test_dispatch_outcomes", "test_insider", "test_metric_streams", "test_monitoring", "test_prometheus", "test_record_replay",
        "test_registry", "test_services_local", "test_vocabulary", "test_zenoh_acl",
    ),
    "e2e": (
        "test_agent_claims", "test_api", "test_bench_distributed", "test_cli_messages", "test_compose",
        "test_dashboard_live",
        "test_dockerfile", "test_equivalence", "test_experiment_flags", "test_forkserver", "test_faults_at_tick", "test_faults_cli_live",
        "test_faults_distributed", "test_faults_up", "test_fuzz_services", "test_hostile", "test_inputs",
        "test_network_services", "test_shared_air",
        "test_readme_example", "test_report", "test_secure_defaults", "test_sweep", "test_up", "test_warehouse_cli", "test_watch",
        "test_live_streams", "test_long_run", "test_no_run", "test_operator_commands", "test_policy_packages", "test_outcome_streams", "test_realtime_fleet", "test_restore_lockstep", "test_start_lines", "test_up_exit",
    ),
}
# Hypothesis: a property test that does not fix its own number of examples takes the profile's. The default suite
# draws few examples of each message (tests/test_schemas.py: every message kind has its own test, and a wire
# contract's mistake shows in the first examples of its kind); HYPOTHESIS_PROFILE=thorough draws ten times as many.
hypothesis_settings.register_profile("suite", max_examples=25)
hypothesis_settings.register_profile("thorough", max_examples=250)
hypothesis_settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))

KIND_OF = {name: kind for kind, names in KINDS.items() for name in names}
SLOW_TIMEOUT = 1800  # seconds: an experiment-scale test may take many minutes on 2 cores


@contextlib.contextmanager
def machine_share(*, alone: bool):
    """Between pytest workers (pyproject's ``-n 3``): a test holds the machine shared with the other workers, or
    ``alone`` while it measures wall-clock behaviour (every stream every second, a real-time period) that the other
    workers' CPU would decide instead of the code. A lock file in the workers' common temporary directory."""
    path = _machine_lock()
    if path is None:
        yield
        return
    # flock favours no one: the other workers' tests, each taking the shared lock anew while an older one still holds
    # it, kept a test that wanted the machine alone waiting for 25 s. A turnstile gives it the next turn: the test that
    # wants it alone holds the turnstile until it has the machine, and a test that would share passes through the
    # turnstile first, so none starts once someone waits to be alone.
    turnstile = path.with_suffix(".turnstile")
    with open(path, "a") as lock, open(turnstile, "a") as gate:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _machine_lock() -> Path | None:
    """The lock file the workers of this test session share (None outside pytest-xdist)."""
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if not os.environ.get("PYTEST_XDIST_WORKER") or not run:
        return None
    return Path(tempfile.gettempdir()) / f"morph-sim-tests-{run}.lock"


def pytest_unconfigure(config):
    # a worker that is done with it removes it; one still at work keeps its lock on the open file (and would be
    # alone with a new one)
    path = _machine_lock()
    if path is not None:
        path.unlink(missing_ok=True)
        path.with_suffix(".turnstile").unlink(missing_ok=True)


@pytest.hookimpl(wrapper=True)
def pytest_collection(session):
    """A worker collects (imports every test module: seconds of CPU) holding the machine shared, so that a test
    marked ``alone`` on another worker waits for that too. pytest rewrites the asserts of every test module it
    imports (~3 CPU-s for this suite) and caches the result beside the module only where bytecode may be written:
    where ``PYTHONDONTWRITEBYTECODE`` is set, each worker would rewrite them all again on every run, so the cache is
    written while the modules are collected (the environment is as it was for the tests)."""
    import sys

    dont_write = sys.dont_write_bytecode
    sys.dont_write_bytecode = False
    try:
        with machine_share(alone=False):
            return (yield)
    finally:
        sys.dont_write_bytecode = dont_write


@pytest.fixture(autouse=True)
def _share_the_machine(request):
    """Each test shares the machine with the other workers, or has it alone if marked ``alone``. (The tests of
    ``shared_default_up`` read a run that had the machine alone while it ran, see there.)"""
    if any(f in request.fixturenames for f in ALONE_RUNS):
        yield
        return
    with machine_share(alone=request.node.get_closest_marker("alone") is not None):
        yield


#: The session fixtures that run one `morph-sim up` for tests in several files, and those of them whose run has the
#: machine alone while it runs (its tests then only read it).
SHARED_RUNS = ("shared_default_up", "recorded_run", "shared_live_run")
ALONE_RUNS = ("shared_default_up",)


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # once, in the process that starts the workers (or the only one)
        _compile_the_sources()
    for kind, what in (("unit", "pure code"), ("fidelity", "against the original and the reference code"),
                       ("services", "services wired in this process"), ("e2e", "real morph-sim processes")):
        config.addinivalue_line("markers", f"{kind}: {what} (set by tests/conftest.py from the file name)")
    config.addinivalue_line("markers", "alone: runs while the other pytest worker waits (wall-clock behaviour)")


def _compile_the_sources() -> None:
    """Byte-compile the packages once before any test starts a process. The suite starts hundreds of service
    processes; where ``PYTHONDONTWRITEBYTECODE`` is set (CI images often set it) none of them may write the compiled
    modules, so each would compile every module it imports again: about 0.1 s of CPU per process start."""
    import compileall

    root = Path(__file__).resolve().parent.parent
    for package in ("schemas", "services", "morph_sim"):
        compileall.compile_dir(root / package, quiet=1)


def _kind(item) -> str | None:
    return KIND_OF.get(Path(str(item.fspath)).stem)


def _group(item) -> str:
    """One pytest worker per file (its module fixtures are built once), and the tests of a shared session run on one
    worker whatever their file, so that run is started once (pyproject's `--dist loadgroup`)."""
    return next((f for f in SHARED_RUNS if f in item.fixturenames), Path(str(item.fspath)).stem)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups off the markers (its hook adds them to the ids)
def pytest_collection_modifyitems(config, items):
    unknown = set()
    for item in items:
        kind = _kind(item)
        if kind is None:
            unknown.add(Path(str(item.fspath)).stem)
            continue
        item.add_marker(getattr(pytest.mark, kind))
        item.add_marker(pytest.mark.xdist_group(_group(item)))
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT))
    if unknown:
        raise pytest.UsageError(f"tests/conftest.py: give these test files a kind in KINDS: {sorted(unknown)}")
    # Workers take groups in this order: the runs that have the machine alone first (every worker starts on one, so
    # they follow each other instead of waiting for a long test another worker is in the middle of); then the live
    # groups, which spend much of their time waiting on wall-clock (paced runs, a process starting, a timeout they
    # provoke), spread among the lab's CPU-bound fidelity groups, so that while one worker waits the others compute;
    # then the services wired in this process (spread among the live groups, they made every live run dearer: 321
    # against 267 CPU-s for the suite); and the many short pure tests last, where they fill in while the other
    # workers end their last long group.
    spread: dict[str, list[str]] = {"e2e": [], "fidelity": []}
    for item in items:
        groups = spread.get(_kind(item))
        if groups is not None and _group(item) not in groups:
            groups.append(_group(item))
    place = {g: (i + 0.5 * (k == "fidelity")) / len(gs) for k, gs in spread.items() for i, g in enumerate(gs)}

    def order(item) -> tuple[int, float]:
        if item.get_closest_marker("alone") or any(f in item.fixturenames for f in ALONE_RUNS):
            return (0, 0.0)
        if _kind(item) in spread:
            return (1, place[_group(item)])
        return (2 + ("services", "unit").index(_kind(item)), 0.0)

    items.sort(key=order)


@pytest.fixture
def live_run(tmp_path):
    """Start ``morph-sim up`` runs (:class:`_procs.LiveRun`); whatever is still running at the end is killed."""
    runs: list[LiveRun] = []

    def start(run_id: str, *flags: str, before=None, **options) -> LiveRun:
        """``before(run)``: called once the run's port and record are known, before ``up`` starts (a client that
        must be there from the first tick)."""
        run = LiveRun(tmp_path, run_id, *flags, **options)
        runs.append(run)
        if before is not None:
            before(run)
        return run.start()

    yield start
    for run in runs:
        run.kill()


# -- shared live runs ----------------------------------------------------------------------------------------------------
# A live `morph-sim up` costs ~2 CPU-s before its first tick and ~10 CPU-ms a tick at tiny scale: tests that only read
# a run of the same kind read one. Each shared run starts, with the observers that must see it from the start or join
# it mid-run, when the first test asks for it, and is followed to its end in the background (tests/_procs.py,
# SharedRun); every test then asserts its own property on the outcome.

@pytest.fixture(scope="session")
def shared_live_run(tmp_path_factory):
    """``live_run`` for tests that each act on a live run of the same kind and may end it: the run started with the
    same id, flags and options is handed to the next test that asks while it still runs; once a test has ended it,
    the next one gets a new run. (Tests that only read a whole run use a ``shared_*`` fixture below.)"""
    runs: dict[tuple, LiveRun] = {}

    def get(run_id: str, *flags: str, **options) -> LiveRun:
        key = (run_id, flags, tuple(sorted(options.items())))
        run = runs.get(key)
        if run is None or not run.running():
            if run is not None:
                run.kill()
            run = runs[key] = LiveRun(tmp_path_factory.mktemp(run_id), run_id, *flags, **options).start()
        return run

    yield get
    for run in runs.values():
        run.kill()


# A default-settings Zenoh client (a user's script, with the run's operator credentials as the README's subscriber):
# per one-second window, the metric streams and the ticks seen; the last deliveries_total; when the run finished.
STREAM_SUBSCRIBER = r'''
import json, sys, time, collections, msgpack, zenoh
port, run, duration, credentials = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
''' + OPERATOR_CLIENT + r'''seconds = collections.defaultdict(set)
ticks = collections.defaultdict(int)
last = {}
t0 = time.monotonic()
def on_metric(s):
    sec = int(time.monotonic() - t0)
    name = str(s.key_expr).split("/metrics/", 1)[1]
    seconds[sec].add(name)
    if name == "deliveries_total":
        m = msgpack.unpackb(s.payload.to_bytes())
        if m["t"] >= last.get("t", -1):
            last.update(t=m["t"], value=m["value"])
    elif name == "latency_seconds":
        last["latency_labels"] = msgpack.unpackb(s.payload.to_bytes())["labels"]
def on_tick(s):
    ticks[int(time.monotonic() - t0)] += 1
def on_event(s):
    if b"run.finished" in s.payload.to_bytes():
        last["finished_at"] = int(time.monotonic() - t0)
with zenoh.open(conf) as session:
    session.declare_subscriber(f"morph/{run}/metrics/**", on_metric)
    session.declare_subscriber(f"morph/{run}/sim/tick", on_tick)
    session.declare_subscriber(f"morph/{run}/events/*", on_event)
    end = time.monotonic() + duration
    while time.monotonic() < end and "finished_at" not in last:
        time.sleep(0.1)
    time.sleep(1.0)  # the monitor's last publications follow the sim's end
print(json.dumps({"seconds": {k: sorted(v) for k, v in seconds.items()}, "ticks": ticks, "last": last}))
'''

# A default run long enough to judge its streams second by second and for a watcher to join it once it has rows:
# 1,000 ticks, 3.5-6 s at full speed (165-270 ticks/s here). The late watcher is started with the run and has done its
# imports when it is let go (``Observer(warm_cli=True)``): started cold once the rows were in, it needed about 2.5 s
# before it tried to connect, and a run of 270 ticks/s had ended by then.
SHARED_STEPS = 1000
LATE_JOIN_ROWS = 20  # the late watcher joins once the record has this many rows


@pytest.fixture(scope="session", params=[SHARED_STEPS, pytest.param(2500, marks=pytest.mark.slow)],
                ids=lambda steps: f"{steps}steps")
def shared_default_up(request, tmp_path_factory):
    """A default lockstep ``morph-sim up`` (tiny, morph, progress lines on), listening on a free port, watched from
    its start by a user's Zenoh client (``streams``, :data:`STREAM_SUBSCRIBER`) and by ``morph-sim watch --run``
    (``watch``), and joined mid-run by ``morph-sim watch --duration 3`` without ``--run`` (``late-watch``).
    :class:`_procs.SharedRun`: call ``finished()`` before reading it."""
    import sys

    steps = request.param
    tmp = tmp_path_factory.mktemp("shared-default-up")
    run = LiveRun(tmp, "live", "--steps", str(steps), quiet=False)
    cli = [sys.executable, "-m", "morph_sim.cli"]
    user_env = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH_")}
    shared = SharedRun(run, [
        Observer("streams", [sys.executable, "-c", STREAM_SUBSCRIBER, str(run.port), run.run_id, "240",
                             str(run.record / "credentials" / "operator.json5")], env=user_env),
        Observer("watch", [*cli, "watch", "--run", run.run_id, "--endpoint", run.endpoint, "--duration", "240",
                           "--output-dir", str(run.output_dir)]),
        Observer("late-watch", ["watch", "--endpoint", run.endpoint, "--duration", "3", "--output-dir",
                                str(run.output_dir)], after_rows=LATE_JOIN_ROWS, env={**os.environ, "COLUMNS": "120"},
                 warm_cli=True),
    ], timeout=240)
    with machine_share(alone=True):  # its streams are judged second by second
        shared.start()
        shared.join()
    yield shared
    shared.stop()

# -- shared live runs ---------------------------------------------------------------------------------------------------
# One definition per kind of live run a test needs, built on _procs.LiveRun like `live_run` above; tests that only
# read a finished run of one kind share it (a session fixture) instead of each starting `morph-sim up`.
ENDLESS_PERIOD = 0.1  # seconds per tick: a run that waits for a test to finish with it costs little CPU meanwhile


@pytest.fixture
def endless_run(shared_live_run):
    """``endless_run()``: a secure ``morph-sim up --scale tiny`` of three robots listening on a loopback port that runs
    until someone stops it (``--steps 100000``), paced at :data:`ENDLESS_PERIOD` so it idles between ticks while the
    test works (a lockstep run would take both cores the whole time). One run is handed from test to test
    (``shared_live_run``) until a test ends it; the next then gets a new one."""

    def start() -> LiveRun:
        return shared_live_run("endless", "--steps", "100000", "--mode", "paced", "--period", str(ENDLESS_PERIOD),
                               *FEW_ROBOTS)

    return start


class RecordedRun:
    """A finished ``morph-sim up --bus-record`` (see ``recorded_run``)."""

    def __init__(self, up: LiveRun, code: int, recording, steps: int, seed: int):
        self.up, self.code, self.recording = up, code, recording
        self.steps, self.seed = steps, seed


@pytest.fixture(scope="session")
def recorded_run(tmp_path_factory):
    """A secure ``morph-sim up --bus-record`` (tiny, MORPH with the reference preset, seed 42, 200 ticks, on-board
    states every 10 ticks and W snapshots every 50), run to its end: the record equals the LocalBus run
    (tests/test_equivalence.py) and the bus recording replays to the record (tests/test_record_replay.py)."""
    out = tmp_path_factory.mktemp("recorded")
    steps, seed = 200, 42
    with machine_share(alone=False):  # (a session fixture starts before a test's own share of the machine)
        up = LiveRun(out, "recorded", "--policy", "morph", "--preset", "reference", "--seed", str(seed), "--steps",
                     str(steps), "--state-every", "10", "--snapshot-every", "50", "--bus-record",
                     str(out / "recorded.mbr")).start()
        try:
            code = up.wait(timeout=120)
        except BaseException:
            up.kill()
            raise
    yield RecordedRun(up, code, out / "recorded.mbr", steps, seed)
    up.kill()
