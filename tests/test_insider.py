"""An insider: one robot's own session (its header name ``agent-<id>``, its own keys only — all that the endpoint's
access control lets its credentials do) used to lie, against the sim and the monitor wired in this process.

Each attack lands at tick :data:`AT` of a tiny run; the run completes, its ``metrics.csv`` equals the same run's
without the attack in every row (every attack here is refused whole, so the liar's own rows are unchanged too), its
snapshots are the same files, and the sim and the monitor count the refusals. The process boundary and the access
control are tests/test_hostile.py's; what is checked here is what the receivers take from a robot's own keys.
"""

from __future__ import annotations

import asyncio
import json
import time

import pytest

from morph_sim.local import run_local
from schemas import Ack, AgentState, Commit, Event, HelpRequest, MetricSample, encode
from schemas.keys import RunKeys
from services.bus.base import Sample
from services.bus.local import LocalNetwork
from services.monitor.recorder import read_metrics
from services.protocol import claims
from services.protocol.claims import (
    FLOOD_REFUSALS,
    ROBOT_EVENTS_PER_TICK,
    SEQ_WINDOW,
    robot_event_bytes,
)
from services.protocol.dispatch import MAX_HELD_PER_PICKER
from services.runconfig import RunConfig

STEPS = 80  # the attack at tick AT, then 50 ticks of the run that must not take any of it
AT = 30  # the tick the attack lands at: the run is under way, rows before and after it are compared


def _config(tmp_path, run_id: str) -> RunConfig:
    return RunConfig(run_id=run_id, scale="tiny", policy="morph", steps=STEPS, seed=42, output_dir=tmp_path,
                     state_every=10, snapshot_every=20)


async def _run(tmp_path, run_id: str, attack=None, refused_stream: list | None = None):
    """The run, with ``attack(put, keys, config, t)`` called at the start of tick :data:`AT`; ``put(key, message,
    sender, seq)`` sends under any header (``sender`` defaults to robot 3's own name)."""
    config = _config(tmp_path, run_id)
    keys = RunKeys(run_id)
    net = LocalNetwork()
    sent = [0]

    def put(key: str, message, sender: str = "agent-3", seq: int | None = None) -> None:
        bus = insider
        payload = message if isinstance(message, bytes) else encode(message)
        # a second session of the robot numbers from one: behind its genuine stream, so no sequence check stops it
        number = seq if seq is not None else 1 + sent[0]
        bus._send(Sample(key, payload, sender, number, time.time()), False)
        sent[0] += 1

    def progress(t: int, _deliveries: int) -> None:
        if t == AT and attack is not None:
            attack(put, keys, config, t)

    insider = net.session("agent-3")  # the compromised robot's credentials: its own name, on its own keys
    if refused_stream is not None:  # a user's client on the monitor's stream of refusals by robot
        observer = net.session("observer")
        await observer.subscribe(keys.metric("refused_by_robot"),
                                 lambda sample: refused_stream.append(sample.decode(MetricSample)))
    run = await run_local(config, network=net, progress=progress)
    record = config.record_dir
    snapshots = sorted(p.name for p in (record / "snapshots").glob("t*.npz"))
    summary = json.loads((record / "summary.json").read_text())
    return run, read_metrics(record), snapshots, summary, sent[0]


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    return asyncio.run(_run(tmp_path_factory.mktemp("insider-base"), "insider"))


async def _attacked(tmp_path, baseline, attack, *, sim_refused: int, monitor_refused: int):
    run, rows, snapshots, summary, sent = await _run(tmp_path, "insider", attack)
    base_run, base_rows, base_snapshots, base_summary, _ = baseline
    assert run.sim.steps == STEPS and run.sim.stopped_early is None
    assert rows == base_rows  # every row: nothing of the attack was taken
    assert snapshots == base_snapshots
    assert run.sim.protocol == base_run.sim.protocol and run.sim.deliveries == base_run.sim.deliveries
    assert summary["sequence_gaps"] == base_summary["sequence_gaps"]
    assert run.sim.rejected == base_run.sim.rejected + sim_refused
    assert run.monitor.rejected == base_run.monitor.rejected + monitor_refused
    return run, summary, sent


async def test_insider_outcomes_and_ticks_out_of_window_are_refused(tmp_path, baseline):
    """Acks of robot 3 claiming 2**62 expiries: after the run, at the current tick (a lie beyond what a tick can
    produce: refused, and the genuine ack of that tick is still taken); a second ack of the tick just answered
    (refused, not preferred); and 300 acks for ticks ahead."""
    def attack(put, keys, config, t):
        put(keys.ack(3), Ack(t=config.steps + 1, agent=3, outcomes={"expired": 2**62}))
        put(keys.ack(3), Ack(t=t - 1, agent=3, requests_sent=[config.n_agvs], links=[0, 1, 2], eta=9.0))
        put(keys.ack(3), Ack(t=t, agent=3, outcomes={"expired": 2**62}))
        for ahead in range(100, 400):
            put(keys.ack(3), Ack(t=t + ahead - 90 if t + ahead - 90 <= config.steps else config.steps,
                                 agent=3, requests_sent=[config.n_agvs], links=[0, 1, 2], eta=9.0))

    # 303 refused by the sim and the monitor alike (the ahead ones beyond the run's end too: out of 0..steps)
    await _attacked(tmp_path, baseline, attack, sim_refused=303, monitor_refused=303)


