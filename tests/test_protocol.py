"""The dispatch protocol (services/protocol) and the lab's discrete-event network: late, not lost.

Unit tests drive the pure endpoints with explicit sim times; the episode tests run the lab's tick loop with faults
on the protocol's messages and on the fleet broadcast."""

from __future__ import annotations

import numpy as np
import pytest

from morph_sim.lab.network import (
    FLEET_KEY,
    EventNetwork,
    LabDispatch,
    dispatch_faults,
    fleet_faults,
)
from morph_sim.lab.runner import DispatchStats, EpisodeSpec, run_episode
from schemas.faults import FaultSpec, Latency, Loss, Scope
from services.policies.coordinators import MorphPolicy
from services.policies.interface import Fleet
from services.protocol.dispatch import (
    AgvEndpoint,
    Commitment,
    CommitmentDesk,
    Outcomes,
    PickerEndpoint,
    Refusal,
    Request,
    decision_points,
)
from services.protocol.tick import TickStep
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig

DT = 1.0


def test_request_delayed_a_tenth_is_handled_before_one_delayed_three_tenths():
    """No rounding to phase boundaries: delivery time orders the requests, not the mission order."""
    out = Outcomes()
    picker = PickerEndpoint(5)
    _, decide_at, _ = decision_points(0, DT)
    first_in_mission_order = Request(agv=0, picker=5, cell=(1, 1), sent_at=0.0, seq=1)
    second = Request(agv=1, picker=5, cell=(2, 2), sent_at=0.0, seq=1)
    picker.receive(first_in_mission_order, 0.0 + 0.3 * DT, out)
    picker.receive(second, 0.0 + 0.1 * DT, out)
    commit, replies = picker.decide(decide_at, assigned=False, rank={0: 0, 1: 1}, outcomes=out)
    assert commit is not None and commit.agv == 1
    assert [(r.agv, r.accepted) for r in replies] == [(1, True), (0, False)]
    # at equal delivery times the fleet's mission order breaks the tie
    tie = PickerEndpoint(5)
    tie.receive(second, 0.2, out)
    tie.receive(first_in_mission_order, 0.2, out)
    assert tie.decide(decide_at, False, {0: 0, 1: 1}, out)[0].agv == 0


def test_request_delivered_after_the_decision_point_waits_for_the_next_one():
    out = Outcomes()
    picker = PickerEndpoint(5)
    picker.receive(Request(0, 5, (1, 1), 0.0, 1), 0.0 + 0.6 * DT, out)  # after t·Δ + Δ/2
    assert picker.decide(decision_points(0, DT)[1], False, {0: 0}, out) == (None, [])
    commit, _ = picker.decide(decision_points(1, DT)[1], False, {0: 0}, out)
    assert commit is not None and commit.agv == 0


def test_commitment_delayed_two_and_a_half_ticks_is_applied_at_the_boundary_after_it_arrives():
    out = Outcomes()
    desk = CommitmentDesk(DT)
    sent = decision_points(0, DT)[1]  # the picker decides at 0.5
    desk.receive(Commitment(5, 0, (1, 1), sent, 1), sent + 2.5 * DT, out)  # arrives at 3.0
    applied_at = []

    def apply(pairs):
        return pairs

    for t in range(4):
        boundary = decision_points(t, DT)[2]
        done, refusals = desk.settle(boundary, {0: 0}, {0: (1, 1)}, apply, out)
        if done:
            applied_at.append(boundary)
        assert not refusals
    assert applied_at == [3.0]
    assert (out.on_time, out.late_applied, out.refused_stale) == (0, 1, 0)


