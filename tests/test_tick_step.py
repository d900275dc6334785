"""The lockstep tick step (services/protocol/tick.py) on its own: pure code over a real warehouse, no bus."""

from __future__ import annotations

import numpy as np

from schemas.network import NetworkProfile
from services.policies.interface import Fleet
from services.policies.loading import make_policy
from services.protocol.dispatch import Commitment, CommitmentDesk, Outcomes
from services.protocol.tick import (
    DemandShift,
    TickStep,
    distinct_cells,
    first_in_mission_order,
    sequential_commits,
)
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig

DT = 1.0


def _controller(seed: int = 3, steps: int = 60) -> CTAController:
    ctl = CTAController(Warehouse(WarehouseConfig.named("tiny", max_steps=steps + 1)))
    ctl.reset(seed)
    return ctl


def _until_someone_needs_a_picker(step: TickStep):
    for _ in range(50):
        obs = step.begin()
        if obs.needs_picker.any():
            return obs
        step.finish()
    raise AssertionError("no AGV needed a picker in 50 steps")


def test_a_demand_shift_takes_effect_at_each_phase_boundary_only():
    shift = DemandShift(("left", "right", "left"), steps=10)
    assert [shift.side_at(t) for t in (0, 1, 9, 10, 19, 20, 29, 30)] == ["left", None, None, "right", None, "left",
                                                                          None, None]
    ctl = _controller()
    step = TickStep(ctl, dt=DT, demand=DemandShift(("right",), steps=5, mode="assignment"))
    step.begin()
    assert ctl.assignment_side == "right"  # the reference's variant: queued items of that half first
    step.finish()


def test_the_decision_plan_lists_requesters_in_mission_order_and_keeps_pickers_with_nothing_new():
    ctl = _controller()
    obs = _until_someone_needs_a_picker(TickStep(ctl, dt=DT))
    order = [int(a) for a in obs.request_order]
    assert len(order) >= 1
    picker = ctl.n_agvs  # the first picker
    requests = {agv: [picker] for agv in reversed(order)}  # arrival order is the reverse of mission order
    plan = TickStep.decision_plan(obs, requests, more=[picker + 1])
    assert plan == {picker: order, picker + 1: []}


def test_a_commitment_for_a_cell_the_agv_no_longer_needs_is_refused_and_a_valid_one_applied():
    ctl = _controller()
    step = TickStep(ctl, dt=DT)
    obs = _until_someone_needs_a_picker(step)
    agv = int(np.flatnonzero(obs.needs_picker)[0])
    cell = (int(obs.target[agv, 0]), int(obs.target[agv, 1]))
    free = [int(p) for p in np.flatnonzero(obs.free_picker)]
    assert len(free) >= 2
    desk, outcomes = CommitmentDesk(DT), Outcomes()
    s = obs.t * DT + DT / 2
    desk.receive(Commitment(free[0], agv, (cell[0] + 1, cell[1]), s, 1), s, outcomes)  # a stale cell
    desk.receive(Commitment(free[1], agv, None, s, 1), s, outcomes)  # no cell said: checked against the AGV's own
    applied, refusals = step.settle(obs, desk, outcomes)
    assert applied == [(free[1], agv)]
    assert [(r.picker, r.agv) for r in refusals] == [(free[0], agv)]
    assert (outcomes.on_time, outcomes.refused_stale) == (1, 1)
    assert step.commits_applied == 1
    assert desk.inbox == []


def test_a_commitment_due_after_the_boundary_waits_for_the_next_one():
    ctl = _controller()
    step = TickStep(ctl, dt=DT)
    obs = _until_someone_needs_a_picker(step)
    agv = int(np.flatnonzero(obs.needs_picker)[0])
    picker = int(np.flatnonzero(obs.free_picker)[0])
    cell = (int(obs.target[agv, 0]), int(obs.target[agv, 1]))
    desk, outcomes = CommitmentDesk(DT), Outcomes()
    late = (obs.t + 1) * DT + 0.3
    desk.receive(Commitment(picker, agv, cell, obs.t * DT + 0.5, 1), late, outcomes)
    assert step.settle(obs, desk, outcomes) == ([], [])
    assert len(desk.inbox) == 1  # not lost: it waits in the inbox


def test_an_idle_robot_takes_no_new_target_and_the_others_move():
    moved = {}
    for idle in ((), (0,)):
        ctl = _controller(seed=1)
        step = TickStep(ctl, dt=DT)
        step.begin()
        start = ctl.wh.x.copy(), ctl.wh.y.copy()
        for _ in range(5):
            step.finish(idle=idle)
            step.begin()
        moved[idle] = [(int(ctl.wh.x[r]), int(ctl.wh.y[r])) != (int(start[0][r]), int(start[1][r]))
                       for r in range(ctl.n)]
    assert moved[()][0] and not moved[(0,)][0]  # robot 0 moves unless its agent is absent


class _SilentRadio:
    """A network model whose robots' radios are all silent (a hand-over outage everywhere)."""

    def __init__(self, stop: float | None):
        self.profile = NetworkProfile.model_validate({"name": "silent", "silence_stop": stop} if stop else
                                                     {"name": "silent"})
        self.asked: list[tuple[float, float]] = []

    def silenced(self, now: float, stop: float) -> set[int]:
        self.asked.append((now, stop))
        return {0, 1}


def test_the_silence_stop_holds_silent_robots_for_the_step_and_counts_them():
    ctl = _controller()
    step = TickStep(ctl, dt=DT)
    step.begin()
    radio = _SilentRadio(stop=2.0)
    step.finish(radio=radio)
    assert radio.asked == [(0.0, 2.0)] and ctl.held == {0, 1} and step.network_stops == 2
    quiet = _SilentRadio(stop=None)  # a profile without a silence stop holds nobody
    step.begin()
    step.finish(radio=quiet)
    assert quiet.asked == [] and step.network_stops == 2


def test_the_final_observation_comes_after_the_last_step():
    ctl = _controller(steps=3)
    step = TickStep(ctl, dt=DT)
    for _ in range(3):
        step.begin()
        step.finish()
    assert step.final().t == 3


def test_the_sequential_mode_gives_each_cell_one_picker_and_counts_every_gate():
    ctl = _controller()
    step = TickStep(ctl, dt=DT)
    obs = _until_someone_needs_a_picker(step)
    seen = []
    commits = sequential_commits(obs, _full_coordinator(ctl), lambda agv: 0.0, lambda ask, p: seen.append(ask))
    assert len(seen) >= len(commits) >= 1
    assert len({p for p, _ in commits}) == len(commits)  # one commitment per picker
    assert distinct_cells(obs, commits) == set(commits)  # and one per cell
    assert step.commit_now(commits) and step.commits_applied >= 1


def _full_coordinator(ctl):
    """Full-Graph: every AGV asks the nearest free picker, always."""
    return make_policy("full").brains(Fleet(ctl.n_agvs, ctl.n_pickers, "tiny"), range(ctl.n), 0)


def test_at_zero_latency_the_first_request_in_mission_order_wins_each_picker():
    assert first_in_mission_order([(3, 9), (1, 9), (2, 8)]) == [(9, 3), (8, 2)]
    assert first_in_mission_order([]) == []
