"""The run's processes as the supervisor keeps them: starting one, its log, its signals, what its end means, and
ending them all.

Process hygiene, because a distributed run must never leave processes behind:

* every child gets its own process group (``start_new_session``), so a terminal Ctrl-C reaches only the supervisor,
  which then ends the children in order; and the kernel sends each child SIGTERM if the supervisor dies
  (``PR_SET_PDEATHSIG``), so even a SIGKILLed supervisor leaves no orphans;
* shutdown is SIGTERM to every group, then SIGKILL by pid to whatever is left after ``TERM_GRACE`` seconds, and a
  final reap: all children are gone within ``SHUTDOWN_BOUND`` (5 s);
* each child's stdout and stderr go to ``<record>/logs/<name>.log``; a child that fails before the run is ready
  makes ``up`` exit non-zero with the tail of that log.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

from services.supervisor.errors import StartError
from services.supervisor.forkserver import ForkedProcess, ForkServer
from services.supervisor.graph import CHILD_ENV, ProcessSpec, child_environment
from services.supervisor.liveline import SHOW_EVERY
from services.supervisor.parent import signal_on_parent_death

TERM_GRACE = 3.0  # seconds between SIGTERM and SIGKILL
SHUTDOWN_BOUND = 5.0
# A crash loop is a failure, not something to retry forever: at most MAX_RESTARTS unplanned restarts of one child
# within RESTART_WINDOW wall seconds. Kills the supervisor carries out itself (crash faults) do not count, so
# "kill agent k every 100 ticks" runs for any number of steps.
MAX_RESTARTS = 5
RESTART_WINDOW = 60.0
RECORD_FAILED = 74  # a monitor's exit status when the record cannot be written (services/monitor/command.py)


def die_with_parent() -> None:  # runs in the child between fork and exec
    signal_on_parent_death(signal.SIGTERM)


@dataclass
class Child:
    spec: ProcessSpec
    log_path: Path
    proc: subprocess.Popen | ForkedProcess | None = None
    restarts: int = 0
    exit_codes: list[int] = field(default_factory=list)
    pids: list[int] = field(default_factory=list)  # every pid this child ever had (tests check they are gone)
    reaped: set[int] = field(default_factory=set)  # pids whose exit was handled
    failures: list[float] = field(default_factory=list)  # monotonic times of unplanned restarts (crash-loop budget)
    planned: dict[int, bool] = field(default_factory=dict)  # pid killed by a crash fault -> restart it cold?
    # ZENOH_CONFIG naming this process's credentials file (secure runs): a file name, never the secret itself
    extra_env: dict[str, str] = field(default_factory=dict)

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def restart_allowed(self, now: float) -> bool:
        self.failures = [x for x in self.failures if now - x < RESTART_WINDOW]
        return len(self.failures) < MAX_RESTARTS

    def start(self, extra: tuple[str, ...] = (), server: ForkServer | None = None,
              on_exit: Callable[[], None] | None = None) -> None:
        """``extra`` flags go after the spec's (argparse: the last one wins), e.g. ``--cold-restart``. With
        ``server`` the process is forked from the run's pre-imported interpreter (whose reports say when it ends),
        else it is a fresh one (exec) and ``on_exit()`` is called from a waiting thread when it ends."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        argv = self.spec.command() + list(extra)
        env = {**self.spec.environment(), **self.extra_env}
        with open(self.log_path, "ab") as out:
            out.write(f"--- start {' '.join(self.spec.argv + extra)} at {time.time():.3f}"
                      f"{' (fork)' if server is not None else ''}\n".encode())
            out.flush()
            if server is None:
                self.proc = subprocess.Popen(
                    argv, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                    start_new_session=True, preexec_fn=die_with_parent, close_fds=True)
        if server is not None:
            try:
                self.proc = server.spawn(argv, env, self.log_path)
            except RuntimeError as exc:
                raise StartError(f"{self.spec.name}: {exc}") from None
        elif on_exit is not None:
            import threading

            proc = self.proc
            threading.Thread(target=lambda: (proc.wait(), on_exit()), name=f"wait-{self.spec.name}",
                             daemon=True).start()
        self.pids.append(self.proc.pid)

    def log_tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return "\n".join(text[-lines:])

    def signal_group(self, sig: int) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        try:
            os.killpg(self.proc.pid, sig)  # its own group: pgid == pid
        except ProcessLookupError:
            pass
        except PermissionError:
            self.proc.send_signal(sig)


