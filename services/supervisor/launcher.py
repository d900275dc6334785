"""The local supervisor of ``morph-sim up``: starts the process graph, watches it, restarts agents, ends it.

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

import asyncio
import logging
import os
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from services.runconfig import RunConfig
from services.supervisor.forkserver import ForkedProcess, ForkServer
from services.supervisor.graph import CHILD_ENV, ProcessSpec, child_environment, process_graph
from services.supervisor.parent import signal_on_parent_death

log = logging.getLogger("morph_sim.supervisor")

TERM_GRACE = 3.0  # seconds between SIGTERM and SIGKILL
SHUTDOWN_BOUND = 5.0
# A crash loop is a failure, not something to retry forever: at most MAX_RESTARTS unplanned restarts of one child
# within RESTART_WINDOW wall seconds. Kills the supervisor carries out itself (crash faults) do not count, so
# "kill agent k every 100 ticks" runs for any number of steps.
MAX_RESTARTS = 5
RESTART_WINDOW = 60.0
MONITOR_END_TIMEOUT = 30.0  # seconds the monitor may take after the sim's end to finish the record
STOPPED_FROM_OUTSIDE = 3  # exit status of `up` when someone else's stop ended the run before its steps
RECORD_FAILED = 74  # a monitor's exit status when the record cannot be written (services/monitor/command.py)
SHOW_EVERY = 0.25  # seconds between live lines; also the longest the watch loop sleeps without news


def _die_with_parent() -> None:  # runs in the child between fork and exec
    signal_on_parent_death(signal.SIGTERM)


class StartError(RuntimeError):
    """A process of the run could not start (message names it and shows its log tail)."""


class RunFailed(StartError):
    """The run ended but its record is not the truth (incomplete, or the monitor failed): the message says why."""


def _last_error(child: "Child") -> str:
    """The child's last error line (``morph-sim <cmd>: error: …``), else the last line of its log."""
    lines = [ln for ln in child.log_tail(40).splitlines() if ln.strip() and not ln.startswith("--- start")]
    errors = [f"{child.spec.role}: " + ln.split(": error: ", 1)[1] for ln in lines if ": error: " in ln]
    return (errors or lines or [f"{child.spec.name} left no log"])[-1].strip()


class RunStalled(StartError):
    """The run stopped advancing: no new tick for ``stall_timeout`` seconds although every phase has a deadline.

    A stall inside Zenoh — a router blocked on a full socket while forwarding (zenoh 1.10.2, lowlatency transport;
    cf. eclipse-zenoh/zenoh#1876; we met it when the monitor handled samples on its receive thread, docs/services.md)
    — is out of reach of every phase deadline of ours. A user gets a clear failure and a record up to the stall
    instead of a silent hang."""


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
                    start_new_session=True, preexec_fn=_die_with_parent, close_fds=True)
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