def test_stale_commitment_is_refused_counted_and_both_sides_learn_it():
    out = Outcomes()
    agv, picker, desk = AgvEndpoint(0), PickerEndpoint(5), CommitmentDesk(DT)
    req = agv.request(5, (1, 1), 0.0, out)
    picker.receive(req, 0.0, out)
    commit, replies = picker.decide(0.5, False, {0: 0}, out)
    agv.receive(replies[0], out)
    assert agv.accepted and agv.outstanding is not None and picker.pending is not None
    desk.receive(commit, 3.0, out)
    # by the time it arrives the AGV needs no picker any more (wanted is empty): refused
    done, refusals = desk.settle(3.0, {}, {}, lambda pairs: pairs, out)
    assert done == [] and refusals == [Refusal(5, 0, 3.0, commit.seq)] and out.refused_stale == 1
    agv.receive(refusals[0], out)
    picker.receive(refusals[0], 3.0, out)
    assert agv.outstanding is None and picker.pending is not None  # the picker hears it at its decision point
    picker.check_pending(3.5, False, out)
    assert picker.pending is None and out.commitment_expired == 0
    # the world's own check (picker no longer free) refuses too
    desk.receive(Commitment(5, 0, (1, 1), 3.5, 2), 3.5, out)
    done, refusals = desk.settle(4.0, {0: 0}, {0: (1, 1)}, lambda pairs: [], out)
    assert done == [] and len(refusals) == 1 and out.refused_stale == 2


def test_duplicates_are_idempotent_and_counted():
    out = Outcomes()
    picker, desk = PickerEndpoint(5), CommitmentDesk(DT)
    req = Request(0, 5, (1, 1), 0.0, 1)
    picker.receive(req, 0.1, out)
    picker.receive(req, 0.2, out)
    commit, replies = picker.decide(0.5, False, {0: 0}, out)
    assert len(replies) == 1
    desk.receive(commit, 0.5, out)
    desk.receive(commit, 0.7, out)
    done, _ = desk.settle(1.0, {0: 0}, {0: (1, 1)}, lambda pairs: pairs, out)
    assert done == [(5, 0)] and out.duplicates == 2 and out.on_time == 1


def test_request_timeout_expires_an_unanswered_request():
    out = Outcomes()
    agv = AgvEndpoint(0, timeout=3.0)
    agv.request(5, (1, 1), 0.0, out)
    assert not agv.may_ask(2.0, True, out)
    assert agv.may_ask(3.0, True, out) and out.expired == 1
    # a mission that no longer needs a picker ends the request without counting it as expired
    agv.request(5, (1, 1), 3.0, out)
    assert not agv.may_ask(4.0, False, out) and agv.outstanding is None and out.expired == 1


def _tiny_latency(delay: float, jitter: float = 0.0, key: str | None = None) -> tuple[FaultSpec, ...]:
    spec = FaultSpec(latency=Latency(delay=delay, jitter=jitter, distribution="normal"), seed=1)
    if key is not None:
        return (spec.model_copy(update={"id": "one", "scope": Scope(key_expr=key)}),)
    return tuple(dispatch_faults(spec))


def test_commitments_delayed_two_and_a_half_ticks_are_all_applied_late_in_an_episode():
    ep = run_episode(EpisodeSpec(scale="tiny", condition="full", seed=3, steps=300, fiedler_every=1000,
                                 faults=_tiny_latency(2.5, key="agent/*/commit")))
    s = ep.summary
    assert s["protocol_on_time"] == 0 and s["protocol_late_applied"] > 20
    assert s["deliveries"] > 0
    # no commitment is lost: each one sent was applied late, refused as stale, or still in flight at the end
    sent = s["protocol_requests"] - s["protocol_declined"] - s["protocol_expired"]
    assert s["protocol_late_applied"] + s["protocol_refused_stale"] >= sent - 5


@pytest.mark.parametrize("condition", ["full", "morph", "tsg", "proximity"])
def test_no_policy_falls_to_zero_deliveries_at_five_ticks_of_latency(condition):
    clean = run_episode(EpisodeSpec(scale="tiny", condition=condition, seed=1, steps=300, radius=4,
                                    fiedler_every=1000))
    late = run_episode(EpisodeSpec(scale="tiny", condition=condition, seed=1, steps=300, radius=4,
                                   fiedler_every=1000, faults=_tiny_latency(5.0, 1.25)))
    assert late.summary["deliveries"] > 0.4 * clean.summary["deliveries"] > 0


