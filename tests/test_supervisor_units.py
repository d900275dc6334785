"""The supervisor's decisions as pure code: what moves the run's clock, the live line, the stall watchdog, what a
child's end means, which ticks and processes crash faults hit, and the verdict of the record check. No process, no
bus: the drivers around them are covered by the `up` tests."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from types import SimpleNamespace

import pytest

from schemas.faults import Crash, FaultSpec
from services.faults.crash import CrashAction
from services.runconfig import RunConfig
from services.supervisor.children import RECORD_FAILED, Child, Exit, exit_verdict
from services.supervisor.crashes import CrashExecutor, TickCursor, planned_restart, target
from services.supervisor.errors import RunFailed
from services.supervisor.graph import ProcessSpec
from services.supervisor.liveline import SHOW_EVERY, LiveLine, live_line
from services.supervisor.observer import Progress, TickGate, counts_metric
from services.supervisor.readiness import tcp_address
from services.supervisor.record import STOPPED_FROM_OUTSIDE, monitor_failure, outcome, take_record_numbers
from services.supervisor.watchdog import StallWatch, default_stall_timeout


# -- the bus observer ----------------------------------------------------------------------------------------------
def test_progress_keeps_the_highest_tick_its_rate_and_the_streams_it_shows():
    p = Progress()
    p.update("tick", 10, math.nan, now=100.0)  # the first sample starts the rate's clock
    assert (p.t, p.started, p.first_t, p.ticks_per_s) == (10, 100.0, 10, 0.0)
    p.update("deliveries_total", 30, 4.0, now=102.0)
    assert (p.t, p.ticks_per_s, p.deliveries) == (30, 10.0, 4.0)
    p.update("links", 20, 7.0, now=103.0)  # an older tick's sample: its value counts, the clock stays
    assert (p.t, p.ticks_per_s, p.links) == (30, 10.0, 7.0)
    p.update("unknown", 31, 99.0, now=102.0)  # a stream the line does not show changes nothing but the clock
    assert (p.t, p.deliveries, p.links) == (31, 4.0, 7.0)


def test_only_the_monitors_samples_within_the_run_count():
    assert counts_metric("monitor", 0, 100) and counts_metric("monitor", 100, 100)
    assert not counts_metric("agent-3", 5, 100)
    assert not counts_metric("monitor", -1, 100) and not counts_metric("monitor", 101, 100)


def test_the_tick_gate_takes_the_sims_ticks_in_order_before_the_final_one():
    gate = TickGate(steps=200)
    assert not gate.admit("agent-1", 0, -1)  # only the sim's
    assert gate.admit("sim", 0, -1) and gate.admit("sim", 1, 0)
    assert not gate.admit("sim", 1, 1)  # a duplicate
    assert not gate.admit("sim", 500, 1)  # outside the run
    assert not gate.admit("sim", 150, 1)  # a forged jump does not move the clock ...
    assert gate.admit("sim", 2, 1)  # ... and the real next tick still does
    assert not gate.admit("sim", 3, 5)  # not newer than the clock the metric streams moved
    for t in range(4, 200):
        gate.admit("sim", t, t - 1)
    assert not gate.admit("sim", 200, 199)  # the final Tick t = steps closes the run: not a tick of it


# -- the live line -------------------------------------------------------------------------------------------------
def test_the_live_line_before_and_during_the_run():
    where = dict(steps=100, n_agents=6, endpoint="tcp/127.0.0.1:7447")
    assert live_line(Progress(), **where) == "waiting for 6 agents to join tcp/127.0.0.1:7447 …"
    p = Progress(t=41, deliveries=12.4, links=30.0, ticks_per_s=55.6)
    assert live_line(p, **where) == "tick 42/100  deliveries 12  links 30  56 ticks/s"


def test_the_live_line_is_paced_and_goes_to_whoever_watches():
    shown = []
    line = LiveLine(lambda p, text: shown.append(text), steps=10, n_agents=2, endpoint="e")
    assert line.due(5.0) and not line.due(5.0 + SHOW_EVERY / 2) and line.due(5.0 + SHOW_EVERY)
    assert line.next_in(5.0 + SHOW_EVERY) == pytest.approx(SHOW_EVERY)
    assert line.next_in(100.0) == 0.01  # late: still a short nap
    line.show(Progress(t=3))
    line.say(Progress(), "run ended")
    assert shown == ["tick 4/10  deliveries 0  links 0  0 ticks/s", "run ended"]
    LiveLine(None, steps=10, n_agents=2, endpoint="e").show(Progress())  # nobody watches: nothing happens


# -- the stall watchdog --------------------------------------------------------------------------------------------
def test_a_run_stalls_when_its_clock_stops_for_longer_than_the_timeout():
    watch = StallWatch(steps=100, timeout=30.0, t=-1, now=0.0)
    assert not watch.check(-1, 1000.0)  # not started: the start deadline is another matter
    assert not watch.check(5, 1000.0)  # the clock moved: the wait starts again
    assert not watch.check(5, 1030.0)
    assert watch.check(5, 1030.5)
    assert watch.reason() == "no tick after tick 5 for 30 s"
    assert not watch.check(6, 2000.0) and not watch.check(6, 2030.0)


def test_after_the_last_tick_nothing_stalls_the_sim_ends_the_run():
    watch = StallWatch(steps=100, timeout=30.0, t=98, now=0.0)
    assert watch.check(98, 31.0)
    watch = StallWatch(steps=100, timeout=30.0, t=99, now=0.0)
    assert not watch.check(99, 1000.0)


def test_the_default_stall_timeout_covers_three_ticks_of_deadlines():
    assert default_stall_timeout(phase_timeout=1.0, period=0.1) == 30.0
    assert default_stall_timeout(phase_timeout=10.0, period=0.1) == 60.0
    assert default_stall_timeout(phase_timeout=1.0, period=20.0) == 60.0


# -- what a child's end means ----------------------------------------------------------------------------------------
def _verdict(role="agent", code=1, *, running=True, planned=False, budget_left=True):
    restart = "never" if role == "sim" else "on-failure"
    return exit_verdict(role, restart, code, running=running, planned=planned, budget_left=budget_left)


def test_what_a_childs_end_means():
    assert _verdict(code=1, running=False) is Exit.FAILED_BEFORE_START
    assert _verdict("monitor", code=RECORD_FAILED, running=False) is Exit.FAILED_BEFORE_START
    assert _verdict(code=0, running=False) is Exit.DONE
    assert _verdict("monitor", code=RECORD_FAILED) is Exit.RECORD_FAILED
    assert _verdict("agent", code=RECORD_FAILED) is Exit.RESTART  # the status means a lost record only from the monitor
    assert _verdict(code=-9) is Exit.RESTART
    assert _verdict(code=-9, budget_left=False) is Exit.DONE  # a crash loop runs out of restarts
    assert _verdict(code=-9, planned=True, budget_left=False) is Exit.RESTART  # the supervisor's own kills don't count
    assert _verdict(code=0) is Exit.DONE  # it finished after the run's stop
    assert _verdict("monitor", code=1) is Exit.RESTART
    assert _verdict("monitor", code=1, budget_left=False) is Exit.MONITOR_FAILED
    assert exit_verdict("agent", "never", 1, running=True, planned=False, budget_left=True) is Exit.DONE
    # the shared air is never restarted: its end mid-run stops the run; it leaves with 0 only after the run's end
    assert exit_verdict("air", "never", -9, running=True, planned=False, budget_left=True) is Exit.AIR_FAILED
    assert exit_verdict("air", "never", 0, running=True, planned=False, budget_left=True) is Exit.DONE


# -- crash faults ----------------------------------------------------------------------------------------------------
def test_each_tick_is_handled_once_in_order():
    ticks = TickCursor()
    assert list(ticks.pending(3)) == [0, 1, 2, 3]
    assert list(ticks.pending(3)) == [] and list(ticks.pending(1)) == []
    for t in ticks.pending(6):
        if t == 5:
            break  # a tick whose actions failed part way counts as handled
    assert list(ticks.pending(6)) == [6]


def test_which_process_a_crash_hits_and_whether_it_comes_back_cold():
    kill = CrashAction(t=7, agent=3, signal="kill", pause_for=None, cold_restart=False, fault_id="k")
    pause = CrashAction(t=7, agent=3, signal="pause", pause_for=2.0, cold_restart=True, fault_id="p")
    assert target(kill.agent) == "agent-3"
    assert planned_restart(kill, 1234, cold_by_default=False) is False
    assert planned_restart(kill, 1234, cold_by_default=True) is True
    assert planned_restart(CrashAction(7, 3, "kill", None, True, "c"), 1234, cold_by_default=False) is True
    assert planned_restart(kill, None, cold_by_default=True) is None  # no process was hit: nothing to restart
    assert planned_restart(pause, 1234, cold_by_default=True) is None  # a paused process comes back by itself


def test_the_executor_carries_out_each_due_crash_once_and_retires_one_shots(tmp_path: Path):
    notes, marks, events = [], [], []
    controller = SimpleNamespace(advanced=[], retired=[], held=0)
    controller.advance = controller.advanced.append
    controller.retire_crash = controller.retired.append
    controller.publish_held = lambda: setattr(controller, "held", controller.held + 1)

    async def publish_event(kind, **details):
        events.append((kind, details["agent"], details["at_tick"]))

    async def scenario():
        config = RunConfig(run_id="u", scale="tiny", steps=20, output_dir=str(tmp_path))
        crashes = CrashExecutor(config, None, pid_of=lambda name: None, mark=lambda *a: marks.append(a),
                                note=lambda kind, what: notes.append(what), publish_event=publish_event)
        crashes.on_tick(0)  # before the controller starts: nothing to do yet
        assert crashes.ticks.done == -1
        crashes.controller = controller
        assert crashes.planner.add(FaultSpec(id="once", crash=Crash(agent=1, at_tick=3))) is None
        assert crashes.planner.add(FaultSpec(id="often", crash=Crash(agent=0, every=4))) is None
        crashes.on_tick(5)
        crashes.catch_up(5)  # the loop's call after the tick's own: nothing twice
        crashes.catch_up(8)
        await asyncio.sleep(0)
        return config

    config = asyncio.run(scenario())
    assert controller.advanced == [t * config.dt for t in range(9)] and controller.held == 1
    assert notes == ["kill agent 1 (pid None) at tick 3", "kill agent 0 (pid None) at tick 4",
                     "kill agent 0 (pid None) at tick 8"]
    assert events == [("agent.crash", 1, 3), ("agent.crash", 0, 4), ("agent.crash", 0, 8)]
    assert controller.retired == ["once"] and marks == []  # no process was hit: no planned restart


# -- the record check ------------------------------------------------------------------------------------------------
def _check(**kw):
    base = dict(rows=50, gaps=[], deliveries=9, final_links=4, problems=[], stopped_early=None, steps=50)
    return SimpleNamespace(**{**base, **kw})


def test_the_final_numbers_are_the_records():
    p = Progress(t=47, deliveries=8.0, links=3.0)
    take_record_numbers(p, _check())
    assert (p.finished, p.t, p.deliveries, p.links) == (True, 49, 9.0, 4.0)
    p = Progress(t=47, deliveries=8.0, links=3.0)
    take_record_numbers(p, _check(rows=40, gaps=[(10, 20)], deliveries=None, final_links=None))
    assert (p.t, p.deliveries, p.links) == (47, 8.0, 3.0)  # a record with gaps: the live tick may be further on
    p = Progress(t=47)
    take_record_numbers(p, _check(rows=0))
    assert p.t == 47


def test_the_outcome_of_a_run_from_its_record():
    assert outcome(_check()) == (0, "completed")
    assert outcome(_check(stopped_early="operator", steps=30)) == (
        STOPPED_FROM_OUTSIDE, "stopped from outside at tick 30 (operator)")
    with pytest.raises(RunFailed, match="the run record is incomplete: 3 rows missing; no summary"):
        outcome(_check(problems=["3 rows missing", "no summary"]))


def test_the_monitor_must_have_finished_well(tmp_path: Path):
    log = tmp_path / "monitor.log"
    log.write_text("--- start morph-sim monitor\nmorph-sim monitor: error: disk full\n")
    monitor = Child(ProcessSpec("monitor", "monitor", ("morph-sim", "monitor")), log)
    monitor.proc = SimpleNamespace(poll=lambda: 0, returncode=0)
    assert monitor_failure([monitor]) is None
    monitor.proc = SimpleNamespace(poll=lambda: 2, returncode=2)
    assert monitor_failure([monitor]) == "the monitor failed (status 2): monitor: disk full; the record is incomplete"
    monitor.proc = SimpleNamespace(poll=lambda: None, returncode=None)
    assert monitor_failure([monitor]).startswith("the monitor did not finish the run record within 30 s")


# -- readiness -------------------------------------------------------------------------------------------------------
def test_only_tcp_endpoints_have_an_address_to_probe():
    assert tcp_address("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert tcp_address("tcp/[::1]:7447") == ("::1", 7447)
    assert tcp_address("udp/127.0.0.1:7447") is None and tcp_address("tcp/localhost:x") is None