def last_error(child: Child) -> str:
    """The child's last error line (``morph-sim <cmd>: error: …``), else the last line of its log."""
    lines = [ln for ln in child.log_tail(40).splitlines() if ln.strip() and not ln.startswith("--- start")]
    errors = [f"{child.spec.role}: " + ln.split(": error: ", 1)[1] for ln in lines if ": error: " in ln]
    return (errors or lines or [f"{child.spec.name} left no log"])[-1].strip()


class Exit(Enum):
    """What the end of a process other than the sim means for the run."""

    FAILED_BEFORE_START = "failed before the run started"  # the run cannot start: up fails with its log
    RECORD_FAILED = "the monitor cannot write the record"  # the run is stopped: its record cannot be the truth
    RESTART = "restart"  # an agent or the monitor failed (or a crash fault killed it): start it again
    MONITOR_FAILED = "the monitor failed"  # beyond its restart budget: the record is lost
    AIR_FAILED = "the air failed"  # the radio's queues so far are gone with it: the run cannot go on as it was
    DONE = "done"  # it finished for good (after the run's stop), or an agent's crash loop ran out of restarts


def exit_verdict(role: str, restart: str, code: int, *, running: bool, planned: bool, budget_left: bool) -> Exit:
    """The meaning of a child's exit with status ``code``. ``running``: the run has ticked; ``planned``: a crash
    fault of the supervisor's own killed it (it is restarted whatever the budget); ``budget_left``: its unplanned
    restarts are within the crash-loop budget (:meth:`Child.restart_allowed`)."""
    if not running and code != 0:
        return Exit.FAILED_BEFORE_START
    if role == "monitor" and code == RECORD_FAILED:
        return Exit.RECORD_FAILED
    if restart == "on-failure" and code != 0 and (planned or budget_left):
        return Exit.RESTART
    if role == "monitor" and code != 0:
        return Exit.MONITOR_FAILED
    if role == "air" and code != 0:  # (it leaves with 0 only once the run has finished)
        return Exit.AIR_FAILED
    return Exit.DONE


def start_fork_server(record_dir: Path, ready_timeout: float, on_exit: Callable[[], None], *,
                      fork: bool = False, wait: bool = True) -> ForkServer:
    """The run's processes start by fork from one interpreter that imported them once (fresh interpreters spend
    ~0.5 CPU-s each on imports). Its environment holds BLAS to one thread, as every child's does, so it stays
    single-threaded and safe to fork. ``fork``/``wait``: see :class:`ForkServer` (then :func:`fork_server_ready`)."""
    log = record_dir / "logs" / "fork-server.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    try:
        return ForkServer(child_environment(CHILD_ENV), log, ready_timeout=ready_timeout, preexec_fn=die_with_parent,
                          on_exit=on_exit, fork=fork, wait=wait)
    except RuntimeError as exc:
        raise StartError(f"{exc}:\n{_log_tail(log)}") from None


def fork_server_ready(server: ForkServer, ready_timeout: float) -> None:
    """Wait for a server started with ``wait=False``; StartError with its log's end if it cannot start."""
    try:
        server.wait_ready(ready_timeout)
    except RuntimeError as exc:
        raise StartError(f"{exc}:\n{_log_tail(Path(server.log_path))}") from None


def _log_tail(log: Path) -> str:
    return "\n".join(log.read_text(errors="replace").splitlines()[-15:]) if log.exists() else ""


async def end_children(children: list[Child], nap: Callable[[float], Awaitable[None]],
                       note: Callable[[str, str], None]) -> None:
    """Every child gone within SHUTDOWN_BOUND: a moment to exit on its own, SIGTERM, then SIGKILL. ``nap(s)``
    waits until a child ends or ``s`` seconds pass; ``note(kind, what)`` keeps the supervisor's account."""

    async def wait_exit(timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(c.alive() for c in children):
            await nap(min(SHOW_EVERY, deadline - time.monotonic()))

    await wait_exit(1.0)
    for child in children:
        child.signal_group(signal.SIGTERM)
    await wait_exit(TERM_GRACE)
    for child in children:
        if child.alive():
            note("kill", f"{child.spec.name} pid {child.pid} ignored SIGTERM")
            child.signal_group(signal.SIGKILL)
    for child in children:
        if child.proc is not None:
            try:
                child.proc.wait(timeout=0.5)
            except subprocess.TimeoutExpired:
                pass
