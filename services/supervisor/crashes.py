"""Crash faults, carried out by the supervisor: kill or pause an agent's process at a tick.

Crash specs from the schedule file or ``morph-sim faults set`` reach the :class:`~services.faults.crash.CrashPlanner`
through the supervisor's ``ctl/faults`` controller (its ``on_crash`` hook); each tick the due actions are carried out
on the agents' pids. What is pure: which ticks are still to be handled (:class:`TickCursor`), which process an action
hits (:func:`target`) and whether its end is a planned restart, cold or warm (:func:`planned_restart`); the planner
itself says which actions are due when. :class:`CrashExecutor` is the driver.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine, Iterator

from services.faults.crash import CrashAction, CrashPlanner, ProcessFaulter
from services.runconfig import RunConfig


class TickCursor:
    """The ticks whose crash actions are still to be carried out, in order, each once."""

    def __init__(self) -> None:
        self.done = -1  # last tick handled

    def pending(self, upto: int) -> Iterator[int]:
        """Every tick after the last handled up to ``upto``; a tick counts as handled as soon as it is yielded, so
        one whose actions failed is not carried out twice."""
        while self.done < upto:
            self.done += 1
            yield self.done


def target(agent: int) -> str:
    """The process a crash action on ``agent`` hits: the agent's, by its name in the process graph."""
    return f"agent-{agent}"


def planned_restart(action: CrashAction, pid: int | None, cold_by_default: bool) -> bool | None:
    """For a kill that hit process ``pid``: restart it cold? (the spec's ``cold_restart``, else the run's). None when
    no restart follows from the action: a pause, or no process was hit."""
    if pid is None or action.signal != "kill":
        return None
    return action.cold_restart or cold_by_default


class CrashExecutor:
    """Carries the crash faults of a run out on its agents' processes.

    ``pid_of(process)`` is the named process's live pid (None: not running); ``mark(process, pid, cold)`` tells
    the process keeper that ``pid``'s end is a planned restart; ``note(kind, what)`` keeps the supervisor's
    account; ``publish_event(kind, at_tick=…, **details)`` is a coroutine that puts an event in the run record."""

    def __init__(self, config: RunConfig, schedule, *, pid_of: Callable[[str], int | None],
                 mark: Callable[[str, int, bool], None], note: Callable[[str, str], None],
                 publish_event: Callable[..., Coroutine]):
        self.config = config
        self.schedule = schedule
        self.mark, self.note, self.publish_event = mark, note, publish_event
        self.planner = CrashPlanner(config.n_agents, config.seed)
        # pause_for is in sim seconds: paced runs map it through the period, lock-step runs at 1 wall s per sim s
        self.faulter = ProcessFaulter(lambda agent: pid_of(target(agent)),
                                      time_scale=config.period / config.dt if config.mode == "paced" else 1.0)
        self.ticks = TickCursor()
        self.controller = None  # the supervisor's ctl/faults controller, once started
        self._tasks: set[asyncio.Task] = set()

    async def start(self, bus, clock: Callable[[], float]) -> None:
        """Serve ``ctl/faults`` for crash faults; ``clock()`` is the run's sim time."""
        from services.faults.controller import FaultController

        # No fault layers here: the supervisor carries out crash faults, and is the only process that judges them
        # (it records fault.crash_planned when it accepts one, agent.crash when it happens).
        self.controller = FaultController(
            bus, self.config.run_id, [], clock=clock, dt=self.config.dt,
            on_crash=self.planner.add, on_crash_reset=self.planner.reset, schedule=self.schedule,
            events=True, hold_events=True, fleet=self.config.n_agents)
        await self.controller.start()

    def on_tick(self, t: int) -> None:
        """A new tick: the kill lands in the tick it was due, not a polling period later."""
        if self.controller is not None:
            self.controller.publish_held()  # the run has started: the monitor listens
            self.catch_up(t)

    def catch_up(self, upto: int) -> None:
        """Carry out the crash actions of every tick up to ``upto`` not yet handled, in tick order. Called as each
        Tick arrives and from the supervisor's loop."""
        controller = self.controller
        if controller is None:
            return
        for t in self.ticks.pending(upto):
            controller.advance(t * self.config.dt)  # scheduled commands of this tick (crash specs reach the planner)
            for action in self.planner.due(t):
                pid = self.faulter.execute(action)
                cold = planned_restart(action, pid, self.config.cold_restart)
                if cold is not None:
                    self.mark(target(action.agent), pid, cold)
                self.note("crash", f"{action.signal} agent {action.agent} (pid {pid}) at tick {t}")
                self._later(self.publish_event("agent.crash", agent=action.agent, signal=action.signal, pid=pid,
                                               fault_id=action.fault_id, tick=t, at_tick=t))
            for fault_id in self.planner.spent():  # one-shot crashes done: `faults list` no longer shows them
                self.planner.reset(fault_id)
                controller.retire_crash(fault_id)

    def _later(self, coro) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)  # a reference until done (the loop keeps only weak ones)
        task.add_done_callback(self._tasks.discard)
