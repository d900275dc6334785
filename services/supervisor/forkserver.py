"""Starting a local run's processes by fork from one interpreter that has imported them already.

Every process of a run (sim, agents, monitor) is the same program with other flags, and a fresh interpreter spends
about half a CPU-second importing numpy, pydantic with the wire models, asyncio, zenoh and the services before its
first tick: for a medium fleet that is most of the CPU an `up` costs before step 0. So the supervisor starts one
``python -m services.supervisor.forkserver``, which imports all of it once and then forks each process on request.

A forked process is what an exec'd one was: its own pid, session and process group, its log file as stdout and
stderr, its own environment (set before Zenoh reads ``ZENOH_RUNTIME`` when its first session opens), its command
line in its argument space (``ps`` and ``/proc/<pid>/cmdline`` show ``… -m services.agent --id 3 …``), and
SIGTERM when its parent dies: the server gets SIGTERM when the supervisor dies and its children theirs when the
server does, so nothing outlives the supervisor. Fork is safe only while this process has one thread (no Zenoh
session is ever opened here, and BLAS is held to one thread by the environment the supervisor gives the server); it
refuses a request otherwise.

Where it can, ``up`` forks the server itself from its own interpreter, which has imported most of what the run's
processes need already (the wire models, numpy, pydantic, the supervisor's half of the services): the server then
imports the rest, a fifth of it, alongside the supervisor's own start instead of after it (``ForkServer(...,
fork=True)``). That needs a supervisor with one thread and an argument space as large as the exec'd server's, for
the command lines its children write there; ``morph-sim up`` makes room for them when it starts
(:func:`argument_space`).

The server speaks JSON lines: on stdin ``{"id": n, "argv": [python, "-m", "services.<sim|agent|monitor>", ...],
"env": {...},
"log": path}``; on stdout
``{"ready": pid}`` once, ``{"id": n, "pid": p}`` or ``{"id": n, "error": "..."}`` per request, and
``{"exit": pid, "status": code}`` (negative: killed by that signal, as ``subprocess`` reports it) for every child
that ends. It ends when its stdin closes.
"""

from __future__ import annotations

import json
import os
import select
import signal
import sys

from services.supervisor.parent import signal_on_parent_death

# What the processes of a run import before their first tick (the rest, e.g. the monitor's scipy.stats, is imported
# where it is used, by the one process that uses it).
PRELOAD = (
    "numpy",
    "zenoh",
    "services.sim.command",
    "services.agent.command",
    "services.monitor.command",
    "services.process",
    "services.bus.zenoh_bus",
    "services.faults.runtime",
    "services.sim.service",
    "services.agent.roles",
    "services.monitor.service",
)
#: the service processes a request may start: ``[python, "-m", "services.<name>", flags...]`` (``ProcessSpec.command()``)
SERVICES = ("sim", "agent", "monitor", "air")
#: bytes of argument space the server reserves for its children's command lines (a medium run's is ~400)
TITLE_SPACE = 4096


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _argument_range() -> tuple[int, int]:
    """(start, end) addresses of this process's argument space (``arg_start``/``arg_end`` of ``/proc/self/stat``)."""
    with open("/proc/self/stat", "rb") as f:
        fields = f.read().rsplit(b")", 1)[1].split()
    return int(fields[45]), int(fields[46])  # fields 48 and 49 of proc(5); fields[0] is field 3


def argument_space() -> int:
    """Bytes of command line this process can show (0 where ``/proc`` does not tell)."""
    try:
        start, end = _argument_range()
    except (OSError, IndexError, ValueError):
        return 0
    return end - start


def set_command_line(argv: list[str]) -> None:
    """Write ``argv`` into this process's argument space, which ``/proc/<pid>/cmdline`` (``ps``, psutil) reads.

    The space is the one the kernel gave this process's own command line (``arg_start``/``arg_end`` of
    ``/proc/self/stat``); CPython keeps its own copies of the arguments, so the original bytes are free to reuse.
    A longer command line is cut to the space."""
    import ctypes

    start, end = _argument_range()
    size = end - start
    if size <= 1:
        return
    data = b"\0".join(a.encode() for a in argv)[: size - 1]
    data += b"\0" * (size - len(data))
    ctypes.memmove(start, data, size)