def test_zero_effect_fleet_fault_gives_the_team_episode():
    """One brain per agent with its own view (the driver used when the broadcast can be faulted) equals the
    vectorised team brain when nothing is actually lost or delayed."""
    noop = tuple(fleet_faults(FaultSpec(loss=Loss(percent=0.0), seed=1)))
    for preset in ("reference", "paper"):
        kw = dict(scale="tiny", condition="morph", preset=preset, seed=42, steps=150, fiedler_every=1000)
        team, own = run_episode(EpisodeSpec(**kw)), run_episode(EpisodeSpec(faults=noop, **kw))
        for col in ("deliveries", "commits", "gate_p_sum", "links"):
            np.testing.assert_array_equal(team.ticks[col], own.ticks[col], err_msg=f"{preset} {col}")
        np.testing.assert_allclose(team.final_weights, own.final_weights)
        assert own.summary["view_age_mean"] == 0.0


def test_same_seed_and_faults_same_run():
    faults = (*_tiny_latency(2.5, 0.6), *dispatch_faults(FaultSpec(id="ge", seed=2, loss=Loss(
        model="gilbert_elliott", percent=20, burst_length=4))), *fleet_faults(FaultSpec(loss=Loss(percent=20), seed=3)))
    spec = EpisodeSpec(scale="tiny", condition="morph", seed=7, steps=200, fiedler_every=1000, faults=faults)
    a, b = run_episode(spec), run_episode(spec)
    for col in ("deliveries", "commits", "gate_p_sum", "links"):
        np.testing.assert_array_equal(a.ticks[col], b.ticks[col])
    assert {k: v for k, v in a.summary.items() if k != "wall_s"} == {k: v for k, v in b.summary.items()
                                                                      if k != "wall_s"}
    assert a.summary["messages_dropped"] > 0 and a.summary["protocol_late_applied"] > 0


def test_agent_whose_fleet_broadcast_is_lost_for_k_ticks_learns_from_a_view_k_ticks_old():
    k, start, victim = 4, 10, 2
    cfg = WarehouseConfig.named("tiny", max_steps=40)
    cta = CTAController(Warehouse(cfg))
    cta.reset(5)
    fleet = Fleet(cta.n_agvs, cta.n_pickers, "tiny")
    brains = [MorphPolicy().brains(fleet, [i], 5) for i in range(fleet.n)]
    learnt: list[int] = []
    inner = brains[victim].learn
    brains[victim].learn = lambda view: (learnt.append(view.t), inner(view))
    net = EventNetwork(fleet_faults(FaultSpec(loss=Loss(percent=0.0), seed=1)), seed=5)
    driver = LabDispatch(fleet.n_agvs, fleet.n_pickers, dt=DT, timeout=5.0, network=net, agent_brains=brains)
    stats = DispatchStats()
    step = TickStep(cta, dt=DT)
    ages = []
    for t in range(start + k + 2):
        if t == start:  # the broadcast to one agent is lost from now on, for k steps
            net.layer.set(FaultSpec(id="blackout", loss=Loss(percent=100.0), duration=k * DT,
                                    scope=Scope(key_expr=FLEET_KEY, agents=[victim])), at=t * DT)
        obs = step.begin()
        driver.learn(obs)
        ages.append(driver.views[victim].age(t * DT))
        driver.dispatch(obs, step.settle, stats)
        step.finish()
    assert ages[start - 1] == 0.0
    assert ages[start + k - 1] == k * DT  # the last lost tick: its view is k ticks old
    assert ages[start + k] == 0.0  # the broadcast is back
    # it learnt nothing new while the broadcast was lost, and resumed from the fresh view
    assert start - 1 in learnt and not set(range(start, start + k)) & set(learnt) and start + k in learnt
    assert driver.view_age_max[start + k - 1] == k * DT


