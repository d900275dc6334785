"""Process helpers for tests that start real OS processes (``morph-sim up`` and friends).

Every test that starts a process bounds each wait and kills what it started by pid if something goes wrong; these
are the shared pieces of that bookkeeping.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import psutil

from services.supervisor.graph import role_of

#: ``up`` flags for a test whose property does not depend on the fleet (security, exit status, telemetry): three
#: robots instead of the tiny scale's eight, since every agent process costs ~0.3 CPU-s to start and its share of
#: every tick. The tests of the default run, of equivalence with the lab and of fleet-wide behaviour keep theirs.
FEW_ROBOTS = ("--agvs", "2", "--pickers", "1")


def terminal_signals() -> None:
    """``preexec_fn`` of a process a test interrupts with SIGINT: SIGINT at its default, as a user's terminal starts
    a command. pytest-xdist workers ignore SIGINT, an ignored signal stays ignored across exec, and Python then
    never raises KeyboardInterrupt: the command would run on as if never interrupted."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def descendants(pid: int) -> set[int]:
    try:
        return {p.pid for p in psutil.Process(pid).children(recursive=True)}
    except psutil.NoSuchProcess:
        return set()


def run_processes(root: int, *roles: str) -> list[tuple[str, psutil.Process]]:
    """(role, process) of the descendants of ``root`` (a run's ``up``) whose role is one of ``roles``: a process
    that ends between the listing and the reading of its command line (a run's processes start and stop around
    the test) is left out, not an error."""
    out = []
    for pid in descendants(root):
        try:
            process = psutil.Process(pid)
            role = role_of(process.cmdline())
        except psutil.Error:
            continue
        if role in roles:
            out.append((role, process))
    return out


def agent_pids(root: int, agent: int) -> list[int]:
    """The pids of robot ``agent``'s agent processes among the descendants of ``root`` (a run's ``up``)."""
    out = []
    for _, process in run_processes(root, "agent"):
        try:
            cmd = process.cmdline()
        except psutil.Error:  # ended since it was listed
            continue
        if "--id" in cmd and cmd[cmd.index("--id") + 1] == str(agent):
            out.append(process.pid)
    return out


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


