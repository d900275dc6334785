"""The preloaded launcher of ``morph-sim up``: a forked service is its own OS process like an exec'd one (pid,
session, log, command line, exit status), dies with the launcher, and the launcher refuses to fork when preloading
left it with threads. The supervisor's own use of it is exercised by every ``up`` test (test_up.py and others)."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest

from _procs import alive, kill_all
from services.bus.zenoh_bus import free_port
from services.supervisor.graph import CHILD_ENV
from services.supervisor.preload import Launcher, LauncherError

CLI = [sys.executable, "-m", "morph_sim.cli"]


def _env(**extra: str) -> dict[str, str]:
    return {**os.environ, **CHILD_ENV, **extra}


@pytest.fixture
def launcher(tmp_path):
    started = Launcher(tmp_path / "launcher.log", argv_room=4096)
    started.start(_env())
    yield started
    pids = [started.proc.pid, *started.children]
    started.close()
    kill_all(alive(pids))


def _text(path: Path) -> str:
    return path.read_text() if path.exists() else ""  # the forked process creates its log


def _wait(cond, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.05)


def _sim_argv(port: int) -> list[str]:
    # a sim waiting for agents that never come: a forked service that runs until it is told to stop
    return [*CLI, "sim", "--run-id", "preload-test", "--scale", "tiny", "--steps", "5",
            "--listen", f"tcp/127.0.0.1:{port}"]


def test_a_forked_service_is_its_own_process_with_its_own_log_command_line_and_exit_status(launcher, tmp_path):
    log = tmp_path / "sim.log"
    argv = _sim_argv(free_port())
    child = launcher.spawn(argv, _env(), log)
    try:
        assert child.pid not in (os.getpid(), launcher.proc.pid)
        _wait(lambda: "listening on" in _text(log))
        assert os.getsid(child.pid) == child.pid and os.getpgid(child.pid) == child.pid  # own session and group
        cmdline = Path(f"/proc/{child.pid}/cmdline").read_bytes().rstrip(b"\0").split(b"\0")
        assert [a.decode() for a in cmdline] == argv  # ps and pid lookups by command line find it
        assert child.poll() is None
        os.kill(child.pid, signal.SIGTERM)  # the service's own stop: it ends cleanly
        assert child.wait(timeout=30) == 0
    finally:
        kill_all(alive([child.pid]))
    assert "morph-sim sim: run preload-test, listening on" in log.read_text()


def test_exit_codes_and_signals_reach_the_supervisor_unchanged(launcher, tmp_path):
    bad = launcher.spawn([*CLI, "sim", "--run-id", "x", "--steps", "-3"], _env(), tmp_path / "bad.log")
    assert bad.wait(timeout=30) == 2  # a bad value: one line naming the field, exit 2, as with exec
    assert "morph-sim sim: error:" in (tmp_path / "bad.log").read_text()
    assert "steps" in (tmp_path / "bad.log").read_text()
    child = launcher.spawn(_sim_argv(free_port()), _env(), tmp_path / "killed.log")
    _wait(lambda: "listening on" in _text(tmp_path / "killed.log"))
    os.kill(child.pid, signal.SIGKILL)
    assert child.wait(timeout=30) == -signal.SIGKILL
    other = launcher.spawn([sys.executable, "-c", "import sys; print('exec path'); sys.exit(7)"], _env(),
                           tmp_path / "exec.log")  # not the morph-sim CLI: exec'd from the fork
    assert other.wait(timeout=30) == 7
    assert "exec path" in (tmp_path / "exec.log").read_text()
    launcher.close()  # what the supervisor does at the end; the statuses stay readable
    assert (bad.poll(), child.poll(), other.poll()) == (2, -signal.SIGKILL, 7)


def test_forked_services_die_with_the_launcher(launcher, tmp_path):
    child = launcher.spawn(_sim_argv(free_port()), _env(), tmp_path / "sim.log")
    _wait(lambda: "listening on" in _text(tmp_path / "sim.log"))
    os.kill(launcher.proc.pid, signal.SIGKILL)  # as when the supervisor is killed (the launcher then gets SIGKILL)
    _wait(lambda: not alive([child.pid]))
    assert child.wait(timeout=10) is not None


def test_the_launcher_refuses_to_fork_with_threads(tmp_path):
    launcher = Launcher(tmp_path / "launcher.log", argv_room=1024)
    # a BLAS thread pool started while importing numpy: forking then could copy a held lock
    with pytest.raises(LauncherError, match="threads after preloading"):
        launcher.start(_env(OPENBLAS_NUM_THREADS="4", OMP_NUM_THREADS="4"))
    assert launcher.proc.poll() is not None


def test_a_sigkilled_up_leaves_no_process_behind(live_run):
    """SIGKILL to the supervisor alone (no handler runs): the launcher gets SIGKILL, each service SIGTERM."""
    run = live_run("killed-up", "--steps", "100000", "--mode", "paced", "--period", "0.05")
    run.wait_for_rows(3)
    run._note_children()
    commands = set()
    for pid in run.seen:
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        commands.add(" ".join(argv[2:4]).strip())
    # the services were forked by the launcher and show their own command lines
    assert {"services.supervisor.preload", "morph_sim.cli sim", "morph_sim.cli agent", "morph_sim.cli monitor"} <= (
        commands), commands
    os.kill(run.pid, signal.SIGKILL)
    run.proc.wait(timeout=10)
    _wait(lambda: not run.left_behind(), timeout=15)
