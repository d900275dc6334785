"""The monitor's row reducer (services/metrics/rows.py) as pure code: messages in, final rows out."""

from __future__ import annotations

import itertools

import numpy as np

from schemas import Ack, AgentState
from services.metrics import catalogue
from services.metrics.rows import ROW_GRACE_TICKS, RowReducer

N, AGVS, STEPS = 3, 1, 40


def reducer(plastic: bool = False) -> RowReducer:
    return RowReducer(N, AGVS, STEPS, state_every=5, snapshot_every=10, plastic=plastic)


def ack(t: int, agent: int, **fields) -> Ack:
    fields.setdefault("links", [j for j in range(N) if j != agent])
    fields.setdefault("outcomes", {})
    return Ack(t=t, agent=agent, **fields)


def every_report(rows: RowReducer, t: int, agents=range(N)) -> list:
    """Tick ``t`` and every agent's ack of it; the rows the tick closed."""
    closed, _ = rows.tick(t, sim_time=float(t), deliveries=1, outcomes=None)
    for a in agents:
        rows.ack(ack(t, a))
    return closed


def test_a_row_closes_when_every_report_is_in():
    rows = reducer()
    assert every_report(rows, 0) == [] and every_report(rows, 1) == []
    (closed,) = every_report(rows, 2)  # tick 2: row 0 is due, and its reports (acks of 0, outcomes of 1) are in
    assert closed.values["t"] == 0 and closed.values["acks"] == N and closed.values["links"] == 3
    assert closed.values["deliveries"] == 1 and closed.values["deliveries_total"] == 1
    assert set(closed.values) == set(catalogue.COLUMNS)
    np.testing.assert_array_equal(closed.links, ~np.eye(N, dtype=bool))
    assert rows.next_row == 1


def test_a_row_without_one_agents_report_waits_for_it():
    rows = reducer()
    every_report(rows, 0)
    every_report(rows, 1, agents=(0, 1))  # agent 2's ack of 1 (its outcomes of step 0) is late
    assert every_report(rows, 2) == []
    rows.ack(ack(1, 2))
    assert [c.values["t"] for c in every_report(rows, 3)] == [0, 1]


def test_a_missing_agents_row_closes_grace_ticks_later_without_it():
    rows = reducer()
    closed = {}
    for t in range(ROW_GRACE_TICKS + 3):
        for c in every_report(rows, t, agents=(0, 1)):
            closed[c.values["t"]] = t
    # row 0 is due at tick 2 and waits ROW_GRACE_TICKS ticks for agent 2, then closes without it
    assert closed == {0: ROW_GRACE_TICKS + 2}
    assert rows.next_row == 1


def test_the_missing_agents_row_is_written_without_it():
    rows = reducer()
    for t in range(ROW_GRACE_TICKS + 3):
        every_report(rows, t, agents=(0, 1))
    final, _ = rows.finish()
    first = [c.values for c in final][0]
    # agent 2's links are missing too: 0–1, 0–2, 1–2 are linked one way or both
    assert first["t"] == 1 and first["acks"] == 2 and first["links"] == 3


def test_outcome_columns_are_the_counts_at_the_step_boundary():
    rows, closed = reducer(), []
    for t in range(6):
        closed += rows.tick(t, sim_time=float(t), deliveries=0, outcomes={"on_time": 10 * t})[0]
        for a in range(N):
            # each robot's counts as they stood at the start of tick t: t requests, one decline from the picker 2
            rows.ack(ack(t, a, outcomes={"requests": t, "declined": int(a == 2 and t >= 2)}))
    by_t = {c.values["t"]: c.values for c in closed + rows.finish()[0]}
    # row t: the robots' counts at the start of tick t+1 and the sim's on tick t+1
    assert [by_t[t]["dispatch_on_time"] for t in range(3)] == [10, 20, 30]
    assert [by_t[t]["dispatch_declined"] for t in range(3)] == [0, 1, 1]
    assert all(by_t[t]["dispatch_expired"] == 0 for t in range(3))
    assert set(catalogue.outcome_values({})) <= set(by_t[0])


def test_averages_are_taken_in_agent_order_whatever_the_arrival_order():
    # summed in arrival order these would differ: 0.1 + 1e16 − 1e16 is 0, 1e16 − 1e16 + 0.1 is 0.1
    etas, ages = [0.1, 1e16, -1e16], [0.1, 1e16, 3.0]

    def row_of(order) -> dict:
        rows = reducer(plastic=True)
        for t in range(3):
            rows.tick(t, sim_time=float(t), deliveries=0, outcomes=None)
            for a in order:
                rows.ack(ack(t, a, eta=etas[a], view_age=ages[a]))
        final, _ = rows.finish()
        return final[0].values

    rows = [row_of(order) for order in itertools.permutations(range(N))]
    assert rows[0]["eta"] == np.mean(etas) and rows[0]["view_age_mean"] == sum(ages) / N
    assert all(r == rows[0] for r in rows)


def test_a_state_sample_completes_into_a_snapshot_and_the_w_block_means():
    rows = reducer()
    W = np.arange(N * N, dtype=float).reshape(N, N)

    def state(agent: int) -> AgentState:
        return AgentState(agent=agent, role="agv" if agent < AGVS else "picker", t=10, w_row=W[agent].tolist(),
                          a_row=[True] * N, theta_row=[0.0] * N, age_row=[0] * N, h=0.0, eta=0.0)

    assert rows.state(state(0)) is None and rows.state(state(1)) is None
    snap = rows.state(state(2))
    assert snap.t == 10 and snap.A.all()
    np.testing.assert_array_equal(snap.W, W)
    closed = []
    for t in range(13):
        closed += every_report(rows, t)
    row10 = next(c.values for c in closed + rows.finish()[0] if c.values["t"] == 10)
    assert row10["w_picker_picker"] == (W[1, 2] + W[2, 1]) / 2 and row10["w_agv_picker"] is not None


def test_the_final_acks_still_missing_are_those_of_the_robots_that_acked_the_tick_before():
    # the monitor may see the sim's end of run before final acks the sim routed to it: it waits for these, and the
    # last row then holds every robot's final links and η, as the in-process run's does
    rows = reducer(plastic=True)
    assert rows.final_acks_missing() == set()  # nothing ticked yet
    for t in range(STEPS):
        every_report(rows, t)
    rows.tick(STEPS, sim_time=float(STEPS), deliveries=0, outcomes=None)  # the final tick
    assert rows.final_acks_missing() == set(range(N))
    rows.ack(ack(STEPS, 0, links=[1], eta=0.5))
    rows.ack(ack(STEPS, 2, links=[], eta=-0.5))
    assert rows.final_acks_missing() == {1}
    rows.ack(ack(STEPS, 1, links=[0], eta=0.1))
    assert rows.final_acks_missing() == set()
    closed, _ = rows.finish()
    last = closed[-1].values
    assert last["t"] == STEPS - 1 and last["links"] == 1  # the pair 0-1, from the final acks


def test_a_robot_absent_at_the_end_is_not_awaited():
    rows = reducer(plastic=True)
    for t in range(STEPS - 1):
        every_report(rows, t)
    every_report(rows, STEPS - 1, agents=(0, 1))  # robot 2 died before its last ack
    rows.tick(STEPS, sim_time=float(STEPS), deliveries=0, outcomes=None)
    assert rows.final_acks_missing() == {0, 1}