def test_outcome_tally_sums_each_endpoint_once_and_keeps_what_a_restarted_one_counted():
    from services.protocol.dispatch import OutcomeTally

    tally = OutcomeTally()
    tally.report(0, 3, {"requests": 4, "expired": 1})
    tally.report(5, 4, {"declined": 2})
    tally.report(0, 4, {"requests": 5, "expired": 1})  # cumulative: counts once
    tally.report(0, 2, {"requests": 1})  # an older report arriving late changes nothing
    assert tally.total() == {**Outcomes().as_dict(), "requests": 5, "expired": 1, "declined": 2}
    tally.report(0, 9, {"requests": 2})  # AGV 0 restarted from zero: its earlier counts stay
    assert tally.total({"on_time": 3})["requests"] == 7 and tally.total({"on_time": 3})["on_time"] == 3
    assert Outcomes(expired=2).counts() == {"expired": 2}


def test_an_agent_service_whose_fleet_broadcast_is_lost_for_k_ticks_learns_from_a_view_k_ticks_old(tmp_path):
    """The same in the services: agent services over LocalBus, the fleet broadcast to one of them lost for k ticks
    (``sim/fleet``, scoped to that agent). Its ack reports a view k ticks old at the last lost tick, and every W row
    at the end equals the lab's agents fed the same stale views; the stale views changed what it learnt."""
    import asyncio

    from morph_sim.local import run_local
    from services.monitor.recorder import read_metrics
    from services.runconfig import RunConfig
    from services.sim.wire import make_controller

    k, start, victim, steps = 4, 10, 1, 24
    sched = tmp_path / "blackout.toml"
    sched.write_text(f'[[at]]\ntick = {start}\nspec = {{ id = "blackout", scope = {{ key_expr = "{FLEET_KEY}", '
                     f'agents = [{victim}] }}, loss = {{ percent = 100 }}, duration = {k * DT} }}\n')
    config = RunConfig(run_id="stale", scale="tiny", policy="morph", seed=5, steps=steps, fault_schedule=sched,
                       output_dir=tmp_path / "faulted")
    run = asyncio.run(run_local(config))
    clean = asyncio.run(run_local(config.model_copy(update={"fault_schedule": None,
                                                            "output_dir": tmp_path / "clean"})))
    rows = read_metrics(tmp_path / "faulted" / "stale")
    n = config.n_agents
    age_max = [float(r["view_age_max"]) for r in rows]
    assert age_max[:start] == [0.0] * start
    assert age_max[start:start + k] == [float(i * DT) for i in range(1, k + 1)]  # k ticks old at the last lost tick
    assert age_max[start + k:] == [0.0] * (steps - start - k)  # the broadcast is back
    assert float(rows[start + k - 1]["view_age_mean"]) == pytest.approx(k * DT / n)

    # the lab's agents, each with its own view, the same broadcast lost to the same agent for the same ticks
    cta = make_controller(config)
    fleet = Fleet(config.n_agvs, config.n_pickers, config.scale)
    brains = [config.make_policy().brains(fleet, [i], config.seed) for i in range(n)]
    net = EventNetwork(fleet_faults(FaultSpec(loss=Loss(percent=0.0), seed=1)), seed=config.seed)
    driver = LabDispatch(fleet.n_agvs, fleet.n_pickers, dt=DT, timeout=config.request_timeout, network=net,
                         agent_brains=brains)
    stats = DispatchStats()
    step = TickStep(cta, dt=DT)
    for t in range(steps):
        if t == start:
            net.layer.set(FaultSpec(id="blackout", loss=Loss(percent=100.0), duration=k * DT,
                                    scope=Scope(key_expr=FLEET_KEY, agents=[victim])), at=t * DT)
        obs = step.begin()
        driver.learn(obs)
        driver.dispatch(obs, step.settle, stats)
        step.finish()
    driver.learn(step.final())
    W, W_clean = run.monitor.snapshots[steps][0], clean.monitor.snapshots[steps][0]
    np.testing.assert_array_equal(W, np.vstack([b.weight_rows() for b in brains]))
    assert driver.view_age_max[start + k - 1] == k * DT
    assert not np.array_equal(W[victim], W_clean[victim])  # learning felt the stale views