@dataclass
class Progress:
    """What the live line shows; fed from the run's metric streams :attr:`STREAMS` (and the tick from every Tick)."""

    STREAMS = ("deliveries_total", "links")

    t: int = -1
    deliveries: float = 0.0
    links: float = 0.0
    ticks_per_s: float = 0.0
    started: float | None = None
    first_t: int = 0
    finished: bool = False

    def update(self, name: str, t: int, value: float) -> None:
        now = time.monotonic()
        if self.started is None:
            self.started, self.first_t = now, t
        if t > self.t:
            self.t = t
            if now > self.started:
                self.ticks_per_s = (t - self.first_t) / (now - self.started)
        if name == "deliveries_total":
            self.deliveries = value
        elif name == "links":
            self.links = value


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
            self._check_port_free()  # StartError naming the port, before anything is written or started
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
        self.ready_timeout = config.ready_timeout if ready_timeout is None else ready_timeout
        # a tick may legitimately take a phase deadline per phase (or a paced period): give three times that
        self.stall_timeout = (max(30.0, 3 * 2 * config.phase_timeout, 3 * config.period) if stall_timeout is None
                              else stall_timeout)
        self.stop_requested: str | None = None
        self.outcome = "interrupted"  # how the run ended, for the final line
        self.check = None  # the record's check at the end of the run (services.monitor.recorder.RecordCheck)
        self.events: list[tuple[float, str, str]] = []
        # Crash faults: specs from the schedule file or `morph-sim faults set` land in the planner (the
        # ctl/faults controller's on_crash hook); each tick the due actions are carried out on the agents' pids.
        from services.faults.crash import CrashPlanner, ProcessFaulter

        self.planner = CrashPlanner(config.n_agents, config.seed)
        # pause_for is in sim seconds: paced runs map it through the period, lock-step runs at 1 wall s per sim s
        self.faulter = ProcessFaulter(self._agent_pid,
                                      time_scale=config.period / config.dt if config.mode == "paced" else 1.0)
        self._crash_t = -1  # last tick whose crash actions were carried out
        self._controller = None  # the supervisor's ctl/faults controller (crash faults), once the watch starts
        self._bus = None
        self._keys = None
        self._tasks: set[asyncio.Task] = set()
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

    def _start_fork_server(self) -> ForkServer:
        """The run's processes start by fork from one interpreter that imported them once (fresh interpreters
        spend ~0.5 CPU-s each on imports). Its environment holds BLAS to one thread, as every child's does, so it
        stays single-threaded and safe to fork."""
        log = self.config.record_dir / "logs" / "fork-server.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        try:
            return ForkServer(child_environment(CHILD_ENV), log, ready_timeout=self.ready_timeout, preexec_fn=_die_with_parent,
                              on_exit=self._notify)
        except RuntimeError as exc:
            tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:]) if log.exists() else ""
            raise StartError(f"{exc}:\n{tail}") from None

    def _agent_pid(self, agent: int) -> int | None:
        child = self.children.get(f"agent-{agent}")
        return child.pid if child is not None and child.alive() else None

    def _crashes(self, upto: int) -> None:
        """Carry out the crash actions of every tick up to ``upto`` not yet handled, in tick order. Called as each
        Tick arrives (the kill lands in the tick it was due, not a polling period later) and from the watch loop."""
        controller = self._controller
        while controller is not None and self._crash_t < upto:
            self._crash_t += 1
            t = self._crash_t
            controller.advance(t * self.config.dt)  # scheduled commands of this tick (crash specs reach the planner)
            for action in self.planner.due(t):
                child = self.children.get(f"agent-{action.agent}")
                pid = self.faulter.execute(action)
                if pid is not None and child is not None and action.signal == "kill":
                    child.planned[pid] = action.cold_restart or self.config.cold_restart
                self._event("crash", f"{action.signal} agent {action.agent} (pid {pid}) at tick {t}")
                self._later(self._publish_event(self._bus, self._keys, "agent.crash", agent=action.agent,
                                                signal=action.signal, pid=pid, fault_id=action.fault_id, tick=t,
                                                at_tick=t))
            for fault_id in self.planner.spent():  # one-shot crashes done: `faults list` no longer shows them
                self.planner.reset(fault_id)
                controller.retire_crash(fault_id)

    def _later(self, coro) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)  # a reference until done (the loop keeps only weak ones)
        task.add_done_callback(self._tasks.discard)

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

    async def _tcp_reachable(self, timeout: float) -> bool:
        proto, _, addr = self.endpoint.partition("/")
        host, _, port = addr.rpartition(":")
        if proto != "tcp" or not port.isdigit():
            return True  # only TCP endpoints are probed; others are left to Zenoh
        deadline = time.monotonic() + timeout
        while True:
            try:
                _, writer = await asyncio.wait_for(asyncio.open_connection(host.strip("[]"), int(port)), 0.5)
                writer.close()
                return True
            except (OSError, asyncio.TimeoutError):
                if time.monotonic() >= deadline:
                    return False
                await asyncio.sleep(0.1)

    async def _run(self) -> int:
        if self.external and not await self._tcp_reachable(3.0):
            raise StartError(f"nothing listens on the Zenoh endpoint {self.endpoint} (--endpoint): start the router "
                             "first, or leave --endpoint out to host the endpoint in the sim")
        sim = self.children["sim"]
        self.server = self._start_fork_server()
        sim.start(server=self.server)
        self._event("start", f"sim pid {sim.pid} ({'connects to' if self.external else 'listens on'} {self.endpoint})")
        # The sim must have opened its endpoint before anyone connects; a short wait for the port is enough.
        await self._wait_endpoint(sim)
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

    def _check_port_free(self) -> None:
        """The endpoint's port must be ours to listen on: if another program holds it, the wait for the sim's port
        below would connect to that program and the run would fail later with a misleading reason."""
        import socket

        proto, _, addr = self.endpoint.partition("/")
        host, _, port = addr.rpartition(":")
        if proto != "tcp" or not port.isdigit():
            return
        family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((host.strip("[]"), int(port)))
            except OSError as exc:
                raise StartError(f"port {port} of {self.endpoint} (--listen) is not free: {exc.strerror}; another "
                                 "program holds it; choose another port or leave --listen out") from None

    async def _wait_endpoint(self, sim: Child) -> None:
        if self.external:
            return
        host, _, port = self.endpoint.partition("/")[2].rpartition(":")
        deadline = time.monotonic() + self.ready_timeout
        while time.monotonic() < deadline:
            if not sim.alive():
                raise StartError(f"sim exited with status {sim.proc.returncode} before opening {self.endpoint}:\n"
                                 f"{sim.log_tail()}")
            try:
                reader, writer = await asyncio.wait_for(asyncio.open_connection(host, int(port)), 0.5)
                writer.close()
                try:
                    await writer.wait_closed()
                except Exception:
                    pass
                return
            except (OSError, asyncio.TimeoutError):
                await asyncio.sleep(0.05)
            if self.stop_requested:
                return
        raise StartError(f"sim did not open {self.endpoint} within {self.ready_timeout:.0f} s:\n{sim.log_tail()}")

    async def _open_bus(self):
        from services.process import open_bus

        operator = None if self.credentials is None else str(self.credentials.operator)
        return await open_bus("supervisor", connect=self.endpoint, config_file=operator)

    async def _watch(self, bus) -> int:
        from schemas import MetricSample, Stop
        from schemas.keys import RunKeys
        from schemas.tick import tick_number

        keys = RunKeys(self.config.run_id)

        def on_metric(sample) -> None:
            try:
                msg = sample.decode(MetricSample)
            except ValueError:
                return
            if sample.sender != "monitor" or not 0 <= msg.t <= self.config.steps:
                return  # progress drives crash faults and the stall watchdog: only the monitor's, within the run
            if msg.value is not None:
                self.progress.update(msg.name, msg.t, msg.value)

        for name in Progress.STREAMS:  # only what the line shows: a run has many more streams, each a message
            await bus.subscribe(keys.metric(name), on_metric)

        from services.tickorder import TickOrder

        ticks = TickOrder(self.config.steps)  # a forged tick must not fire the crash faults of the ticks it skips

        def on_tick(sample) -> None:  # every tick (the metric stream is decimated): crash faults hit their tick
            try:
                if sample.sender != "sim":
                    return
                t = tick_number(sample.payload)  # only the number (the monitor and the agents validate the rest)
                if not ticks.admit(t):
                    return
            except ValueError:
                return
            if self.progress.t < t < self.config.steps:  # (a final Tick t = steps closes the run)
                self.progress.update("tick", t, float("nan"))
                if self._controller is not None:
                    self._controller.publish_held()  # the run has started: the monitor listens
                    self._crashes(t)

        self._bus, self._keys = bus, keys
        await bus.subscribe(keys.tick, on_tick)
        from services.faults.controller import FaultController

        # No fault layers here: the supervisor carries out crash faults, and is the only process that judges them
        # (it records fault.crash_planned when it accepts one, agent.crash when it happens).
        self._controller = FaultController(
            bus, self.config.run_id, [], clock=lambda: max(self.progress.t, 0) * self.config.dt, dt=self.config.dt,
            on_crash=self.planner.add, on_crash_reset=self.planner.reset, schedule=self.schedule,
            events=True, hold_events=True, fleet=self.config.n_agents)
        await self._controller.start()
        ready_deadline = time.monotonic() + self.ready_timeout
        last_shown = 0.0
        last_tick, last_tick_at = self.progress.t, time.monotonic()
        while True:
            if self.stop_requested:
                self._event("stop", self.stop_requested)
                try:
                    await bus.publish(keys.stop, Stop(reason=self.stop_requested))
                except Exception:
                    pass
                return 143 if self.stop_requested == "SIGTERM" else 130
            sim = self.children["sim"]
            if not sim.alive():
                code = sim.proc.returncode
                if code != 0:
                    raise StartError(f"sim exited with status {code}:\n{sim.log_tail()}")
                return await self._end_of_run()
            running = self.progress.t >= 0
            if running:
                self._crashes(self.progress.t)
            for child in self.children.values():
                if child.spec.role == "sim" or child.alive() or child.pid in child.reaped:
                    continue
                child.reaped.add(child.pid)
                code = child.proc.returncode
                child.exit_codes.append(code)
                if not running and code != 0:
                    raise StartError(f"{child.spec.name} exited with status {code} before the run started:\n"
                                     f"{child.log_tail()}")
                if child.spec.role == "monitor" and code == RECORD_FAILED:
                    self._event("record", "the monitor cannot write the run record")
                    try:
                        await bus.publish(keys.stop, Stop(reason="the run record cannot be written"))
                    except Exception:
                        pass
                    raise RunFailed(f"{_last_error(child)}; the run was stopped")
                planned = child.pid in child.planned
                if child.spec.restart == "on-failure" and code != 0 and (
                        planned or child.restart_allowed(time.monotonic())):
                    old_pid = child.pid
                    cold = child.planned.pop(old_pid, False)
                    if not planned:
                        child.failures.append(time.monotonic())
                    child.restarts += 1
                    # A restart is a fresh interpreter (exec), as a rebooted robot's program is: its seconds of
                    # start-up let the monitor take in its predecessor's last states, which it restores from.
                    child.start(("--cold-restart",) if cold else (), on_exit=self._notify)
                    self._event("restart", f"{child.spec.name} exited with {code}; restarted as pid {child.pid}")
                    await self._publish_event(bus, keys, "agent.restart", agent=child.spec.agent, exit_code=code,
                                              old_pid=old_pid, pid=child.pid, restarts=child.restarts,
                                              planned=planned, cold=cold)
                elif child.spec.role == "monitor" and code != 0:
                    raise StartError(f"monitor exited with status {code}:\n{child.log_tail()}")
                # otherwise it finished for good (after the run's stop): nothing to do
            if self.progress.t != last_tick:
                last_tick, last_tick_at = self.progress.t, time.monotonic()
            elif (running and self.progress.t < self.config.steps - 1
                  and time.monotonic() - last_tick_at > self.stall_timeout):  # (after the last tick: the sim ends)
                self._event("stalled", f"no tick after tick {last_tick} for {self.stall_timeout:.0f} s")
                raise RunStalled(f"the run stalled: no tick after tick {last_tick} for {self.stall_timeout:.0f} s "
                                 f"(phase deadlines included); the record holds the ticks up to the stall; sim log:\n"
                                 f"{sim.log_tail()}")
            if not running and time.monotonic() > ready_deadline:
                raise StartError(f"the run did not start within {self.ready_timeout:.0f} s; sim log:\n"
                                 f"{sim.log_tail()}")
            now = time.monotonic()
            if now - last_shown >= SHOW_EVERY:
                last_shown = now
                self._show()
            await self._nap(max(0.01, last_shown + SHOW_EVERY - time.monotonic()))

    async def _end_of_run(self) -> int:
        """The sim has ended the run: wait for the monitor to finish the record, then check the record against the
        sim's own account. 0 only when the steps, the rows and the summary agree; the final line shows the
        record's numbers (never a stale live value)."""
        from services.monitor.recorder import check_record

        monitors = [c for c in self.children.values() if c.spec.role == "monitor"]
        if self.end_grace > 0 and self.on_progress is not None:
            self.on_progress(self.progress, f"run ended; the monitor serves its last values for {self.end_grace:.0f} s")
        deadline = time.monotonic() + MONITOR_END_TIMEOUT + self.end_grace
        while time.monotonic() < deadline and any(c.alive() for c in monitors):
            if self.stop_requested:  # Ctrl-C while the monitor finishes (or serves its grace): stop now
                self._event("stop", self.stop_requested)
                return 143 if self.stop_requested == "SIGTERM" else 130
            await self._nap(min(SHOW_EVERY, deadline - time.monotonic()))
        for monitor in monitors:
            if monitor.alive():
                raise RunFailed(f"the monitor did not finish the run record within {MONITOR_END_TIMEOUT:.0f} s of "
                                f"the run's end; the record is incomplete")
            code = monitor.proc.returncode
            if code != 0:
                raise RunFailed(f"the monitor failed (status {code}): {_last_error(monitor)}; the record is "
                                "incomplete")
        self.check = check = check_record(self.config.record_dir, self.config.steps)
        p = self.progress
        p.finished = True
        if check.rows:
            p.t = check.rows - 1 if not check.gaps else max(p.t, check.rows - 1)
        if check.deliveries is not None:
            p.deliveries = float(check.deliveries)
        if check.final_links is not None:
            p.links = float(check.final_links)
        self._show(force=True)
        if check.problems:
            raise RunFailed("the run record is incomplete: " + "; ".join(check.problems))
        if check.stopped_early is not None:
            self.outcome = f"stopped from outside at tick {check.steps} ({check.stopped_early})"
            return STOPPED_FROM_OUTSIDE
        self.outcome = "completed"
        return 0

    async def _publish_event(self, bus, keys, kind: str, *, at_tick: int | None = None, **details) -> None:
        """Supervisor events (crashes, restarts) go into the run record through the monitor, with their tick and sim
        time: a crash at the tick it was due (the live tick may be a little further on), a restart at the live tick."""
        from schemas import Event

        t = max(self.progress.t, 0) if at_tick is None else at_tick
        try:
            await bus.publish(keys.event("supervisor"), Event(
                kind=kind, source="supervisor", t=t, sim_time=t * self.config.dt, wall_time=time.time(),
                details=details))
        except Exception:
            log.warning("could not publish %s event", kind, exc_info=True)

    def _show(self, force: bool = False) -> None:
        if self.on_progress is None:
            return
        p = self.progress
        if p.t < 0:
            line = f"waiting for {self.config.n_agents} agents to join {self.endpoint} …"
        else:
            line = (f"tick {p.t + 1}/{self.config.steps}  deliveries {p.deliveries:.0f}  links {p.links:.0f}  "
                    f"{p.ticks_per_s:.0f} ticks/s")
        self.on_progress(p, line)

    async def _wait_exit(self, children: list[Child], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(c.alive() for c in children):
            await self._nap(min(SHOW_EVERY, deadline - time.monotonic()))

    async def shutdown(self) -> None:
        """Every child gone within SHUTDOWN_BOUND: a moment to exit on its own, SIGTERM, then SIGKILL."""
        children = list(self.children.values())
        await self._wait_exit(children, 1.0)
        for child in children:
            child.signal_group(signal.SIGTERM)
        await self._wait_exit(children, TERM_GRACE)
        for child in children:
            if child.alive():
                self._event("kill", f"{child.spec.name} pid {child.pid} ignored SIGTERM")
                child.signal_group(signal.SIGKILL)
        for child in children:
            if child.proc is not None:
                try:
                    child.proc.wait(timeout=0.5)
                except subprocess.TimeoutExpired:
                    pass
        if self.server is not None:
            self.server.close()
