"""Secure by default: per-run credentials on disk, the endpoint's access control, the operator's stop, and bad input
refused in one line before a run starts."""

from __future__ import annotations

import itertools
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from schemas import Stop, encode
from schemas.keys import RunKeys
from services.bus.zenoh_bus import endpoint, free_port, zenoh_config
from services.credentials import RunCredentials
from services.protocol.tickorder import TickOrder

# isort: split
import zenoh  # noqa: E402  (after zenoh_bus set the runtime environment)

from _procs import agent_pids, kill_tree

CLI = [sys.executable, "-m", "morph_sim.cli"]
WAIT = 180  # seconds: a bound on each command and wait, for a hang (a loaded machine is slow, not stuck)


def test_tick_order_takes_the_clock_forward_only_and_resyncs_on_two_consecutive_ticks():
    order = TickOrder(steps=1000, max_gap=4)
    with pytest.raises(ValueError, match="outside 0..1000"):
        order.admit(100_000)
    assert order.admit(7)  # the first tick a (re)started receiver sees
    assert not order.admit(7) and not order.admit(3)  # duplicate, stale
    assert order.admit(8) and order.admit(11)  # in order, and a gap of lost ticks
    with pytest.raises(ValueError, match="jumps"):
        order.admit(500)  # a lone far-ahead tick never moves the clock
    assert order.admit(12) and order.last == 12
    with pytest.raises(ValueError):
        order.admit(600)
    assert order.admit(601) and order.last == 601  # two consecutive: the clock really is there


def test_credentials_are_owner_only_and_the_endpoint_enforces_them(tmp_path):
    """The files `up` writes, loaded by a live endpoint: who may publish what, and nobody without a password."""
    run = "acl-run"
    keys = RunKeys(run)
    creds = RunCredentials.create(tmp_path / "credentials", run, n_agents=3, where="tcp/127.0.0.1:1")
    assert oct(creds.directory.stat().st_mode & 0o777) == "0o700"
    assert {oct(p.stat().st_mode & 0o777) for p in creds.directory.iterdir()} == {"0o600"}
    where = endpoint(free_port())
    host = zenoh.open(zenoh_config(listen=where, mode="router", base=zenoh.Config.from_file(str(creds.endpoint))))
    seen: list[tuple[str, bytes]] = []
    cond = threading.Condition()

    def on(sample) -> None:
        with cond:
            seen.append((str(sample.key_expr), sample.payload.to_bytes()))
            cond.notify_all()

    host.declare_subscriber(keys.everything, on)

    def client(path: Path | None):
        base = zenoh.Config.from_file(str(path)) if path else None
        return zenoh.open(zenoh_config(connect=where, mode="client", connect_timeout=3.0, base=base))

    def arrives(session, key: str, payload: bytes, sentinel_key: str) -> bool:
        """Put ``key`` then an allowed sentinel on the same session: once the sentinel arrived, so would have it."""
        mark = f"sentinel-{time.monotonic_ns()}".encode()
        session.put(key, payload)
        deadline = time.monotonic() + 5
        while True:
            session.put(sentinel_key, mark)
            with cond:
                if cond.wait_for(lambda: (sentinel_key, mark) in seen, 0.2):
                    return (key, payload) in seen
            assert time.monotonic() < deadline, f"allowed sentinel on {sentinel_key} never arrived"

    try:
        with pytest.raises(Exception):
            client(None).close()  # no credentials: no session
        agent0, operator, monitor = client(creds.agent(0)), client(creds.operator), client(creds.monitor)
        try:
            own = keys.ack(0)
            assert arrives(agent0, keys.ack(0), b"mine", own)
            assert not arrives(agent0, keys.ack(1), b"forged ack", own)
            assert not arrives(agent0, keys.tick, b"forged tick", own)
            assert not arrives(agent0, keys.event("sim"), b"forged end", own)
            assert not arrives(agent0, keys.stop, encode(Stop(reason="x")), own)
            assert not arrives(agent0, keys.faults, b"forged fault", own)
            assert not arrives(monitor, keys.stop, b"monitor stop", keys.metric("links"))
            assert not arrives(operator, keys.tick, b"operator tick", keys.stop)
            assert not arrives(operator, keys.ack(2), b"operator ack", keys.stop)
            assert arrives(operator, keys.faults, b"operator fault", keys.stop)
            # oversized: dropped by the endpoint on arrival, and the session is still there afterwards
            assert not arrives(agent0, keys.agent_state(0), b"\0" * (64 * 1024), own)
            # a robot's on-board state reaches that robot only: not another robot, not a whole-run subscriber
            sensed: list[tuple[str, str]] = []
            subs = [agent0.declare_subscriber(keys.onboard(0), lambda s: sensed.append(("own", str(s.key_expr)))),
                    agent0.declare_subscriber(keys.onboard(1), lambda s: sensed.append(("other", str(s.key_expr)))),
                    monitor.declare_subscriber(keys.everything, lambda s: sensed.append(("run", str(s.key_expr))))]
            deadline = time.monotonic() + 10
            while ("own", keys.onboard(0)) not in sensed:
                assert time.monotonic() < deadline, "robot 0 never received its own on-board state"
                host.put(keys.onboard(1), b"1")
                host.put(keys.onboard(0), b"0")
                time.sleep(0.1)
            host.put(keys.onboard(1), b"1")
            assert arrives(agent0, keys.ack(0), b"mine again", own)  # a round trip after the last put
            assert [(who, key) for who, key in sensed if "@onboard" in key] == [("own", keys.onboard(0))] * len(
                [1 for who, _ in sensed if who == "own"]), sensed
            for sub in subs:
                sub.undeclare()
        finally:
            for s in (agent0, operator, monitor):
                s.close()
    finally:
        host.close()