# -- broadcast Full-Graph: an AGV asks every free picker, the desk keeps one ----------------------------------------
def _one_per_agv(pairs):
    """The world's rule for the desk: one picker per mission cell (the first in order)."""
    taken, out = set(), []
    for picker, agv in pairs:
        if agv not in taken:
            taken.add(agv)
            out.append((picker, agv))
    return out


def _broadcast(out: Outcomes):
    """AGV 0 asks pickers 5 and 6 at once; both are free and accept; both commitments reach the sim."""
    agv, pickers, desk = AgvEndpoint(0), {p: PickerEndpoint(p) for p in (5, 6)}, CommitmentDesk(DT)
    commits = []
    for p, endpoint in pickers.items():
        req = agv.request(p, (1, 1), 0.0, out)
        endpoint.receive(req, 0.0, out)
        commit, replies = endpoint.decide(0.5, False, {0: 0}, out)
        assert commit is not None and replies[0].accepted
        agv.receive(replies[0], out)
        commits.append(commit)
    assert agv.accepted == {5, 6} and set(agv.asked) == {5, 6}
    for c in commits:
        desk.receive(c, 0.5, out)
    return agv, pickers, desk


def test_broadcast_two_pickers_accept_exactly_one_is_applied_the_other_released_and_counted():
    out = Outcomes()
    agv, pickers, desk = _broadcast(out)
    done, refusals = desk.settle(1.0, {0: 0}, {0: (1, 1)}, _one_per_agv, out)
    assert done == [(5, 0)] and out.on_time == 1
    assert refusals == [Refusal(6, 0, 1.0, pickers[6].pending.seq)] and out.refused_stale == 1
    agv.receive(refusals[0], out)  # the refusal goes to both sides: the AGV forgets picker 6's acceptance
    pickers[6].receive(refusals[0], 1.0, out)
    pickers[6].check_pending(1.5, False, out)  # its next decision point
    assert pickers[6].pending is None and out.commitment_expired == 0  # released: free to take the next request
    assert agv.asked.keys() == {5}
    assert not agv.may_ask(1.0, False, out) and not agv.asked  # served: its mission needs no picker any more


def test_broadcast_a_lost_refusal_is_healed_by_the_pickers_timeout():
    out = Outcomes()
    _, pickers, desk = _broadcast(out)
    _, refusals = desk.settle(1.0, {0: 0}, {0: (1, 1)}, _one_per_agv, out)
    assert [r.picker for r in refusals] == [6]  # ... and lost on its way to picker 6
    loser = pickers[6]
    for t in range(1, 5):  # still holding itself for a commitment that will never land: it declines meanwhile
        loser.receive(Request(1, 6, (2, 2), t, t), t + 0.1, out)
        commit, replies = loser.decide(t + 0.5, False, {1: 0}, out)
        assert commit is None and not replies[0].accepted
    commit, replies = loser.decide(5.5, False, {1: 0}, out)  # 5 s (the timeout) after it committed: freed
    assert loser.pending is None and out.commitment_expired == 1
    loser.receive(Request(1, 6, (2, 2), 6.0, 9), 6.0, out)
    commit, replies = loser.decide(6.5, False, {1: 0}, out)
    assert commit is not None and replies[0].accepted