async def test_insider_new_sender_names_and_sequence_jumps(tmp_path, baseline):
    """1,000 acks under a new header name on robot 3's key, numbers 9,999 apart, then 1,000 more under its own
    name: no new stream, no gap of millions."""
    def attack(put, keys, config, t):
        bogus = encode(Ack(t=t, agent=3))
        for k in range(1, 1001):
            put(keys.ack(3), bogus, sender="mallory", seq=9_999 * k)
        for k in range(1, 1001):
            put(keys.ack(3), bogus, seq=(SEQ_WINDOW + 10) * k * 2)

    # the monitor: 2,000 (sender, then the jumps; its own ack stream's genuine numbers stay where they were);
    # the sim judges names too (1,000) and refuses the other 1,000 as second acks of tick AT (nothing taken)
    run, summary, _ = await _attacked(tmp_path, baseline, attack, sim_refused=2000, monitor_refused=2000)
    assert summary["sequence_gaps"] == 0
    # the sim reports the flood once, naming the robot, in the record (the run itself goes on unchanged)
    assert run.sim.flooding == [3] and baseline[0].sim.flooding == []
    events = [json.loads(line) for line in (tmp_path / "insider" / "events.jsonl").read_text().splitlines()]
    floods = [e for e in events if e["kind"] == "agent.flooding"]
    assert [(e["source"], e["details"]["agent"], e["details"]["refused"]) for e in floods] == [("sim", 3, 256)]


async def test_insider_states_of_ticks_that_do_not_exist(tmp_path, baseline):
    """Agent-state messages of robot 3 for ticks beyond the run and far ahead: no snapshot is begun or written."""
    def attack(put, keys, config, t):
        row = [0.5] * config.n_agents
        for k in range(300):
            future = config.steps + 1 + k if k % 2 else t + 20 + k
            put(keys.agent_state(3), AgentState(
                t=future, agent=3, role="agv", w_row=row, a_row=[False] * config.n_agents,
                theta_row=row, age_row=[0] * config.n_agents, h=0.0, eta=0.1))

    await _attacked(tmp_path, baseline, attack, sim_refused=0, monitor_refused=300)


async def test_insider_picker_commits_far_ticks_and_forged_numbers(tmp_path, baseline):
    """A picker's own key: 3,000 commitments of tick 10**9 and 1,000 with numbers 1..1,000 for ticks long past;
    none is held (the sim's later genuine commitments of that picker are applied as without the attack)."""
    def attack(put, keys, config, t):
        p = config.n_agvs
        for k in range(3000):
            put(keys.commit(p), Commit(t=10**9, picker=p, agv=0, seq=k + 1), sender=f"agent-{p}")
        for seq in range(1, 1001):
            put(keys.commit(p), Commit(t=0, picker=p, agv=0, seq=seq), sender=f"agent-{p}")

    run, _, _ = await _attacked(tmp_path, baseline, attack, sim_refused=4000, monitor_refused=4000)
    assert MAX_HELD_PER_PICKER < 4000


def _events(tmp_path) -> list[dict]:
    return [json.loads(line) for line in (tmp_path / "insider" / "events.jsonl").read_text().splitlines()]


async def test_insider_events_fill_neither_the_record_nor_memory(tmp_path, baseline):
    """Robot 3's own events key: 2,000 events of 4 KB (more than any robot's event needs: refused before they are
    decoded) and 2,000 small ones in one tick (a tick's budget recorded, the rest refused)."""
    def attack(put, keys, config, t):
        big = Event(kind="agent.note", source=3, details={"junk": "x" * 4000})
        assert len(encode(big)) > robot_event_bytes(config.n_agents)
        for _ in range(2000):
            put(keys.event(3), big)
        for k in range(2000):
            put(keys.event(3), Event(kind="agent.note", source=3, details={"k": k}))

    await _attacked(tmp_path, baseline, attack, sim_refused=0, monitor_refused=4000 - ROBOT_EVENTS_PER_TICK)
    # what a robot may legitimately say of itself: a tick's budget of events under its own name, in the record
    notes = [e for e in _events(tmp_path) if e["kind"] == "agent.note"]
    assert [(e["source"], e["details"]["k"]) for e in notes] == [(3, k) for k in range(ROBOT_EVENTS_PER_TICK)]