SILENT_SOCKETS = 150  # connections that never say a word: each holds one of the endpoint's pending handshakes


def test_the_operator_stops_a_secure_run_and_nobody_else_can(endless_run):
    """...while 150 silent sockets are held open to the endpoint, which also lists faults and restarts a killed
    agent as it would without them."""
    up = endless_run()  # secure (the default), until stopped, paced (tests/conftest.py)
    ep, run_id, record = up.endpoint, up.run_id, up.record
    up.wait_for_rows(3)
    silent = [socket.create_connection(("127.0.0.1", up.port)) for _ in range(SILENT_SOCKETS)]
    try:
        _operate_among_silent_sockets(up, ep, run_id, record)
    finally:
        for s in silent:
            s.close()


def _operate_among_silent_sockets(up, ep, run_id, record) -> None:
    # a killed robot is restarted and its new process opens a session: it rejoins the run
    victim = agent_pids(up.pid, 1)
    assert len(victim) == 1
    os.kill(victim[0], 9)
    up.wait_until(lambda: [p for p in agent_pids(up.pid, 1) if p != victim[0]] != [] and up.rows() > 0, 60,
                  "agent 1 restarted")
    rows = up.rows()
    up.wait_until(lambda: up.rows() >= rows + 5, WAIT, "ticks after the restart")
    # the operator's fault list gets every process's answer, well within its connect timeout
    started = time.monotonic()
    listed = subprocess.run([*CLI, "faults", "list", "--run", run_id, "--endpoint", ep, "--output-dir",
                             str(record.parent)], capture_output=True, text=True, timeout=WAIT)
    assert listed.returncode == 0, listed.stdout + listed.stderr
    assert time.monotonic() - started < 8.0, "the fault list waited for a handshake slot"
    # with a robot's credentials the stop is refused by the endpoint (the command sends it, nobody hears it);
    # without credentials there is no session at all (both at once: neither may end the run)
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_CONFIG"}
    robot_cmd = subprocess.Popen([*CLI, "stop", "--run", run_id, "--endpoint", ep, "--timeout", "2",
                                  "--credentials", str(record / "credentials" / "agent-0.json5")],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # (a session the endpoint refuses is told apart from a slow one only by the connect timeout: 2 s here)
        anon = subprocess.run([*CLI, "stop", "--run", "other-run", "--endpoint", ep, "--connect-timeout", "2"],
                              capture_output=True, text=True, timeout=WAIT, env=env)
        out, err = robot_cmd.communicate(timeout=WAIT)
        robot = subprocess.CompletedProcess(robot_cmd.args, robot_cmd.returncode, out, err)
    finally:
        kill_tree(robot_cmd)
    # the run goes on after both commands are done: more ticks come into its record
    after = up.rows()
    up.wait_until(lambda: up.rows() >= after + 5, WAIT, "ticks after the robot's and the anonymous stop")
    assert robot.returncode in (0, 1) and "Traceback" not in robot.stderr
    assert anon.returncode == 1 and "no credentials" in anon.stderr and "Traceback" not in anon.stderr
    op = subprocess.run([*CLI, "stop", "--run", run_id, "--endpoint", ep, "--output-dir", str(record.parent)],
                        capture_output=True, text=True, timeout=WAIT)
    assert op.returncode == 0, op.stderr
    assert up.wait(timeout=WAIT) == 3, up.stderr()[-3000:]  # stopped from outside
    summary = json.loads((record / "summary.json").read_text())
    assert summary["finished"]["stopped_early"] == "operator stop"


def _up_error(*flags: str, tmp_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, "up", "--quiet", "--steps", "5", "--output-dir", str(tmp_path), *flags],
                          capture_output=True, text=True, timeout=60)