def test_broadcast_is_the_papers_all_to_all_and_its_messages_grow_with_the_pickers():
    """Full-Graph as the paper means it: an AGV asks every free picker at once; conflicts are resolved by the desk
    (refused, counted). Requests per decision and messages per delivery grow with the number of pickers, faster
    than the unicast Full-Graph's (the O(N²) claim, measured in messages)."""
    per_request, per_delivery, ratio = [], [], []
    for scale in ("tiny", "small", "medium"):
        b = run_episode(EpisodeSpec(scale=scale, condition="full-broadcast", seed=3, steps=300)).summary
        u = run_episode(EpisodeSpec(scale=scale, condition="full", seed=3, steps=300)).summary
        assert b["protocol_refused_stale"] > 0 and u["protocol_refused_stale"] == 0
        assert b["protocol_requests"] > b["dispatched"]  # several requests per decision
        per_request.append(b["protocol_requests"] / b["dispatched"])
        per_delivery.append(b["messages_sent"] / b["deliveries"])
        ratio.append(per_delivery[-1] / (u["messages_sent"] / u["deliveries"]))
    assert per_request == sorted(per_request) and per_request[0] > 1.0
    assert per_delivery == sorted(per_delivery) and ratio == sorted(ratio) and ratio[-1] > 1.5


# -- what one author may claim (services/protocol/claims.py) ------------------------------------------------------
def test_claims_tick_window():
    from services.protocol.claims import TICKS_AHEAD, TICKS_BEHIND, check_tick

    check_tick(10, 10, 100, "ack")
    check_tick(10 + TICKS_AHEAD, 10, 100, "ack")
    check_tick(100, -1, 100, "ack")  # no clock yet: the run's range only
    for t, now in ((101, 100), (10 + TICKS_AHEAD + 1, 10), (200 - TICKS_BEHIND - 1, 200), (10**9, -1)):
        with pytest.raises(ValueError, match="tick"):
            check_tick(t, now, 1000 if t != 101 and t != 10**9 else 100, "ack")


def test_claims_outcome_bound_per_tick_with_restart():
    from services.protocol.claims import OUTCOME_CARRY_TICKS, OutcomeBound, outcome_step_bound

    per = outcome_step_bound(8)
    bound = OutcomeBound(per)
    bound.check(3, 1, {"requests": per})  # one tick's worth
    with pytest.raises(ValueError, match="grew by"):
        bound.check(3, 2, {"requests": 2 * per + 1})
    bound.check(3, 2, {"requests": 2 * per})  # the refused report was not taken: the allowance is still there
    bound.check(3, 5, {"requests": 5 * per})  # three quiet ticks carry their allowance
    bound.check(3, 6, {"requests": 1})  # restarted from zero: judged from zero
    with pytest.raises(ValueError):
        bound.check(3, 7, {"expired": 2**62})
    bound.check(3, 6, {"expired": 2**62})  # older than the last taken: the tally ignores it, so does the bound
    with pytest.raises(ValueError):  # a long silence carries at most OUTCOME_CARRY_TICKS ticks of allowance
        bound.check(3, 6 + 10 * OUTCOME_CARRY_TICKS, {"requests": per * (OUTCOME_CARRY_TICKS + 2)})


def test_claims_once_per_tick_copies_and_seconds():
    from services.protocol.claims import MAX_COPIES, OncePerTick

    once = OncePerTick()
    assert once.admit(3, 10, 0, seq=7)
    assert [once.admit(3, 10, 0, seq=7) for _ in range(MAX_COPIES)] == [False] * MAX_COPIES  # the network's copies
    with pytest.raises(ValueError, match=f"more than {MAX_COPIES} copies"):
        once.admit(3, 10, 0, seq=7)
    with pytest.raises(ValueError, match="second answer"):
        once.admit(3, 10, 0, seq=8)
    assert once.admit(3, 10, 1, seq=9) and once.admit(4, 10, 0, seq=8)
    once.forget(3, 11, 0)
    assert once.admit(3, 11, 0, seq=1)
    once.forget(3, 11, 0)
    assert once.admit(3, 11, 0, seq=2)  # a forgotten (refused) answer does not keep the genuine one out
    for t in range(12, 12 + 100 * once.keep):  # remembered ticks stay bounded
        once.admit(5, t, 0, seq=t)
    assert len(once._seen) <= 64 * once.keep + 1


