"""Where episodes run: this machine's processes (default) or a Dask cluster.

An executor maps a picklable, module-level function over a list of picklable tasks and yields the results as they
finish (any order; callers key results by task). Both executors run the same function on the same tasks, so a
result does not depend on where it was computed: every episode seeds its own streams from its task.

* :class:`LocalExecutor` — ``jobs`` worker processes of :func:`episode_pool`, the one pool of this machine's
  processes every study uses (``jobs=1``: in this process, no pool). Workers ignore SIGINT so Ctrl-C reaches only
  the parent, which stops them; nothing keeps running after an interrupt, nor after the parent is killed (each
  worker dies with it).
* :class:`DaskExecutor` — a ``dask.distributed`` client on a scheduler address (``tcp://HOST:8786``) or an existing
  client/cluster; needs the optional extra ``pip install 'morph-sim[cluster]'``. The workers need morph-sim
  installed at the same version (see docs/sweep.md, two-machine recipe).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor as PoolExecutor, Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Any, Protocol

EXECUTORS = ("local", "dask")
CLUSTER_HINT = "pip install 'morph-sim[cluster]'"


class Executor(Protocol):
    def map_unordered(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]: ...

    def close(self) -> None: ...


#: seconds a stopped worker gets to end before the parent goes on
STOP_WAIT = 5.0


def _worker_start(parent: int) -> None:
    """A pool worker's first act: deaf to SIGINT, and bound to the life of the process that started it."""
    # Ctrl-C goes to the whole process group; only the parent decides what an interrupt means.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with(parent)


def _die_with(parent: int) -> None:
    """End this worker when ``parent`` ends, however it ends. A parent killed with SIGKILL runs no clean-up, and the
    workers, which hold copies of the pool's pipes, would never see them close and would wait for work forever.
    Linux: the kernel sends SIGKILL on the parent's death; elsewhere a daemon thread notices the worker was handed
    to another parent. (On Linux the parent is the thread that started the worker: episode_pool starts them in the
    thread that holds the pool, which outlives them.)"""
    from services.supervisor.parent import signal_on_parent_death

    if signal_on_parent_death(signal.SIGKILL):
        if os.getppid() != parent:  # the parent died before the kernel was asked
            os._exit(1)
        return
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL)
        os._exit(1)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


PARENT_POLL = 0.5  # seconds between a worker's looks at its parent where no kernel signal tells it


class _InProcess(PoolExecutor):
    """``jobs == 1``: each episode runs in this process when submitted (no worker process to start or feed)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # delivered by future.result(), as a pool would
            future.set_exception(exc)
        return future


@contextmanager
def episode_pool(jobs: int) -> Iterator[PoolExecutor]:
    """This machine's worker processes for episodes: forked (nothing is imported again per worker) and deaf to
    SIGINT. When the parent leaves the block on an error or an interrupt, queued episodes are dropped and running
    ones stopped, so nothing outlives the command; on a normal exit it waits for every episode submitted."""
    if jobs < 1:
        raise ValueError(f"jobs: must be at least 1, got {jobs}")
    if jobs == 1:
        yield _InProcess()
        return
    # What every episode imports on its first summary (the link-distance correlation's scipy.stats, about half a
    # CPU-second): imported here once, the forked workers have it instead of each importing it again.
    import scipy.stats  # noqa: F401

    pool = ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork" if sys.platform != "win32" else "spawn"),
                               initializer=_worker_start, initargs=(os.getpid(),))
    try:
        yield pool
    except BaseException:
        _stop(pool)
        raise
    pool.shutdown(wait=True)


def _stop(pool: ProcessPoolExecutor) -> None:
    """Drop the queued episodes and end the workers (they ignore SIGINT, so only the parent can stop them).
    ProcessPoolExecutor gains a method for this in Python 3.14; before it, the pool's own process table.

    Then wait for the pool's manager thread, which closes its wake-up pipe once it sees the workers gone. Python
    3.11 wakes every such thread at interpreter exit without a lock: a close racing that wake-up raised "OSError:
    [Errno 9] Bad file descriptor" as an interrupted command's last line, after its own (seen once in a run of the
    suite). With the thread ended first, the pipe is closed and the exit's wake-up does nothing."""
    workers = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)  # (shutdown forgets it)
    pool.shutdown(wait=False, cancel_futures=True)
    for worker in workers:
        if worker.is_alive():
            worker.terminate()
    for worker in workers:
        worker.join(STOP_WAIT)
    if manager is not None:
        manager.join(STOP_WAIT)


