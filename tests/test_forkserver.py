"""The fork server the local supervisor starts a run's processes from: each forked process is what an exec'd one
was (own pid, session, command line, environment, log, exit status), and nothing outlives the server."""

from __future__ import annotations

import os
import signal
import socket
import sys
import time

import psutil
import pytest

from services.supervisor.forkserver import ForkServer

AGENT = [sys.executable, "-m", "services.agent"]  # what the supervisor asks the server to start
from services.supervisor.graph import CHILD_ENV


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MORPH_")}
    env.update(CHILD_ENV)
    env.update(extra)
    return env


@pytest.fixture
def server(tmp_path):
    srv = ForkServer(_env(), tmp_path / "fork-server.log", ready_timeout=60)
    yield srv
    srv.close()
    try:
        os.kill(srv.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _connecting_agent(port: int) -> list[str]:
    """An agent that tries to reach an endpoint nobody listens on: it stays alive for its connect timeout."""
    return [*AGENT, "--id", "0", "--run-id", "fork-test", "--endpoint", f"tcp/127.0.0.1:{port}"]


def test_a_forked_process_has_its_own_session_command_line_and_exit_status(server, tmp_path):
    log = tmp_path / "agent-0.log"
    argv = _connecting_agent(_closed_port())
    proc = server.spawn(argv, _env(), log)
    try:
        child = psutil.Process(proc.pid)
        assert child.ppid() == server.pid
        assert os.getpgid(proc.pid) == proc.pid and os.getsid(proc.pid) == proc.pid  # its own session and group
        deadline = time.monotonic() + 10
        while child.cmdline()[: len(argv)] != argv:  # written right after the fork
            assert time.monotonic() < deadline, child.cmdline()
            time.sleep(0.01)
        assert all(arg == "" for arg in child.cmdline()[len(argv):])  # the rest of the space is blank
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == -signal.SIGTERM  # the exit status as subprocess reports a signal
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)


def test_a_forked_command_reads_its_own_environment_and_writes_its_own_log(server, tmp_path):
    log = tmp_path / "bad.log"  # the variable is the child's alone: the server's environment has no MORPH_SCALE
    proc = server.spawn([*AGENT, "--id", "0", "--run-id", "fork-test"], _env(MORPH_SCALE="huge"), log)
    assert proc.wait(30) == 2  # a config error: one line and status 2, as when started by exec
    text = log.read_text()
    assert "services.agent: error:" in text and "scale" in text, text
    assert proc.poll() == 2


def test_every_process_is_forked_from_one_single_threaded_interpreter(server, tmp_path):
    assert len(os.listdir(f"/proc/{server.pid}/task")) == 1
    port = _closed_port()
    procs = [server.spawn(_connecting_agent(port), _env(), tmp_path / f"a{i}.log") for i in range(3)]
    try:
        assert {psutil.Process(p.pid).ppid() for p in procs} == {server.pid}
        assert len({p.pid for p in procs}) == 3
    finally:
        for p in procs:
            p.send_signal(signal.SIGKILL)
        assert [p.wait(10) for p in procs] == [-signal.SIGKILL] * 3


def test_not_a_morph_sim_command_is_refused(server, tmp_path):
    with pytest.raises(RuntimeError, match="not a service of a run"):
        server.spawn([sys.executable, "-c", "print(1)"], _env(), tmp_path / "x.log")


def test_the_supervisor_hears_each_end_as_it_happens(tmp_path):
    import threading

    ended = threading.Semaphore(0)
    srv = ForkServer(_env(), tmp_path / "fork-server.log", ready_timeout=60, on_exit=ended.release)
    try:
        port = _closed_port()
        procs = [srv.spawn(_connecting_agent(port), _env(), tmp_path / f"a{i}.log") for i in range(2)]
        procs[0].send_signal(signal.SIGKILL)
        assert ended.acquire(timeout=10)  # told without being asked
        assert procs[0].poll() == -signal.SIGKILL and procs[1].poll() is None
        procs[1].send_signal(signal.SIGKILL)
        assert ended.acquire(timeout=10) and procs[1].poll() == -signal.SIGKILL
    finally:
        srv.close()
    assert ended.acquire(timeout=10)  # and of the server's own end


def test_children_end_with_a_killed_server_and_the_server_ends_with_its_channel(tmp_path):
    srv = ForkServer(_env(), tmp_path / "fork-server.log", ready_timeout=60)
    proc = srv.spawn(_connecting_agent(_closed_port()), _env(), tmp_path / "a.log")
    os.kill(srv.pid, signal.SIGKILL)  # its children get SIGTERM from its death
    assert proc.wait(10) in (-signal.SIGTERM, ForkServer.LOST)
    assert not psutil.pid_exists(proc.pid) or psutil.Process(proc.pid).status() == psutil.STATUS_ZOMBIE
    srv.close()
    with pytest.raises(RuntimeError, match="ended"):
        srv.spawn(_connecting_agent(_closed_port()), _env(), tmp_path / "b.log")

    other = ForkServer(_env(), tmp_path / "fork-server-2.log", ready_timeout=60)
    other.close()  # its channel closed: it ends by itself
    assert other.proc.returncode == 0