def test_claims_sender_binding():
    from services.protocol.claims import SenderBinding

    senders = SenderBinding()
    senders.check(3, "agent-3")
    senders.check(4, "host-a")  # an agent that claimed id 4: its instance name binds
    senders.check(4, "host-a")
    senders.check(4, "agent-4")
    for robot, name in ((4, "host-b"), (3, ""), (5, "")):
        with pytest.raises(ValueError):
            senders.check(robot, name)
    with pytest.raises(ValueError, match="agent-3"):
        senders.check(3, "mallory")  # robot 3's keys carry its own name already
    senders.check(6, "mallory")  # the first name seen under 6's keys binds (an instance-named session) ...
    senders.check(6, "agent-6")  # ... beside its identity
    with pytest.raises(ValueError):
        senders.check(6, "mallory-2")


def test_claims_sequence_window():
    from services.protocol.claims import SEQ_WINDOW, SeqWindow

    s = SeqWindow()
    assert s.take(1) == 0 and s.take(5) == 3 and s.take(4) == 0
    with pytest.raises(ValueError):
        s.take(5 + SEQ_WINDOW + 1)
    assert s.take(6) == 0 and s.last == 6  # the genuine stream goes on
    gaps = 0
    for k in range(1, 1001):  # a forger's numbers 9,999 apart: each one refused, no gap counted
        try:
            gaps += s.take(6 + 9_999 * k)
        except ValueError:
            pass
    assert gaps == 0 and s.last == 6
    with pytest.raises(ValueError):
        s.take(10**6)
    assert s.take(10**6 + 1) == 0 and s.last == 10**6 + 1  # two consecutive: the stream really moved (resync)


def test_desk_refuses_far_commitments_and_bounds_what_it_holds():
    from services.protocol.dispatch import MAX_HELD_PER_PICKER, Commitment, CommitmentDesk, Outcomes

    dt = 1.0
    desk, out = CommitmentDesk(dt), Outcomes()
    now = 100 * dt

    def commit(t, seq, agv=0, picker=5):
        return Commitment(picker, agv, (1, 2), t * dt + dt / 2, seq)

    for bad in (10**9, 102, 100 - 65):
        with pytest.raises(ValueError, match="tick"):
            desk.receive(commit(bad, 1), now, out, now=now)
    assert desk.inbox == []
    # a forged number does not shadow the genuine commitment that later carries it
    desk.receive(commit(100, 7, agv=1), now, out, now=now)
    desk.receive(commit(101, 7, agv=0), now, out, now=now)
    assert len(desk.inbox) == 2 and out.duplicates == 0
    desk.receive(commit(101, 7, agv=0), now, out, now=now)  # the network's copy
    assert len(desk.inbox) == 2 and out.duplicates == 1
    for seq in range(100, 100 + MAX_HELD_PER_PICKER - 2):
        desk.receive(commit(100, seq), now, out, now=now)
    with pytest.raises(ValueError, match="waiting"):
        desk.receive(commit(100, 999), now, out, now=now)
    desk.receive(commit(100, 999, picker=6), now, out, now=now)  # another picker is not held up
    assert len(desk.inbox) == MAX_HELD_PER_PICKER + 1


def test_a_flood_is_reported_once_per_robot_at_the_threshold_and_only_for_robots():
    from services.protocol.claims import FloodWatch

    watch = FloodWatch(n_agents=8, threshold=3, cut_off=5)
    assert [watch.note(3) for _ in range(7)] == [None, None, 3, None, 5, None, None]  # reported, then cut off
    assert [watch.note(who) for who in ("sim", "monitor", 8, -1, True, None)] == [None] * 6
    assert set(watch.refused) == {3}  # bounded by the fleet


