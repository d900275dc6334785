"""Process faults: the crash planner's schedule (at a tick, every k ticks, a seeded random agent) and the
faulter's signals on a real child process (SIGSTOP/SIGCONT, SIGKILL), by pid."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

from schemas import FaultCommand, FaultSpec
from schemas.faults import Crash
from services.bus import LocalNetwork
from services.faults.controller import FaultController
from services.faults.crash import CrashPlanner, ProcessFaulter

from _procs import until


def test_planner_at_tick_every_k_and_seeded_random_agent() -> None:
    plan = CrashPlanner(n_agents=8, seed=3)
    assert plan.add(FaultSpec(id="a", crash=Crash(agent=2, at_tick=5))) is None
    assert plan.add(FaultSpec(id="b", crash=Crash(agent=1, every=100))) is None
    assert plan.add(FaultSpec(id="c", crash=Crash(every=50, signal="pause", pause_for=2.0))) is None
    assert plan.add(FaultSpec(crash=Crash(agent=8, at_tick=1))).startswith("crash.agent: agent 8 is not in this run")
    hits = {t: [(a.fault_id, a.agent) for a in plan.due(t)] for t in range(0, 301) if plan.due(t)}
    assert sorted(hits) == [5, 50, 100, 150, 200, 250, 300]
    assert hits[5] == [("a", 2)] and [f for f, _ in hits[100]] == ["b", "c"] and hits[100][0] == ("b", 1)
    randoms = [hits[t][-1][1] for t in (50, 100, 150, 200, 250, 300)]
    assert len(set(randoms)) > 1 and all(0 <= a < 8 for a in randoms)
    again = CrashPlanner(n_agents=8, seed=3)
    again.add(FaultSpec(id="c", crash=Crash(every=50, signal="pause", pause_for=2.0)))
    assert [again.due(t)[0].agent for t in (50, 100, 150, 200, 250, 300)] == randoms  # same seed, same victims


def test_controller_routes_crash_specs_to_the_planner() -> None:
    plan = CrashPlanner(n_agents=4)
    ctl = FaultController(LocalNetwork().session("supervisor"), "cr", [], clock=lambda: 0.0, on_crash=plan.add)
    assert ctl.handle(FaultCommand(op="set", spec=FaultSpec(id="k", crash=Crash(agent=3, every=100)))).ok
    bad = ctl.handle(FaultCommand(op="set", spec=FaultSpec(crash=Crash(agent=9, at_tick=1))))
    assert not bad.ok and "agent 9" in bad.error
    assert [a.agent for a in plan.due(200)] == [3] and [e.kind for e in ctl.log] == ["fault.crash_planned"]


def test_a_crash_at_a_tick_already_reached_is_refused_naming_at_tick() -> None:
    """A crash that can no longer happen at its tick is refused, not listed as active and never carried out."""
    plan = CrashPlanner(n_agents=8)
    ctl = FaultController(LocalNetwork().session("supervisor"), "cr", [], clock=lambda: 0.0, on_crash=plan.add,
                          on_crash_reset=plan.reset)
    for t in range(0, 1531):
        plan.due(t)
    past = ctl.handle(FaultCommand(op="set", spec=FaultSpec(id="late", crash=Crash(agent=1, at_tick=1421))))
    assert not past.ok and past.error == ("crash.at_tick: tick 1421 has passed (the run is at tick 1530); "
                                          "give a later tick")
    assert past.active == [] and ctl.log == []
    now = ctl.handle(FaultCommand(op="set", spec=FaultSpec(id="soon", crash=Crash(agent=1, at_tick=1531))))
    assert now.ok and [s.id for s in now.active] == ["soon"]
    assert ctl.handle(FaultCommand(op="reset", fault_id="soon")).ok and plan.due(1531) == []
    # a one-shot crash carried out is spent (the supervisor then retires it); a repeating one is not
    plan.add(FaultSpec(id="once", crash=Crash(agent=2, at_tick=1540)))
    plan.add(FaultSpec(id="again", crash=Crash(agent=3, every=10)))
    assert plan.spent() == [] and [a.fault_id for a in plan.due(1540)] == ["once", "again"]
    assert plan.spent() == ["once"]


def _state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0]


async def test_faulter_pauses_resumes_and_kills_a_real_process() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(20)"])
    try:
        plan = CrashPlanner(n_agents=2)
        plan.add(FaultSpec(id="p", crash=Crash(agent=1, at_tick=1, signal="pause", pause_for=0.2)))
        plan.add(FaultSpec(id="k", crash=Crash(agent=1, at_tick=3)))
        plan.add(FaultSpec(id="gone", crash=Crash(agent=0, at_tick=3)))
        faulter = ProcessFaulter(lambda agent: child.pid if agent == 1 else None)
        [pause] = plan.due(1)
        assert faulter.execute(pause) == child.pid
        await until(lambda: _state(child.pid) == "T", what="the child stopped")
        await until(lambda: _state(child.pid) in ("S", "R"), what="the child continued after pause_for")
        kill, absent = plan.due(3)
        assert faulter.execute(kill) == child.pid and faulter.execute(absent) is None
        assert child.wait(timeout=5) == -signal.SIGKILL
    finally:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
            child.wait(timeout=5)
