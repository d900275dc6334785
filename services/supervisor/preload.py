"""A preloaded launcher: the processes of ``morph-sim up`` forked from one process that has already imported them.

Every process of a run imports the same heavy modules (numpy, pydantic and the wire models, asyncio, the services)
before it does anything: ≈ 0.35 CPU-s each, 3–4 CPU-s of a tiny run's start-up on two cores. The supervisor instead
starts one launcher process per run (``python -m services.supervisor.preload``) that imports them once, and asks it to
fork each service. A forked service is the same OS process it would be after ``exec``:

* its own pid, its own session and process group (``setsid``), its own log file on stdout and stderr, stdin on
  ``/dev/null``, the environment the supervisor gave it, and its command line in ``/proc/<pid>/cmdline`` (written into
  the launcher's reserved argument space), so ``ps`` and anyone looking for ``morph_sim.cli agent --id 3`` find it;
* it gets SIGTERM when the launcher dies (``PR_SET_PDEATHSIG``), and the launcher gets SIGKILL when the supervisor
  dies, so a killed supervisor still leaves no process behind;
* its exit status reaches the supervisor unchanged: the launcher reaps it and reports the code (negative: the
  signal), which :class:`Forked` returns like ``Popen.returncode``.

Forking is safe only from a single-threaded process: the launcher imports nothing that starts a thread and opens no
Zenoh session (importing zenoh starts no thread; its runtime starts with the first session, in the service); it checks
``/proc/self/task`` after preloading and refuses to fork otherwise, and the supervisor then starts every process with
``exec`` as before. A command other than ``python -m morph_sim.cli …`` is exec'd from the fork. Docker compose,
Kubernetes and ``python -m services.<name>`` do not use this: each container or process starts on its own.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

# What every service process imports on its way to the first tick (the sim, agent and monitor commands and their
# services). What a service imports beyond these it imports itself after the fork.
PRELOAD = (
    "numpy", "pydantic", "msgpack", "zenoh", "asyncio", "logging", "argparse", "json",
    "schemas", "schemas.tick", "schemas.keys", "services.runconfig", "services.envconfig", "services.bus.zenoh_bus",
    "services.supervisor.process", "services.faults.runtime", "services.sim.command", "services.sim.service",
    "services.agent.command", "services.agent.service", "services.monitor.command", "services.monitor.service",
    "morph_sim.cli", "morph_sim.commands.sim", "morph_sim.commands.agent", "morph_sim.commands.monitor",
)
CLI_MODULE = "morph_sim.cli"
START_TIMEOUT = 60.0  # seconds the launcher may take to import PRELOAD (a loaded two-core machine: a few seconds)
FORK_TIMEOUT = 10.0  # seconds for the launcher to answer a fork request with the new pid
_PR_SET_PDEATHSIG = 1


def _die_with(sig: int) -> None:
    """``sig`` to this process when its parent dies (Linux; elsewhere nothing)."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, sig)
    except Exception:
        pass


def _threads() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 1


