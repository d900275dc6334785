"""The local supervisor of ``morph-sim up``: starts the process graph, watches it, restarts agents, ends it.

This is the driver; each concern is a module of its own: the processes and what their ends mean (``children``),
the endpoint's readiness (``readiness``), what the run's traffic says (``observer``), the live line (``liveline``),
crash faults (``crashes``), the stall watchdog (``watchdog``) and the record check at the end (``record``).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from collections.abc import Callable

from services.credentials import SUPERVISOR
from services.runconfig import RunConfig
from services.supervisor.children import (
    RECORD_FAILED,
    SHUTDOWN_BOUND,
    TERM_GRACE,
    Child,
    Exit,
    end_children,
    exit_verdict,
    fork_server_ready,
    last_error,
    start_fork_server,
)
from services.supervisor.crashes import CrashExecutor
from services.supervisor.errors import RunFailed, RunStalled, StartError
from services.supervisor.forkserver import ForkServer
from services.supervisor.graph import process_graph
from services.supervisor.liveline import SHOW_EVERY, LiveLine
from services.supervisor.observer import Progress, RunObserver
from services.supervisor.readiness import check_port_free, tcp_reachable, wait_endpoint
from services.supervisor.record import (
    MONITOR_END_TIMEOUT,
    STOPPED_FROM_OUTSIDE,
    monitor_failure,
    outcome,
    take_record_numbers,
)
from services.supervisor.watchdog import StallWatch, default_stall_timeout

# The names importers know the supervisor by, wherever they live now.
__all__ = ["MONITOR_END_TIMEOUT", "RECORD_FAILED", "SHOW_EVERY", "SHUTDOWN_BOUND", "STOPPED_FROM_OUTSIDE",
           "TERM_GRACE", "Child", "Progress", "RunFailed", "RunStalled", "StartError", "Supervisor"]

log = logging.getLogger("morph_sim.supervisor")


class Supervisor:
    """Runs one distributed run of ``config`` to completion or interruption."""

    def __init__(self, config: RunConfig, *, endpoint: str | None = None,
                 on_progress: Callable[[Progress, str], None] | None = None, ready_timeout: float | None = None,
                 stall_timeout: float | None = None, insecure: bool = False, monitor_args: tuple[str, ...] = (),
                 end_grace: float = 0.0):
        from services.bus.zenoh_bus import endpoint as make_endpoint, free_port
        from services.credentials import RunCredentials, run_credentials
        from services.process import ZENOH_CONFIG_ENV

        self.config = config
        self.external = config.endpoint is not None
        self.endpoint = config.endpoint or endpoint or config.listen or make_endpoint(free_port())
        self.specs = process_graph(config, self.endpoint, monitor_args)
        self.end_grace = end_grace  # seconds the monitor keeps serving after the run (Prometheus), waited for too
        logs = config.record_dir / "logs"
        self.children = {spec.name: Child(spec, logs / f"{spec.name}.log") for spec in self.specs}
        from services.faults.schedule import load_schedule

        # a bad schedule file fails now, before anything is written or started
        self.schedule = load_schedule(config.fault_schedule, config.n_agents) if config.fault_schedule else None
        # Secure by default: the embedded endpoint admits only this run's processes and the operator, each with its
        # own password, and enforces who may publish what (services/credentials.py). An external router's security
        # is its deployment's (docs/deploy.md); --insecure keeps the endpoint open.
        self.insecure = insecure
        self.credentials: RunCredentials | None = None
        if not self.external:
            check_port_free(self.endpoint)  # StartError naming the port, before anything is written or started
        if not insecure and not self.external:
            directory = run_credentials(config.record_dir).directory
            try:
                self.credentials = RunCredentials.create(directory, config.run_id, config.n_agents,
                                                         where=self.endpoint)
            except OSError as exc:  # a full disk or quota: nothing was started yet, so the run is refused whole
                raise StartError(f"credentials: cannot write {exc.filename or directory}: "
                                 f"{exc.strerror or exc}") from None
            for child in self.children.values():
                child.extra_env[ZENOH_CONFIG_ENV] = str(self.credentials.for_role(child.spec.role, child.spec.agent))
        self.progress = Progress()
        self.on_progress = on_progress
        self.line = LiveLine(on_progress, steps=config.steps, n_agents=config.n_agents, endpoint=self.endpoint)
        self.ready_timeout = config.ready_timeout if ready_timeout is None else ready_timeout
        self.stall_timeout = (default_stall_timeout(config.phase_timeout, config.period) if stall_timeout is None
                              else stall_timeout)
        self.stop_requested: str | None = None
        self.outcome = "interrupted"  # how the run ended, for the final line
        self.check = None  # the record's check at the end of the run (services.monitor.recorder.RecordCheck)
        self.events: list[tuple[float, str, str]] = []
        self.crashes = CrashExecutor(config, self.schedule, pid_of=self._live_pid, mark=self._mark_planned,
                                     note=self._event, publish_event=self._publish_event)
        self._bus = None
        self._keys = None
        # the pre-imported interpreter every process of the run is forked from (restarts excepted)
        self.server: ForkServer | None = None
        # The watch loops wait on this (set when a child ends or a stop is asked for) and otherwise wake only for
        # their periodic duties (the live line, the start, stall and end-of-record deadlines).
        self._wake: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # -- bookkeeping -------------------------------------------------------------------------------------------------
    @property
    def all_pids(self) -> list[int]:
        server = [] if self.server is None else [self.server.pid]
        return server + [pid for child in self.children.values() for pid in child.pids]

    def _live_pid(self, name: str) -> int | None:
        child = self.children.get(name)
        return child.pid if child is not None and child.alive() else None

    def _mark_planned(self, name: str, pid: int, cold: bool) -> None:
        """``pid`` of process ``name`` was killed by a crash fault: its end is a planned restart."""
        child = self.children.get(name)
        if child is not None:
            child.planned[pid] = cold

    def _event(self, kind: str, what: str) -> None:
        self.events.append((time.time(), kind, what))
        log.info("%s: %s", kind, what)

    def request_stop(self, reason: str) -> None:
        if self.stop_requested is None:
            self.stop_requested = reason
        self._notify()

    def _notify(self) -> None:
        """Wake the watch loop now (from any thread): a child ended, or a stop was asked for."""
        loop, wake = self._loop, self._wake
        if loop is None or wake is None:
            return
        try:
            loop.call_soon_threadsafe(wake.set)
        except RuntimeError:  # the loop has closed: nobody is waiting
            pass

    async def _nap(self, timeout: float) -> None:
        """Until :meth:`_notify` or ``timeout`` seconds, whichever comes first."""
        wake = self._wake
        if wake is None:
            await asyncio.sleep(timeout)
            return
        try:
            await asyncio.wait_for(wake.wait(), max(timeout, 0.0))
        except asyncio.TimeoutError:
            pass
        wake.clear()

    def prestart(self) -> None:
        """Start the fork server now, forked from this process if it has one thread (before the live line's thread
        and the event loop), so that it imports the rest of the run's code while this process goes on starting."""
        if self.server is None:
            self.server = start_fork_server(self.config.record_dir, self.ready_timeout, self._notify, fork=True,
                                            wait=False)

    # -- main ----------------------------------------------------------------------------------------------------------
    async def run(self) -> int:
        """0 when the run completed, 130/143 when interrupted; raises StartError if a process cannot start."""
        loop = asyncio.get_running_loop()
        self._loop, self._wake = loop, asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                loop.add_signal_handler(sig, self.request_stop, signal.Signals(sig).name)
            except (NotImplementedError, RuntimeError):  # not the main thread (tests drive it from a thread)
                pass
        try:
            return await self._run()
        finally:
            await self.shutdown()
            for sig in (signal.SIGINT, signal.SIGTERM):
                try:
                    loop.remove_signal_handler(sig)
                except (NotImplementedError, RuntimeError):
                    pass

    async def _run(self) -> int:
        if self.external and not await tcp_reachable(self.endpoint, 3.0):
            raise StartError(f"nothing listens on the Zenoh endpoint {self.endpoint} (--endpoint): start the router "
                             "first, or leave --endpoint out to host the endpoint in the sim")
        sim = self.children["sim"]
        if self.server is None:
            self.server = start_fork_server(self.config.record_dir, self.ready_timeout, self._notify)
        else:
            fork_server_ready(self.server, self.ready_timeout)
        sim.start(server=self.server)
        self._event("start", f"sim pid {sim.pid} ({'connects to' if self.external else 'listens on'} {self.endpoint})")
        # The sim must have opened its endpoint before anyone connects; a short wait for the port is enough.
        if not self.external:
            await wait_endpoint(sim, self.endpoint, self.ready_timeout, lambda: bool(self.stop_requested))
        for name, child in self.children.items():
            if name != "sim":
                child.start(server=self.server)
        self._event("start", f"{len(self.children) - 1} agent and monitor processes")
        try:
            bus = await self._open_bus()
        except ConnectionError as exc:
            await asyncio.sleep(0.5)  # let a failing sim write its reason
            raise StartError(f"cannot reach the run's Zenoh endpoint {self.endpoint}: {exc}\nsim log:\n"
                             f"{sim.log_tail()}") from None
        try:
            return await self._watch(bus)
        finally:
            await bus.close()

    async def _open_bus(self):
        from services.process import open_bus

        operator = None if self.credentials is None else str(self.credentials.operator)
        return await open_bus(SUPERVISOR, connect=self.endpoint, config_file=operator)

    async def _watch(self, bus) -> int:
        """The run from the processes' start to its end: the observer feeds the progress from the bus, the crash
        executor and the stall watchdog go by it, and each pass of the loop handles the children's ends."""
        from schemas.keys import RunKeys

        self._bus, self._keys = bus, RunKeys(self.config.run_id)
        await RunObserver(self.progress, self.config.steps, self.crashes.on_tick).attach(bus, self._keys)
        await self.crashes.start(bus, clock=lambda: max(self.progress.t, 0) * self.config.dt)
        ready_deadline = time.monotonic() + self.ready_timeout
        stall = StallWatch(self.config.steps, self.stall_timeout, self.progress.t, time.monotonic())
        while True:
            if self.stop_requested:
                return await self._stop(self.stop_requested)
            sim = self.children["sim"]
            if not sim.alive():
                code = sim.proc.returncode
                if code != 0:
                    raise StartError(f"sim exited with status {code}:\n{sim.log_tail()}")
                return await self._end_of_run()
            running = self.progress.t >= 0
            if running:
                self.crashes.catch_up(self.progress.t)
            await self._handle_exits(running)
            if stall.check(self.progress.t, time.monotonic()):
                self._event("stalled", stall.reason())
                raise RunStalled(f"the run stalled: {stall.reason()} (phase deadlines included); the record holds "
                                 f"the ticks up to the stall; sim log:\n{sim.log_tail()}")
            if not running and time.monotonic() > ready_deadline:
                raise StartError(f"the run did not start within {self.ready_timeout:.0f} s; sim log:\n"
                                 f"{sim.log_tail()}")
            if self.line.due(time.monotonic()):
                self.line.show(self.progress)
            await self._nap(self.line.next_in(time.monotonic()))

    async def _stop(self, reason: str) -> int:
        """Someone asked this supervisor to stop (a signal): the run's processes are told to stop too."""
        from schemas import Stop

        self._event("stop", reason)
        try:
            await self._bus.publish(self._keys.stop, Stop(reason=reason))
        except Exception:
            pass
        return 143 if reason == "SIGTERM" else 130

    async def _handle_exits(self, running: bool) -> None:
        """Every child (but the sim) that ended since the last pass: restart it, fail the run, or let it be."""
        from schemas import Stop

        for child in self.children.values():
            if child.spec.role == "sim" or child.alive() or child.pid in child.reaped:
                continue
            child.reaped.add(child.pid)
            code = child.proc.returncode
            child.exit_codes.append(code)
            planned = child.pid in child.planned
            verdict = exit_verdict(child.spec.role, child.spec.restart, code, running=running, planned=planned,
                                   budget_left=planned or child.restart_allowed(time.monotonic()))
            if verdict is Exit.FAILED_BEFORE_START:
                raise StartError(f"{child.spec.name} exited with status {code} before the run started:\n"
                                 f"{child.log_tail()}")
            if verdict in (Exit.RECORD_FAILED, Exit.AIR_FAILED):
                why = ("the run record cannot be written" if verdict is Exit.RECORD_FAILED else
                       "the air process ended mid-run: its queues cannot be rebuilt")
                self._event("record" if verdict is Exit.RECORD_FAILED else "air", why)
                try:
                    await self._bus.publish(self._keys.stop, Stop(reason=why))
                except Exception:
                    pass
                raise RunFailed(f"{last_error(child) if verdict is Exit.RECORD_FAILED else why} (status {code}); "
                                "the run was stopped")
            if verdict is Exit.RESTART:
                old_pid = child.pid
                cold = child.planned.pop(old_pid, False)
                if not planned:
                    child.failures.append(time.monotonic())
                child.restarts += 1
                # A restart is a fresh interpreter (exec), as a rebooted robot's program is: its seconds of
                # start-up let the monitor take in its predecessor's last states, which it restores from.
                child.start(("--cold-restart",) if cold else (), on_exit=self._notify)
                self._event("restart", f"{child.spec.name} exited with {code}; restarted as pid {child.pid}")
                await self._publish_event("agent.restart", agent=child.spec.agent, exit_code=code, old_pid=old_pid,
                                          pid=child.pid, restarts=child.restarts, planned=planned, cold=cold)
            elif verdict is Exit.MONITOR_FAILED:
                raise StartError(f"monitor exited with status {code}:\n{child.log_tail()}")

    async def _end_of_run(self) -> int:
        """The sim has ended the run: wait for the monitor to finish the record, then check the record against the
        sim's own account. 0 only when the steps, the rows and the summary agree; the final line shows the
        record's numbers (never a stale live value)."""
        from services.monitor.recorder import check_record

        monitors = [c for c in self.children.values() if c.spec.role == "monitor"]
        if self.end_grace > 0:
            self.line.say(self.progress, f"run ended; the monitor serves its last values for {self.end_grace:.0f} s")
        deadline = time.monotonic() + MONITOR_END_TIMEOUT + self.end_grace
        while time.monotonic() < deadline and any(c.alive() for c in monitors):
            if self.stop_requested:  # Ctrl-C while the monitor finishes (or serves its grace): stop now
                self._event("stop", self.stop_requested)
                return 143 if self.stop_requested == "SIGTERM" else 130
            await self._nap(min(SHOW_EVERY, deadline - time.monotonic()))
        failure = monitor_failure(monitors)
        if failure is not None:
            raise RunFailed(failure)
        self.check = check = check_record(self.config.record_dir, self.config.steps)
        take_record_numbers(self.progress, check)
        self.line.show(self.progress)
        code, self.outcome = outcome(check)
        return code

    async def _publish_event(self, kind: str, *, at_tick: int | None = None, **details) -> None:
        """Supervisor events (crashes, restarts) go into the run record through the monitor, with their tick and sim
        time: a crash at the tick it was due (the live tick may be a little further on), a restart at the live tick."""
        from schemas import Event

        t = max(self.progress.t, 0) if at_tick is None else at_tick
        try:
            await self._bus.publish(self._keys.event("supervisor"), Event(
                kind=kind, source="supervisor", t=t, sim_time=t * self.config.dt, wall_time=time.time(),
                details=details))
        except Exception:
            log.warning("could not publish %s event", kind, exc_info=True)

    async def shutdown(self) -> None:
        """Every child gone within SHUTDOWN_BOUND (services/supervisor/children.py), then the fork server."""
        await end_children(list(self.children.values()), self._nap, self._event)
        if self.server is not None:
            self.server.close()
