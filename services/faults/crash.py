"""Process faults: kill an agent (SIGKILL) or pause it (SIGSTOP, SIGCONT after ``pause_for``) at a tick,
every k ticks, or a seeded random agent — the supervisor's half of a ``crash`` fault spec.

* :class:`CrashPlanner` (pure): which crash actions are due at tick ``t``. A spec without ``agent`` picks a random
  robot from a stream seeded by (run seed, fault id, tick), so the same seed kills the same agents.
* :class:`ProcessFaulter` (thin shell): carries an action out on a pid the supervisor knows, by pid only. Restarting
  the killed agent is the supervisor's existing on-failure restart; the restarted agent rejoins through liveliness and
  restores its plasticity state from the monitor's ``state/agent/<id>`` queryable, or starts cold when the spec says
  ``cold_restart`` (the supervisor passes that on to the new process).

Plug into :class:`FaultController` with ``on_crash=planner.add``.
"""

from __future__ import annotations

import asyncio
import os
import random
import signal
from collections.abc import Callable
from dataclasses import dataclass

from schemas.faults import FaultSpec


@dataclass(frozen=True)
class CrashAction:
    t: int
    agent: int
    signal: str  # "kill" | "pause"
    pause_for: float | None
    cold_restart: bool
    fault_id: str


class CrashPlanner:
    def __init__(self, n_agents: int, seed: int = 0):
        if n_agents < 1:
            raise ValueError(f"n_agents: must be >= 1, got {n_agents}")
        self.n_agents = n_agents
        self.seed = seed
        self._specs: list[tuple[str, FaultSpec]] = []
        # the last tick whose actions were asked for (due): a crash at or before it can no longer happen at its tick
        self.reached = -1

    def add(self, spec: FaultSpec) -> str | None:
        """Accept a crash spec (the controller's ``on_crash`` hook); returns an error message naming the field, or
        None. A crash at a tick already reached is refused: accepting it would promise a crash that never comes."""
        crash = spec.crash
        if crash is None:
            return "crash: not a crash spec"
        if crash.agent is not None and not 0 <= crash.agent < self.n_agents:
            return f"crash.agent: agent {crash.agent} is not in this run (robot ids 0..{self.n_agents - 1})"
        if crash.at_tick is not None and crash.at_tick <= self.reached:
            return (f"crash.at_tick: tick {crash.at_tick} has passed (the run is at tick {self.reached}); "
                    f"give a later tick")
        self._specs.append((spec.id or f"crash-{len(self._specs) + 1}", spec))
        return None

    def spent(self) -> list[str]:
        """Ids of one-shot crash specs whose tick has been reached: carried out, no longer active."""
        return [f for f, spec in self._specs
                if spec.crash is not None and spec.crash.every is None and spec.crash.at_tick is not None
                and spec.crash.at_tick <= self.reached]

    def reset(self, fault_id: str | None = None) -> None:
        """Forget the crash spec ``fault_id``, or every one."""
        self._specs = [] if fault_id is None else [(f, s) for f, s in self._specs if f != fault_id]

    def due(self, t: int) -> list[CrashAction]:
        """Actions at tick ``t`` in the order the specs were added."""
        self.reached = max(self.reached, t)
        out = []
        for fault_id, spec in self._specs:
            c = spec.crash
            assert c is not None
            start = c.at_tick if c.at_tick is not None else (c.every or 0)
            if t < start:
                continue
            if t != start and (c.every is None or (t - start) % c.every):
                continue
            agent = c.agent
            if agent is None:
                seed = spec.seed if spec.seed is not None else self.seed
                agent = random.Random(f"{seed}|crash|{fault_id}|{t}").randrange(self.n_agents)
            out.append(CrashAction(t, agent, c.signal, c.pause_for, c.cold_restart, fault_id))
        return out


class ProcessFaulter:
    """Sends the signals of crash actions to the pids ``pid_of(agent)`` returns (None: the agent is not running)."""

    def __init__(self, pid_of: Callable[[int], int | None], *, time_scale: float = 1.0):
        self.pid_of = pid_of
        self.time_scale = time_scale  # wall seconds per sim second for pause_for (paced runs: period / dt)
        self.done: list[tuple[CrashAction, int | None]] = []

    def execute(self, action: CrashAction) -> int | None:
        """Carry ``action`` out; returns the pid signalled, or None if the agent had no process."""
        pid = self.pid_of(action.agent)
        if pid is None:
            self.done.append((action, None))
            return None
        try:
            if action.signal == "kill":
                os.kill(pid, signal.SIGKILL)
            else:
                os.kill(pid, signal.SIGSTOP)
                loop = asyncio.get_running_loop()
                loop.call_later((action.pause_for or 0.0) * self.time_scale, _resume, pid)
        except ProcessLookupError:
            pid = None
        self.done.append((action, pid))
        return pid


def _resume(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGCONT)
    except ProcessLookupError:
        pass