def set_cmdline(argv: list[str]) -> bool:
    """Write ``argv`` as this process's command line (``/proc/self/cmdline``) into the argument space the kernel
    reserved at exec; False when it does not fit (the command line then stays the launcher's)."""
    try:
        with open("/proc/self/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        start, end = int(fields[45]), int(fields[46])  # arg_start, arg_end (fields 48 and 49 of proc(5))
        data = b"\0".join(a.encode() for a in argv) + b"\0"
        if len(data) > end - start:
            return False
        with open("/proc/self/mem", "r+b", buffering=0) as mem:
            mem.seek(start)
            mem.write(data.ljust(end - start, b"\0"))
        return True
    except (OSError, ValueError, IndexError):
        return False


# -- the launcher process ----------------------------------------------------------------------------------------------

def _child(request: dict, fds: tuple[int, ...], launcher: int) -> None:
    """In the forked child: become the service process of ``request`` and run it; never returns."""
    code = 1
    try:
        os.setsid()
        _die_with(signal.SIGTERM)
        if os.getppid() != launcher:  # the launcher died between the fork and the line above
            os._exit(1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGPIPE):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.set_wakeup_fd(-1)
        for fd in fds:
            os.close(fd)
        log = os.open(request["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.dup2(log, 1)
        os.dup2(log, 2)
        os.close(log)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        argv, env = request["argv"], request["env"]
        os.environ.clear()
        os.environ.update(env)
        if request.get("cwd"):
            os.chdir(request["cwd"])
        if argv[1:3] != ["-m", CLI_MODULE]:
            os.execve(argv[0], argv, env)
        set_cmdline(argv)
        sys.argv = [argv[0], *argv[3:]]
        from morph_sim.cli import main

        code = int(main(argv[3:]) or 0)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if not isinstance(exc.code, (int, type(None))):
            print(exc.code, file=sys.stderr)
    except BaseException:
        import traceback

        traceback.print_exc()
        code = 1
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def serve() -> int:
    """The launcher: preload, say ``ready`` (or why it cannot fork), then fork one process per request line until the
    supervisor closes the request pipe."""
    import importlib

    requests, replies = os.dup(0), os.dup(1)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    os.dup2(2, 1)  # anything printed here goes to the launcher's log, never into the reply pipe

    def reply(message: dict) -> None:
        os.write(replies, (json.dumps(message) + "\n").encode())

    set_cmdline([sys.executable, "-m", "services.supervisor.preload"])
    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except Exception as exc:  # a broken install: the services started by exec will say what is wrong
            reply({"ready": False, "why": f"cannot import {name}: {exc}"})
            return 1
    threads = _threads()
    if threads != 1:
        reply({"ready": False, "why": f"{threads} threads after preloading; forking needs one"})
        return 1
    import gc

    gc.freeze()  # the preloaded objects stay out of the collector: children do not copy their pages to scan them
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    fds = (requests, replies, wake_r, wake_w)
    me = os.getpid()
    reply({"ready": True, "pid": me})
    pending = b""

    def reap() -> None:
        while True:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            reply({"exit": pid, "code": os.waitstatus_to_exitcode(status)})

    while True:
        try:
            ready, _, _ = select.select([requests, wake_r], [], [])
        except InterruptedError:
            continue
        if wake_r in ready:
            try:
                while os.read(wake_r, 512):
                    pass
            except BlockingIOError:
                pass
        reap()
        if requests not in ready:
            continue
        data = os.read(requests, 1 << 16)
        if not data:  # the supervisor is done (or gone): children still running get SIGTERM as this process exits
            return 0
        pending += data
        while b"\n" in pending:
            line, pending = pending.split(b"\n", 1)
            request = json.loads(line)
            try:
                pid = os.fork()
            except OSError as exc:
                reply({"error": f"fork failed: {exc}"})
                continue
            if pid == 0:
                _child(request, fds, me)
            reply({"pid": pid})


# -- the supervisor's side -----------------------------------------------------------------------------------------------

class LauncherError(RuntimeError):
    """The launcher cannot start a process (the message says why); the supervisor then uses exec."""


class Forked:
    """A process the launcher forked, with the part of ``subprocess.Popen`` the supervisor uses."""

    def __init__(self, launcher: "Launcher", pid: int):
        self.launcher, self.pid = launcher, pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.launcher.collect(0.0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout)
            self.launcher.collect(0.05 if left is None else min(0.05, left))
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass


class Launcher:
    """The supervisor's handle on its launcher process: :meth:`start` it, :meth:`spawn` services, :meth:`close`."""

    def __init__(self, log_path: Path, argv_room: int):
        self.log_path = log_path
        self.argv_room = argv_room  # bytes of command line a forked process may need (see set_cmdline)
        self.proc: subprocess.Popen | None = None
        self.children: dict[int, Forked] = {}
        self._pending = b""
        self._replies: list[dict] = []

    def start(self, env: dict[str, str]) -> None:
        """Start the launcher with ``env`` (the services' common environment: thread counts of the numeric libraries
        are read as they are imported) and wait until it has preloaded; LauncherError if it cannot fork."""
        self.launch(env)
        self.wait_ready()

    def launch(self, env: dict[str, str]) -> None:
        """Start the launcher process (it then preloads: :meth:`wait_ready`). Call it from the thread that outlives
        the run: the launcher gets SIGKILL when that thread ends."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as log:
            log.write(f"--- start launcher at {time.time():.3f}\n".encode())
            log.flush()
            # the room argument reserves the command-line space each forked service writes its own command line into
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "services.supervisor.preload", "x" * self.argv_room], env=env,
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, start_new_session=True,
                preexec_fn=lambda: _die_with(signal.SIGKILL), close_fds=True)
        os.set_blocking(self.proc.stdout.fileno(), False)

    def wait_ready(self) -> None:
        """Wait until the launched launcher has preloaded; LauncherError (and the launcher ended) if it cannot fork."""
        hello = self._next(lambda m: "ready" in m, START_TIMEOUT)
        if hello is None or not hello.get("ready"):
            ended = None if self.proc is None else self.proc.poll()
            why = (hello or {}).get("why") or (f"it exited with status {ended} (log {self.log_path})" if ended is not None
                                               else f"no answer within {START_TIMEOUT:.0f} s")
            self.close()
            raise LauncherError(f"the preloaded launcher cannot fork: {why}")

    def spawn(self, argv: list[str], env: dict[str, str], log_path: Path) -> Forked:
        if self.proc is None or self.proc.poll() is not None:
            raise LauncherError("the preloaded launcher is not running")
        request = {"argv": argv, "env": env, "log": str(log_path), "cwd": os.getcwd()}
        try:
            self.proc.stdin.write((json.dumps(request) + "\n").encode())
            self.proc.stdin.flush()
        except OSError as exc:
            raise LauncherError(f"the preloaded launcher does not take requests: {exc}") from None
        answer = self._next(lambda m: "pid" in m or "error" in m, FORK_TIMEOUT)
        if answer is None or "error" in answer:
            raise LauncherError((answer or {}).get("error") or f"no pid within {FORK_TIMEOUT:.0f} s")
        child = Forked(self, int(answer["pid"]))
        self.children[child.pid] = child
        return child

    def collect(self, timeout: float) -> None:
        """Read what the launcher reported (exit statuses), waiting up to ``timeout`` seconds for something."""
        self._read(timeout)
        self._apply()

    def _apply(self) -> None:
        keep = []
        for message in self._replies:
            if "exit" in message:
                child = self.children.get(int(message["exit"]))
                if child is not None:
                    child.returncode = int(message["code"])
            else:
                keep.append(message)
        self._replies = keep
        if self.proc is not None and self.proc.poll() is not None and not self._pending:
            # the launcher is gone: its children got SIGTERM (PR_SET_PDEATHSIG) and nobody reports them any more
            for child in self.children.values():
                if child.returncode is None and not _exists(child.pid):
                    child.returncode = -signal.SIGTERM

    def _read(self, timeout: float) -> None:
        if self.proc is None or self.proc.stdout.closed:
            return
        fd = self.proc.stdout.fileno()
        try:
            ready, _, _ = select.select([fd], [], [], max(0.0, timeout))
        except (OSError, ValueError):
            return
        if not ready:
            return
        while True:
            try:
                data = os.read(fd, 1 << 16)
            except BlockingIOError:
                break
            except OSError:
                break
            if not data:
                break
            self._pending += data
        while b"\n" in self._pending:
            line, self._pending = self._pending.split(b"\n", 1)
            try:
                self._replies.append(json.loads(line))
            except ValueError:
                continue

    def _next(self, wanted, timeout: float) -> dict | None:
        """The first reply ``wanted`` accepts, waiting up to ``timeout`` seconds; None if none comes (or the
        launcher ended without sending it)."""
        deadline = time.monotonic() + timeout
        while True:
            for i, message in enumerate(self._replies):
                if wanted(message):
                    return self._replies.pop(i)
            self._apply()
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            if self.proc is None or self.proc.poll() is not None:
                self._read(0.0)  # what it wrote before it ended
                found = [m for m in self._replies if wanted(m)]
                return found[0] if found else None
            self._read(min(left, 0.1))

    def close(self, timeout: float = 2.0) -> None:
        """End the launcher (after its children: any still running get SIGTERM as it exits)."""
        if self.proc is None or self.proc.stdout.closed:
            return
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.collect(0.0)
        try:
            self.proc.stdout.close()
        except OSError:
            pass


def _exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


if __name__ == "__main__":
    status = serve()
    # no interpreter teardown: finalising numpy, scipy and the models costs a loaded machine seconds, and `up` waits for
    # this process at its end (everything is gone within 5 s of Ctrl-C)
    sys.stderr.flush()
    os._exit(status)