_HERE = itertools.count()


def _up_error_here(*flags: str, tmp_path: Path, capsys) -> tuple[int, str]:
    """The same command line through the CLI's ``main`` in this process (same parser, same error handling): for
    more bad values once a real process has shown the exit status and the one line."""
    from morph_sim.cli import main

    # an id of its own per call: the default id names this process, the same for every call
    code = main(["up", "--quiet", "--steps", "5", "--output-dir", str(tmp_path), "--run-id", f"here-{next(_HERE)}",
                 *flags])
    return code, capsys.readouterr().err


def test_bad_input_is_refused_in_one_line_before_any_process_starts(tmp_path, capsys):
    too_big = _up_error("--agvs", "200", tmp_path=tmp_path)
    assert too_big.returncode == 2
    lines = too_big.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("morph-sim up: error: ")
    assert lines[0].endswith("agvs: 200 AGVs + 3 pickers exceed the 162 highway cells they spawn on (scale tiny)")
    assert not list(tmp_path.iterdir())  # nothing was started or written
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        busy = _up_error("--listen", f"tcp/127.0.0.1:{port}", tmp_path=tmp_path)
    assert busy.returncode == 1
    lines = busy.stderr.strip().splitlines()
    assert len(lines) == 1 and f"port {port}" in lines[0] and "not free" in lines[0], busy.stderr
    assert not list(tmp_path.iterdir())  # the refused run left no directory: its id is free for the fixed command
    schedule = tmp_path / "crash.toml"
    schedule.write_text('[[at]]\ntick = 10\nspec = { id = "k", crash = { agent = 99, at_tick = 10 } }\n')
    code, err = _up_error_here("--fault-schedule", str(schedule), tmp_path=tmp_path, capsys=capsys)
    assert code == 2 and err.strip().splitlines() == [
        f"morph-sim up: error: fault schedule {schedule}: at[0].spec.crash.agent: agent 99 outside 0..7 "
        "(a fleet of 8)"]
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe[[at]]")
    for path, why in ((binary, "not UTF-8"), (tmp_path, "is a directory")):
        code, err = _up_error_here("--fault-schedule", str(path), tmp_path=tmp_path, capsys=capsys)
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert str(path) in err and why in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin.toml", "crash.toml"]  # no run directory left


def test_the_credentials_command_writes_the_files_of_a_by_hand_run(tmp_path):
    out = tmp_path / "creds"
    done = subprocess.run([*CLI, "credentials", "--run-id", "byhand", "--scale", "tiny", "--out", str(out)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["endpoint.json5", "passwords.txt", "operator.json5", "monitor.json5", "air.json5",
                            *(f"agent-{i}.json5" for i in range(8))])
    acl = json.loads((out / "endpoint.json5").read_text())["access_control"]
    assert acl["default_permission"] == "deny" and {"id": "agent-7", "usernames": ["agent-7"]} in acl["subjects"]
    assert "password" not in done.stdout