def test_a_robots_events_are_bounded_in_size_and_per_tick_and_its_budget_comes_back_next_tick():
    from services.protocol.claims import EventBudget, robot_event_bytes

    budget = EventBudget(n_agents=8, per_tick=2)
    assert budget.max_bytes == robot_event_bytes(8) >= 2048 + 16 * 8  # a restore event's W row of 8 fits
    budget.check_size(3, budget.max_bytes)
    with pytest.raises(ValueError, match="event of robot 3: .* bytes, at most"):
        budget.check_size(3, budget.max_bytes + 1)
    budget.take(3, 10)
    budget.take(3, 10)
    with pytest.raises(ValueError, match="more than 2 in tick 10"):
        budget.take(3, 10)
    budget.take(4, 10)  # another robot's budget is its own
    budget.take(3, 11)  # the next tick's budget
    with pytest.raises(ValueError, match="outside 0..7"):
        budget.take(8, 11)
    assert set(budget._used) == {3, 4}  # one counter per robot of the fleet


def test_a_picker_takes_one_request_of_an_agv_a_tick_its_copies_a_few_times_and_a_reused_number_at_another_tick():
    from services.protocol.dispatch import MAX_REQUEST_COPIES, Outcomes, PickerEndpoint, Request

    ep, out = PickerEndpoint(5), Outcomes()
    ep.receive(Request(3, 5, (1, 2), 10.0, 7), 10.0, out)
    for _ in range(MAX_REQUEST_COPIES - 1):  # the network's copies: counted at the next decision point
        ep.receive(Request(3, 5, (1, 2), 10.0, 7), 10.0, out)
    with pytest.raises(ValueError, match=f"received more than {MAX_REQUEST_COPIES} times"):
        ep.receive(Request(3, 5, (1, 2), 10.0, 7), 10.0, out)
    with pytest.raises(ValueError, match="a second request of AGV 3 sent at 10 s"):
        ep.receive(Request(3, 5, (6, 6), 10.0, 8), 10.0, out)
    ep.receive(Request(4, 5, (1, 2), 10.0, 7), 10.0, out)  # another AGV's number 7 is its own
    ep.receive(Request(3, 5, (1, 2), 11.0, 7), 11.0, out)  # number 7 again a tick later: a request, not a copy
    assert [(r.agv, r.sent_at) for _, r in ep.inbox] == [(3, 10.0), (4, 10.0), (3, 11.0)]
    assert len(ep.copies) == MAX_REQUEST_COPIES - 1


def test_a_mailbox_takes_at_most_a_ticks_worth_of_policy_messages_from_one_sender():
    from schemas import PolicyMessage
    from schemas.fields import MAX_POLICY_MESSAGES
    from services.policies.interface import pack_mail
    from services.protocol.dispatch import Mailbox

    box = Mailbox()
    data = pack_mail({"bid": 1.0})
    for k in range(MAX_POLICY_MESSAGES):
        assert box.receive(PolicyMessage(t=5, sender=3, to=4, pseq=k + 1, data=data), 5.0)
    assert not box.receive(PolicyMessage(t=5, sender=3, to=4, pseq=1, data=data), 5.0)  # a copy: dropped quietly
    with pytest.raises(ValueError, match=f"robot 3 sent more than {MAX_POLICY_MESSAGES} of tick 5"):
        box.receive(PolicyMessage(t=5, sender=3, to=4, pseq=MAX_POLICY_MESSAGES + 1, data=data), 5.0)
    assert box.receive(PolicyMessage(t=5, sender=2, to=4, pseq=1, data=data), 5.0)  # another sender's are its own
    assert box.receive(PolicyMessage(t=6, sender=3, to=4, pseq=MAX_POLICY_MESSAGES + 2, data=data), 6.0)  # next tick
    assert len(box.items) == MAX_POLICY_MESSAGES + 2