def _child(request: dict, server_pid: int, started: int, channels: tuple[int, ...]) -> None:
    """In the forked child: become the requested process, run it, and leave with its exit status. ``started`` is
    written to once the child has its own session and its parent-death signal, so that the supervisor never
    signals a group that does not exist yet."""
    code = 1
    try:
        os.setsid()  # its own session and process group: the supervisor signals the group
        signal_on_parent_death(signal.SIGTERM)
        if os.getppid() != server_pid:  # the server died before the prctl took hold
            os._exit(1)
        os.write(started, b"s")
        os.close(started)
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_DFL)
        log = os.open(request["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(log, 1)
        os.dup2(log, 2)
        for fd in (log, null, *channels):
            try:
                os.close(fd)
            except OSError:
                pass
        os.environ.clear()
        os.environ.update(request["env"])
        set_command_line(request["argv"])
        module, args = request["argv"][2], request["argv"][3:]
        sys.argv = [module, *args]
        import importlib

        from services.process import command_main

        code = int(command_main(importlib.import_module(module + ".command"), args) or 0)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        import traceback

        traceback.print_exc()
        code = 1
    finally:
        _leave(code)


def _leave(code: int) -> None:
    """End a forked process with ``code``: what it printed reaches its log, and no interpreter teardown runs (it
    would free, and so copy, what the process shares with its parent)."""
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


def _is_service(argv: list[str]) -> bool:
    return len(argv) >= 3 and argv[1] == "-m" and argv[2] in {f"services.{name}" for name in SERVICES}


def _status(raw: int) -> int:
    return -os.WTERMSIG(raw) if os.WIFSIGNALED(raw) else os.WEXITSTATUS(raw)


def serve() -> int:
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    import gc

    gc.freeze()  # what every child shares stays shared: the collector never touches (and so copies) those pages
    out = sys.stdout

    def say(message: dict) -> None:
        out.write(json.dumps(message) + "\n")
        out.flush()

    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so that the wakeup fd is written
    signal.set_wakeup_fd(wake_w)
    stdin = sys.stdin.fileno()
    me = os.getpid()
    say({"ready": me})
    pending = b""
    while True:
        readable, _, _ = select.select([stdin, wake_r], [], [])
        if wake_r in readable:
            try:
                os.read(wake_r, 512)
            except BlockingIOError:
                pass
        while True:  # every child that ended, reaped and reported
            try:
                pid, raw = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            say({"exit": pid, "status": _status(raw)})
        if stdin not in readable:
            continue
        chunk = os.read(stdin, 65536)
        if not chunk:  # the supervisor closed the channel: the run is over
            return 0
        pending += chunk
        while b"\n" in pending:
            line, pending = pending.split(b"\n", 1)
            request = json.loads(line)
            if not _is_service(request["argv"]):
                say({"id": request["id"], "error": f"not a service of a run: {request['argv'][:4]}"})
                continue
            if _threads() != 1:
                say({"id": request["id"], "error": f"the fork server has {_threads()} threads; fork is unsafe"})
                continue
            sys.stdout.flush()
            sys.stderr.flush()
            started_r, started_w = os.pipe()
            pid = os.fork()
            if pid == 0:
                os.close(started_r)
                _child(request, me, started_w, (wake_r, wake_w))
            os.close(started_w)
            try:
                os.read(started_r, 1)  # b"" if the child ended first: its exit is reported as any other
            finally:
                os.close(started_r)
            say({"id": request["id"], "pid": pid})


class ForkedProcess:
    """A child of the fork server, as the supervisor sees it: the part of ``subprocess.Popen`` it uses."""

    def __init__(self, server: "ForkServer", pid: int):
        self.server, self.pid = server, pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.server.status(self.pid)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        import subprocess

        if self.poll() is None:
            self.returncode = self.server.wait_status(self.pid, timeout)
            if self.returncode is None:
                raise subprocess.TimeoutExpired(["morph-sim", str(self.pid)], timeout)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)


class _ServerProcess:
    """The part of ``subprocess.Popen`` :class:`ForkServer` uses, for a server forked from the supervisor itself."""

    def __init__(self, pid: int, stdin, stdout):
        self.pid, self.stdin, self.stdout = pid, stdin, stdout
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, raw = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped elsewhere: it has ended, how is not known
                self.returncode = ForkServer.LOST
            else:
                if pid:
                    self.returncode = _status(raw)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        import subprocess
        import time

        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise subprocess.TimeoutExpired([sys.executable, "-m", __name__], timeout)
            time.sleep(0.01)
        return self.returncode  # type: ignore[return-value]

    def kill(self) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _fork_server(env: dict[str, str], log_path, preexec_fn) -> _ServerProcess:
    """The server as a fork of this process, which must have one thread: what the exec'd server would be (its own
    session, its log as stderr, only its channels open, ``env`` as its environment, its own command line)."""
    import traceback

    from_supervisor, to_server = os.pipe()
    from_server, to_supervisor = os.pipe()
    log = os.open(log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the server
        code = 1
        try:
            os.setsid()
            if preexec_fn is not None:
                preexec_fn()
            os.dup2(from_supervisor, 0)
            os.dup2(to_supervisor, 1)
            os.dup2(log, 2)
            os.closerange(3, 1 << 20)  # every descriptor the supervisor had open (its record, its terminal's copies)
            signal.set_wakeup_fd(-1)
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGCHLD):
                signal.signal(sig, signal.SIG_DFL)
            os.environ.clear()
            os.environ.update(env)
            set_command_line([sys.executable, "-m", __name__])
            sys.argv = [__name__]
            code = serve()
        except BaseException:
            traceback.print_exc()
        finally:
            _leave(code)
    for fd in (from_supervisor, to_supervisor, log):
        os.close(fd)
    return _ServerProcess(pid, os.fdopen(to_server, "wb"), os.fdopen(from_server, "rb"))


class ForkServer:
    """The supervisor's end: starts the server, asks it for processes, hears how they end.

    A thread reads the server's lines (forks answer within milliseconds; exits come at any time), so ``poll`` and
    ``wait`` work from the supervisor's event loop and from its final synchronous reap alike."""

    #: exit status of a child whose end the server could not report (the server itself was killed; the child then
    #: got SIGTERM from its parent's death)
    LOST = -signal.SIGTERM

    def __init__(self, env: dict[str, str], log_path, *, ready_timeout: float = 60.0, preexec_fn=None,
                 on_exit=None, fork: bool = False, wait: bool = True):
        """``on_exit()`` is called (on the reader thread) whenever a child has ended, and when the server has.
        ``fork``: fork the server from this process where that is safe (one thread, room for command lines), else
        start ``python -m services.supervisor.forkserver``. ``wait=False``: return at once; :meth:`wait_ready`
        before the first :meth:`spawn`."""
        import subprocess
        import threading

        self.on_exit = on_exit
        self._lock = threading.Condition()
        self._exits: dict[int, int] = {}
        self._answers: dict[int, dict] = {}
        self._next = 0
        self._ready = False
        self._closed = False
        self.log_path = log_path
        self.forked = fork and _threads() == 1 and argument_space() >= TITLE_SPACE
        if self.forked:
            self.proc = _fork_server(env, log_path, preexec_fn)
        else:
            with open(log_path, "ab") as log:
                self.proc = subprocess.Popen(
                    [sys.executable, "-m", __name__, " " * TITLE_SPACE], env=env, stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE, stderr=log, start_new_session=True, preexec_fn=preexec_fn,
                    close_fds=True)
        self.pid = self.proc.pid
        self._reader = threading.Thread(target=self._read, name="fork-server", daemon=True)
        self._reader.start()
        if wait:
            self.wait_ready(ready_timeout)

    def wait_ready(self, timeout: float) -> None:
        """Until the server has imported what its children need; RuntimeError if it cannot start."""
        with self._lock:
            if not self._lock.wait_for(lambda: self._ready or self._closed, timeout):
                self.close()
                raise RuntimeError(f"the fork server did not start within {timeout:.0f} s")
            if not self._ready:
                raise RuntimeError(f"the fork server ended with status {self.proc.wait()} before it was ready "
                                   f"(its log: {self.log_path})")

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                message = json.loads(line)
            except ValueError:  # not the server's (something it imported printed): not a report
                continue
            if not isinstance(message, dict):
                continue
            with self._lock:
                if "ready" in message:
                    self._ready = True
                elif "exit" in message:
                    self._exits[message["exit"]] = message["status"]
                else:
                    self._answers[message["id"]] = message
                self._lock.notify_all()
            if "exit" in message and self.on_exit is not None:
                self.on_exit()
        with self._lock:  # the server is gone (closed by us, or killed): so are its children
            self._closed = True
            self._lock.notify_all()
        if self.on_exit is not None:
            self.on_exit()

    def spawn(self, argv: list[str], env: dict[str, str], log_path, timeout: float = 10.0) -> ForkedProcess:
        """Fork ``argv`` (``python -m services.<name> …``) with ``env``, its output appended to ``log_path``."""
        with self._lock:
            if self._closed:
                raise RuntimeError("the fork server has ended")
            self._next += 1
            ident = self._next
            self.proc.stdin.write((json.dumps({"id": ident, "argv": argv, "env": env, "log": str(log_path)})
                                   + "\n").encode())
            self.proc.stdin.flush()
            if not self._lock.wait_for(lambda: ident in self._answers or self._closed, timeout):
                raise RuntimeError(f"the fork server did not answer within {timeout:.0f} s")
            answer = self._answers.pop(ident, None)
        if answer is None:
            raise RuntimeError("the fork server ended while starting a process")
        if "error" in answer:
            raise RuntimeError(f"the fork server refused: {answer['error']}")
        return ForkedProcess(self, answer["pid"])

    @staticmethod
    def _gone(pid: int) -> bool:
        """No such process, or only its zombie (whoever reaps orphans here may not do it soon)."""
        try:
            with open(f"/proc/{pid}/stat", "rb") as f:
                return f.read().rsplit(b")", 1)[1].split()[0] in (b"Z", b"X")
        except OSError:
            return True

    def status(self, pid: int) -> int | None:
        with self._lock:
            if pid in self._exits:
                return self._exits[pid]
            if self._closed and self._gone(pid):
                return self.LOST
            return None

    def wait_status(self, pid: int, timeout: float | None) -> int | None:
        import time

        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while True:
                if pid in self._exits:
                    return self._exits[pid]
                if self._closed and self._gone(pid):
                    return self.LOST
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                # after the server's end no line will come: look again for the pid now and then
                self._lock.wait(0.05 if self._closed else left)

    def close(self, timeout: float = 2.0) -> None:
        """End the server (its children are the supervisor's to end first) and reap it."""
        import subprocess

        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


if __name__ == "__main__":
    # argv[1] is TITLE_SPACE bytes of padding: the argument space each child writes its command line into.
    # No interpreter teardown at the end: it would only spend CPU freeing what every child shared.
    status = serve()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
