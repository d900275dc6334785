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
from schemas import Ack, AgentState, Commit, encode
from schemas.keys import RunKeys
from services.bus.base import Sample
from services.bus.local import LocalNetwork
from services.monitor.recorder import read_metrics
from services.protocol.claims import SEQ_WINDOW
from services.protocol.dispatch import MAX_HELD_PER_PICKER
from services.runconfig import RunConfig

STEPS = 80  # the attack at tick AT, then 50 ticks of the run that must not take any of it
AT = 30  # the tick the attack lands at: the run is under way, rows before and after it are compared


def _config(tmp_path, run_id: str) -> RunConfig:
    return RunConfig(run_id=run_id, scale="tiny", policy="morph", steps=STEPS, seed=42, output_dir=tmp_path,
                     state_every=10, snapshot_every=20)


async def _run(tmp_path, run_id: str, attack=None):
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