class LiveRun:
    """``morph-sim up`` as a user starts it, for a test: its own session (so its whole process group can be killed
    by pid), listening on a free loopback port, stdout and stderr in files (an unread pipe can fill and stall the
    supervisor), every wait bounded. Use it through the ``live_run`` fixture (tests/conftest.py), which kills what
    is still running at the end of the test.
    """

    def __init__(self, tmp_path, run_id: str, *flags: str, scale: str = "tiny", listen: bool = True,
                 output_dir=None, env: dict[str, str] | None = None, quiet: bool = True):
        from pathlib import Path

        from services.bus.zenoh_bus import free_port

        self.run_id = run_id
        self.output_dir = Path(output_dir) if output_dir is not None else Path(tmp_path)
        self.record = self.output_dir / run_id
        self.port = free_port() if listen else None
        self.endpoint = f"tcp/127.0.0.1:{self.port}" if listen else None
        self.argv = [sys.executable, "-m", "morph_sim.cli", "up", *(["--quiet"] if quiet else []), "--scale", scale,
                     "--run-id", run_id, "--output-dir", str(self.output_dir), *flags,
                     *(["--listen", self.endpoint] if listen else [])]
        self.env = env
        self._logs = Path(tmp_path) / f"up-{run_id}"
        self.proc: subprocess.Popen | None = None
        self.seen: set[int] = set()  # every descendant pid observed while waiting

    # -- lifecycle -----------------------------------------------------------------------------------------------------
    def start(self) -> LiveRun:
        self._logs.mkdir(parents=True, exist_ok=True)
        with open(self._logs / "stdout", "wb") as out, open(self._logs / "stderr", "wb") as err:
            self.proc = subprocess.Popen(self.argv, stdout=out, stderr=err, env=self.env, start_new_session=True)
        return self

    @property
    def pid(self) -> int:
        return self.proc.pid

    def running(self) -> bool:
        return self.proc.poll() is None

    def wait(self, timeout: float) -> int:
        """Wait for the run to end by itself; its exit status (the test fails with the output after ``timeout``)."""
        deadline = time.monotonic() + timeout
        while self.proc.poll() is None:
            self._note_children()
            assert time.monotonic() < deadline, f"up did not end within {timeout} s\n{self.stderr()[-3000:]}"
            time.sleep(0.05)
        return self.proc.returncode

    async def finished(self, timeout: float) -> int:
        """:meth:`wait` for an async test: the event loop (and the test's own subscriptions) keeps running."""
        import asyncio

        deadline = time.monotonic() + timeout
        while self.proc.poll() is None:
            self._note_children()
            assert time.monotonic() < deadline, f"up did not end within {timeout} s\n{self.stderr()[-3000:]}"
            await asyncio.sleep(0.05)
        return self.proc.returncode

    async def endpoint_open(self, timeout: float = 60.0) -> None:
        """:meth:`wait_for_endpoint` for an async test."""
        await until(self._accepts, timeout, f"endpoint on 127.0.0.1:{self.port} (up alive: {self.running()})")

    def _accepts(self) -> bool:
        assert self.running(), f"up ended ({self.proc.returncode})\n{self.stderr()[-3000:]}"
        try:
            socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
            return True
        except OSError:
            return False

    def signal(self, sig: int = signal.SIGTERM) -> None:
        """Send ``sig`` to the supervisor process only (what Ctrl-C or ``docker stop`` does)."""
        self._note_children()
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)

    def stop(self, timeout: float = 15.0) -> int | None:
        """SIGTERM, then the exit status within ``timeout`` (None, and everything killed, if it did not end)."""
        self.signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            return None

    def kill(self) -> None:
        """SIGKILL the supervisor, its process group and every descendant seen, and reap the supervisor."""
        if self.proc is None:
            return
        self._note_children()
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        kill_all(alive(self.seen))
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass

    def left_behind(self) -> list[int]:
        """Processes of this run still alive (call after it ended)."""
        return alive(self.seen | {self.proc.pid})

    # -- waiting for the run's state ----------------------------------------------------------------------------------
    def _note_children(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.seen |= descendants(self.proc.pid)

    def wait_until(self, condition, timeout: float, what: str, poll: float = 0.1) -> None:
        """Wait for ``condition()`` while the run is alive; fail naming ``what`` if it ends or ``timeout`` passes."""
        deadline = time.monotonic() + timeout
        while not condition():
            self._note_children()
            assert self.proc.poll() is None, f"up ended ({self.proc.returncode}) before {what}\n{self.stderr()[-3000:]}"
            assert time.monotonic() < deadline, f"no {what} within {timeout} s\n{self.stderr()[-3000:]}"
            time.sleep(poll)

    def wait_for_endpoint(self, timeout: float = 60.0) -> None:
        self.wait_until(self._accepts, timeout, f"endpoint on 127.0.0.1:{self.port}", poll=0.1)

    def rows(self) -> int:
        """Rows of ``metrics.csv`` written so far."""
        path = self.record / "metrics.csv"
        return max(0, path.read_text().count("\n") - 1) if path.exists() else 0

    def wait_for_rows(self, n: int, timeout: float = 90.0) -> None:
        self.wait_until(lambda: self.rows() >= n, timeout, f"{n} rows in {self.record / 'metrics.csv'}")

    # -- output ----------------------------------------------------------------------------------------------------------
    def stdout(self) -> str:
        return (self._logs / "stdout").read_text(errors="replace")

    def stderr(self) -> str:
        return (self._logs / "stderr").read_text(errors="replace")


async def until(condition, timeout: float = 3.0, what: str = "condition") -> None:
    """Wait (on the event loop) until ``condition()`` holds; fail naming ``what`` after ``timeout`` seconds."""
    import asyncio

    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"{what} not met within {timeout} s"
        await asyncio.sleep(0.005)


def sample_rss(pid: int, role: str, into: list[int]) -> None:
    """Append the resident memory of each descendant of ``pid`` that is a ``role`` process of the run (a live
    process's memory while a run goes on; a process that just ended is passed over)."""
    for proc in psutil.Process(pid).children(recursive=True):
        try:
            if role_of(proc.cmdline()) == role:
                into.append(proc.memory_info().rss)
        except psutil.Error:
            pass


# A ``morph-sim`` command started ahead of its time: it imports what the command imports (the CLI, the command's
# module, rich, Zenoh) and runs ``morph_sim.cli.main`` with its arguments once a line arrives on its stdin.
WARM_CLI = """
import sys
import morph_sim.cli, morph_sim.commands.watch, services.process, services.bus.zenoh_bus, schemas, schemas.keys, zenoh
import rich.console, rich.live, rich.panel, rich.table
if sys.stdin.readline():
    sys.exit(morph_sim.cli.main(sys.argv[1:]))
"""


class Observer:
    """A process that watches a live run as a user's client does (``morph-sim watch``, a Zenoh script): started once
    the run's endpoint accepts connections and ``after_rows`` rows are in its record; stdout and stderr in files.

    ``warm_cli``: ``argv`` are ``morph-sim`` arguments, and the process starts with the run, imports what the command
    needs and runs it once ``after_rows`` rows are in. A late joiner of a run that lasts a few seconds joins it then,
    not after the interpreter's start and its imports (about 2.5 s on a busy machine, once longer than the rest of
    a 1,000-tick run)."""

    def __init__(self, name: str, argv: list[str], *, after_rows: int = 0, env: dict[str, str] | None = None,
                 warm_cli: bool = False):
        self.name, self.argv, self.after_rows, self.env, self.warm_cli = name, argv, after_rows, env, warm_cli
        self.proc: subprocess.Popen | None = None
        self.released = False  # a warm command was told to run
        self.out = self.err = ""

    def start(self, logs) -> None:
        argv, stdin = self.argv, None
        if self.warm_cli:
            argv, stdin = [sys.executable, "-c", WARM_CLI, *self.argv], subprocess.PIPE
        with open(logs / f"{self.name}.out", "wb") as out, open(logs / f"{self.name}.err", "wb") as err:
            self.proc = subprocess.Popen(argv, stdin=stdin, stdout=out, stderr=err, env=self.env,
                                         start_new_session=True)

    def release(self) -> None:
        """Let a warm command run (it reads one line)."""
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(b"go\n")
        self.proc.stdin.close()
        self.released = True

    def finish(self, logs, timeout: float) -> None:
        """Wait for the observer to end by itself (killed with its descendants after ``timeout``); read its output.
        A warm command never released ends without running (its stdin is closed)."""
        if self.proc is None:
            return
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            kill_tree(self.proc)
        self.out = (logs / f"{self.name}.out").read_text(errors="replace")
        self.err = (logs / f"{self.name}.err").read_text(errors="replace")

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.returncode


class SharedRun:
    """One live ``morph-sim up`` that several tests read (the ``shared_*`` fixtures in tests/conftest.py): the run and
    the observers that must see it from its start or join it mid-run are followed to the end in a background thread
    (every descendant noted, the resident memory of ``sample`` children sampled every 0.5 s), so no test's order
    decides what is observed. Each test calls :meth:`finished` and asserts its own property on the outcome."""

    def __init__(self, run: LiveRun, observers: list[Observer], *, timeout: float, sample: str = "monitor"):
        import threading

        self.run, self.observers, self.timeout, self.sample = run, {o.name: o for o in observers}, timeout, sample
        self.rss: list[int] = []
        self.left_behind: list[int] | None = None  # processes of the run alive after it ended by itself
        self.failure: str | None = None  # why following the run failed (every test that reads the run fails with it)
        self._thread = threading.Thread(target=self._follow, name=f"follow-{run.run_id}", daemon=True)

    def start(self) -> SharedRun:
        self.run.start()
        self._thread.start()
        return self

    def _follow(self) -> None:
        run, logs = self.run, self.run._logs
        pending = sorted(self.observers.values(), key=lambda o: o.after_rows)
        deadline = time.monotonic() + self.timeout
        try:
            for observer in pending:
                if observer.warm_cli:
                    observer.start(logs)
            run.wait_for_endpoint(60)
            while run.running() and time.monotonic() < deadline:
                rows = run.rows() if pending else 0
                while pending and rows >= pending[0].after_rows:
                    observer = pending.pop(0)
                    if observer.warm_cli:
                        observer.release()
                    else:
                        observer.start(logs)
                run._note_children()
                sample_rss(run.pid, self.sample, self.rss)
                time.sleep(0.1 if pending else 0.5)
            if run.running():
                self.failure = f"up did not end within {self.timeout} s\n{run.stderr()[-3000:]}"
            else:
                self.left_behind = run.left_behind()  # before anything is killed below
        except (AssertionError, OSError, psutil.Error) as exc:
            self.failure = f"following the run failed: {exc}"
        finally:
            for observer in self.observers.values():
                observer.finish(logs, 30)
            run.kill()

    def join(self) -> None:
        """Wait until the run and its observers have ended (without judging how)."""
        self._thread.join(self.timeout + 60)

    def finished(self) -> SharedRun:
        """Wait until the run and its observers have ended; fail (in the test that asks) if following it failed."""
        self.join()
        assert not self._thread.is_alive(), f"the shared run {self.run.run_id} is still being followed"
        assert self.failure is None, self.failure
        return self

    def observer(self, name: str) -> Observer:
        """The observer ``name`` after the run (fails if the run ended before it could join)."""
        observer = self.observers[name]
        joined = observer.released if observer.warm_cli else observer.proc is not None
        assert joined, f"the run ended before {name} joined it (after {observer.after_rows} rows)"
        return observer

    def stop(self) -> None:
        """Kill the run and its observers (fixture teardown)."""
        for observer in self.observers.values():
            if observer.proc is not None:
                kill_tree(observer.proc)
        self.run.kill()
        self._thread.join(30)


# The start of a user's Zenoh client script run with the run's operator credentials (``port`` and ``credentials``
# come from its argv): it waits until ``up`` has written them, then connects as a client to the run's endpoint.
OPERATOR_CLIENT = r'''
while True:  # `up` writes the run's operator credentials before it starts the sim
    try:
        conf = zenoh.Config.from_file(credentials)
        break
    except Exception:
        time.sleep(0.1)
conf.insert_json5("mode", '"client"'); conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:%s"]' % port)
'''
