"""Process helpers for tests that start real OS processes (``morph-sim up`` and friends).

Every test that starts a process bounds each wait and kills what it started by pid if something goes wrong; these
are the shared pieces of that bookkeeping.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time

import psutil


def descendants(pid: int) -> set[int]:
    try:
        return {p.pid for p in psutil.Process(pid).children(recursive=True)}
    except psutil.NoSuchProcess:
        return set()


def alive(pids) -> list[int]:
    out = []
    for pid in pids:
        try:
            if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                out.append(pid)
        except psutil.NoSuchProcess:
            pass
    return out


def kill_all(pids) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def kill_tree(proc: subprocess.Popen) -> None:
    """If ``proc`` still runs, kill its descendants and then it, and reap it."""
    if proc.poll() is None:
        for child in psutil.Process(proc.pid).children(recursive=True):
            child.kill()
        proc.kill()
        proc.communicate()


def wait_for_port(port: int, proc: subprocess.Popen, deadline: float, poll: float) -> None:
    """Wait until something accepts TCP connections on 127.0.0.1:``port``; fail if ``proc`` ends or
    ``deadline`` (a ``time.monotonic()`` value) passes first."""
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert proc.poll() is None and time.monotonic() < deadline, f"nothing opened 127.0.0.1:{port}"
            time.sleep(poll)