async def test_insider_a_robot_that_floods_past_the_cut_off_is_held_and_the_run_goes_on(tmp_path, baseline,
                                                                                         monkeypatch):
    """5,000 commitments of tick 10**9 on a picker's own key in one tick: reported at FLOOD_REFUSALS refusals, cut
    off at the cut-off (lowered here to 4,096, so the run need not take 65,536) — from then on its messages are
    refused unread and its robot is held, as a crashed robot's — and the run completes. What the cut-off changes is
    the liar's own part: its acks, and the deliveries that needed it."""
    monkeypatch.setattr(claims, "CUT_OFF_REFUSALS", 4096)
    p = _config(tmp_path, "insider").n_agvs

    def attack(put, keys, config, t):
        for k in range(5000):
            put(keys.commit(p), Commit(t=10**9, picker=p, agv=0, seq=k + 1), sender=f"agent-{p}")

    stream: list[MetricSample] = []
    run, rows, _, summary, _ = await _run(tmp_path, "insider", attack, refused_stream=stream)
    base_run, base_rows = baseline[0], baseline[1]
    # the monitor's stream names it (the rest of the fleet has nothing refused) once it floods, and its last value is
    # the record's count
    assert stream and set(stream[-1].labels) == {str(p)} and stream[-1].value == run.monitor.rejected
    assert not stream[0].labels and stream[0].value == 0
    assert run.sim.steps == STEPS and run.sim.stopped_early is None
    assert run.sim.flooding == [p] and run.sim.cut_off == [p] and base_run.sim.cut_off == []
    cut = [e for e in _events(tmp_path) if e["kind"] in ("agent.flooding", "agent.cut_off")]
    assert [(e["kind"], e["source"], e["details"]["agent"], e["details"]["refused"]) for e in cut] == [
        ("agent.flooding", "sim", p, FLOOD_REFUSALS), ("agent.cut_off", "sim", p, 4096)]
    at = cut[1]["t"]
    assert AT < at <= AT + 2  # reported at the start of the tick after the flood
    assert rows[:AT] == base_rows[:AT]  # before the attack: the same run
    # held from the cut on: every tick's acks are the other seven robots' (the monitor takes nothing of it either)
    assert all(int(r["acks"]) == 7 for r in rows[at + 1:]), [r["acks"] for r in rows[at + 1:]]
    assert all(int(r["acks"]) == 8 for r in base_rows[at + 1:])
    # its genuine messages after the cut are refused too: more than the flood itself
    assert run.sim.rejected > 5000 and summary["steps"] == STEPS


async def test_insider_new_sub_keys_under_its_own_prefix_are_refused_before_anything_is_kept_per_key(tmp_path,
                                                                                                   baseline):
    """Robot 3's own prefix admits any sub-key: 1,500 acks on made-up kinds (``agent/3/k<i>``) and 1,500 requests to
    made-up receivers. The monitor (which takes every key of the run) refuses each before counting it by kind or
    keeping a sequence number for its key; nobody else subscribes to such keys."""
    def attack(put, keys, config, t):
        ack = encode(Ack(t=t, agent=3))
        for i in range(1500):
            put(f"{keys.agent_prefix(3)[:-3]}/k{i}", ack)
            put(f"{keys.agent_prefix(3)[:-3]}/request/x{i}", ack)

    _, summary, _ = await _attacked(tmp_path, baseline, attack, sim_refused=0, monitor_refused=3000)
    assert set(summary["messages"]) == set(baseline[3]["messages"]), summary["messages"]


async def test_insider_an_agv_asks_a_picker_once_a_tick_however_often_it_sends(tmp_path, baseline):
    """AGV 3's own request key to picker 5: 3,000 requests for the current tick, numbered 1..3,000 (its genuine
    stream's numbers too). The picker takes the first — an AGV's own request is its own to make, for whatever cell
    it names — and refuses the other 2,999 unread by its decision (no thousands of answers, no copies counted, no
    genuine request later taken for a copy of a forged number)."""
    picker = _config(tmp_path, "insider").n_agvs + 1

    def attack(put, keys, config, t):
        for seq in range(1, 3001):
            put(keys.request(3, picker), HelpRequest(t=t, agv=3, picker=picker, target_x=3, target_y=4, seq=seq))

    run, rows, _, _, _ = await _run(tmp_path, "insider", attack)
    base_run, base_rows = baseline[0], baseline[1]
    assert run.sim.steps == STEPS and run.sim.stopped_early is None
    assert run.agents[picker].rejected == base_run.agents[picker].rejected + 2999
    assert rows[:AT] == base_rows[:AT]
    # what one more request of AGV 3's can change: the picker's answer to it, and what the fleet does after that
    # differently (who asks whom next); never thousands of answers or copies
    for row, base in zip(rows, base_rows):
        assert abs(int(row["dispatch_declined"]) - int(base["dispatch_declined"])) < 10
        assert int(row["dispatch_duplicates"]) == int(base["dispatch_duplicates"]) == 0