#: Most local worker processes: more than the machine's cores only queue for them, and each is a Python process
#: of its own (about 100 MB with an episode loaded), so 256 already asks for more cores and memory than one machine
#: has; a larger --jobs would start that many processes at once.
MAX_LOCAL_JOBS = 256


def check_jobs(jobs: int) -> int:
    """``jobs`` if it is a number of local worker processes: 1..MAX_LOCAL_JOBS."""
    from services.inputs import at_most

    if jobs < 1:
        raise ValueError(f"jobs: must be at least 1, got {jobs}")
    return at_most(jobs, MAX_LOCAL_JOBS, "jobs", "worker processes")


class LocalExecutor:
    def __init__(self, jobs: int = 2):
        self.jobs = check_jobs(jobs)
        self._running: Iterator[Any] | None = None

    def map_unordered(self, fn, tasks):
        self._running = self._results(fn, list(tasks))
        return self._running

    def _results(self, fn, tasks):
        if self.jobs == 1 or len(tasks) <= 1:
            for task in tasks:
                yield fn(task)
            return
        with episode_pool(min(self.jobs, len(tasks))) as pool:
            for future in as_completed([pool.submit(fn, task) for task in tasks]):
                yield future.result()

    def close(self) -> None:
        """Stop what :meth:`map_unordered` still runs (a caller that left its loop early)."""
        if self._running is not None:
            self._running.close()  # GeneratorExit in the pool's block: its workers are stopped
            self._running = None


class DaskExecutor:
    """Runs tasks on a Dask cluster. ``scheduler``: an address like ``tcp://HOST:8786``, a ``distributed.Client``
    or anything with a ``scheduler_address`` (a LocalCluster)."""

    def __init__(self, scheduler: Any, *, timeout: float = 30.0):
        try:
            from distributed import Client
        except ImportError:
            raise ImportError(f"executor dask: dask.distributed is not installed; {CLUSTER_HINT}") from None
        if scheduler is None or scheduler == "":
            raise ValueError("scheduler: the dask executor needs --scheduler tcp://HOST:8786")
        self._own = not isinstance(scheduler, Client)
        if isinstance(scheduler, Client):
            self.client = scheduler
        else:
            address = getattr(scheduler, "scheduler_address", scheduler)
            if not isinstance(address, str) or "://" not in address:
                raise ValueError(f"scheduler: {address!r} is not an address like tcp://HOST:8786")
            try:
                self.client = Client(address, timeout=timeout, set_as_default=False)
            except OSError as exc:
                raise ValueError(f"scheduler: cannot reach {address}: {exc}") from None
        self._futures: list = []

    def map_unordered(self, fn, tasks):
        from distributed import as_completed

        tasks = list(tasks)
        if not tasks:
            return
        # pure=False: two equal tasks are still two episodes to run (never deduplicated by the scheduler)
        self._futures = self.client.map(fn, tasks, pure=False)
        try:
            for future in as_completed(self._futures, loop=self.client.loop):
                yield future.result()
        finally:
            self.client.cancel([f for f in self._futures if not f.done()])
            self._futures = []

    def close(self) -> None:
        if self._own:
            self.client.close()


def make_executor(kind: str = "local", *, jobs: int = 2, scheduler: Any = None) -> Executor:
    if kind == "local":
        return LocalExecutor(jobs)
    if kind == "dask":
        return DaskExecutor(scheduler)
    raise ValueError(f"executor: unknown {kind!r} (choose from {', '.join(EXECUTORS)})")
