"""Crash faults under ``morph-sim up``: real OS processes over Zenoh on loopback.

A schedule file asks for "kill agent k every 80 ticks"; the supervisor carries it out by pid (SIGKILL), restarts
the agent, which restores its brain from the monitor's latest state and rejoins. The run completes with every tick
in the record. Every wait is bounded; whatever the test started is killed by pid on failure.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from pathlib import Path

from schemas import AgentState, Event
from schemas.keys import RunKeys
from services.bus.zenoh_bus import endpoint, free_port
from services.monitor.recorder import read_metrics

from _procs import FEW_ROBOTS, alive, descendants, kill_all

UP_TIMEOUT = 150

# three robots: a kill, a restart and a restore are one agent's and the monitor's; the rest of the fleet only runs on
VICTIM = 2  # the picker (AGVs 0 and 1, picker 2)
EVERY, COLD = 80, 120  # agent VICTIM is killed at ticks 80 and 160, agent 1 at 120 for a cold restart
STEPS = 3 * EVERY
PERIOD = 0.08  # paced: the 80 ticks after each kill take 6.4 s, more than a restarted agent (a fresh interpreter) needs
# to start, restore and rejoin on a loaded machine (2.5 s were once too few; with 4 s, on three workers, one was
# restarted 1.1 s after its kill and acked its first tick 3.3 s later, 0.2 s before the next kill)


def _events(record: Path) -> list[dict]:
    return [json.loads(line) for line in (record / "events.jsonl").read_text().splitlines() if line.strip()]


async def _port_open(port: int, proc: subprocess.Popen, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            _, writer = await asyncio.wait_for(asyncio.open_connection("127.0.0.1", port), 0.5)
            writer.close()
            return True
        except (OSError, asyncio.TimeoutError):
            await asyncio.sleep(0.1)
    return False


async def test_up_kills_an_agent_every_80_ticks_and_it_rejoins_with_its_state(tmp_path):
    schedule = tmp_path / "crash.toml"
    schedule.write_text(f'[[at]]\ntick = 0\nspec = {{ id = "kill-{VICTIM}", crash = {{ agent = {VICTIM}, '
                        f'every = {EVERY} }} }}\n'
                        # and one cold restart for comparison: agent 1 between the two kills starts from zero
                        f'[[at]]\ntick = 0\nspec = {{ id = "cold-1", crash = {{ agent = 1, at_tick = {COLD}, '
                        'cold_restart = true } }\n')
    port = free_port()
    run_id = "upkill"
    argv = [sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny", "--run-id", run_id,
            "--output-dir", str(tmp_path), "--policy", "morph", "--preset", "paper", "--seed", "5",
            "--steps", str(STEPS), "--mode", "paced", "--period", str(PERIOD), "--phase-timeout", "3",
            "--state-every", "10", *FEW_ROBOTS,
            "--listen", endpoint(port), "--fault-schedule", str(schedule)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: set[int] = set()
    received: list[tuple[str, object]] = []  # ("state", AgentState) | ("restored", Event), in arrival order
    bus = None
    try:
        if not await _port_open(port, proc, 60):
            proc.kill()
            raise AssertionError(f"the sim never opened its endpoint: {proc.communicate(timeout=10)[1][-3000:]}")
        from services.process import open_bus

        # a secured run: the observer connects with the operator credentials `up` wrote into the run directory
        bus = await open_bus("test-observer", connect=endpoint(port),
                             config_file=str(tmp_path / run_id / "credentials" / "operator.json5"))
        keys = RunKeys(run_id)
        await bus.subscribe(keys.agent_state(VICTIM), lambda s: received.append(("state", s.decode(AgentState))))

        def on_event(sample) -> None:
            event = sample.decode(Event)
            if event.kind == "agent.restored":
                received.append(("restored", event))

        await bus.subscribe(keys.event(VICTIM), on_event)
        deadline = time.monotonic() + UP_TIMEOUT
        while proc.poll() is None and time.monotonic() < deadline:
            seen |= descendants(proc.pid)
            await asyncio.sleep(0.1)
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err[-3000:]
        assert "completed" in out and "3 restarts" in out, out
    finally:
        if bus is not None:
            await bus.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
        left = alive(seen | {proc.pid})
        kill_all(left)
    assert left == [], f"processes left behind: {left}"

    record = tmp_path / run_id
    rows = read_metrics(record)
    assert [int(r["t"]) for r in rows] == list(range(STEPS))  # no tick lost from the record
    events = _events(record)
    crashes = [e for e in events if e["kind"] == "agent.crash"]
    restarts = [e for e in events if e["kind"] == "agent.restart"]
    assert [(e["details"]["tick"], e["details"]["agent"]) for e in crashes] == [
        (EVERY, VICTIM), (COLD, 1), (2 * EVERY, VICTIM)]
    assert all(e["details"]["pid"] for e in crashes)
    # each crash at the tick it was due and its sim time (Δ = 1 s); the specs scheduled at tick 0 are in the record,
    # planned by the supervisor (the process that carries them out) and by no other process
    assert all(e["t"] == e["details"]["tick"] and e["sim_time"] == float(e["t"]) for e in crashes)
    planned = [e for e in events if e["kind"].startswith("fault.crash")]
    assert sorted((e["kind"], e["source"], e["details"]["fault_id"], e["t"], e["sim_time"]) for e in planned) == [
        ("fault.crash_planned", "supervisor", "cold-1", 0, 0.0),
        ("fault.crash_planned", "supervisor", f"kill-{VICTIM}", 0, 0.0)]
    assert [(e["details"]["agent"], e["details"]["planned"], e["details"]["cold"]) for e in restarts] == [
        (VICTIM, True, False), (1, True, True), (VICTIM, True, False)]
    assert not [e for e in events if e["kind"] == "agent.restored" and e["source"] == 1]  # cold: nothing restored
    assert any(e["kind"] == "agent.restored" and e["source"] == VICTIM for e in events)  # the record has them too

    # Each restarted agent resumed with the W row its predecessor published last.
    # Each subscription has its own thread here, so a restarted agent's first state may arrive before its restored
    # event: the states are told apart by process instead (one key, so in the order each process published them;
    # the numbers an agent gives its messages start again in a new process).
    restored = [e for kind, e in received if kind == "restored"]
    assert len(restored) == 2, [k for k, _ in received]
    by_process: list[list[AgentState]] = []
    for kind, state in received:
        if kind == "state":
            if not by_process or state.seq <= by_process[-1][-1].seq:
                by_process.append([])
            by_process[-1].append(state)
    assert len(by_process) == 3, [[(s.t, s.seq) for s in p] for p in by_process]
    for event, predecessor in zip(restored, by_process):
        last = predecessor[-1]
        assert event.details["from_t"] == last.t
        assert event.details["w_row"] == last.w_row
    assert any(any(e.details["w_row"]) for e in restored)  # a learnt state came back, not zeros
    froms = [e.details["from_t"] for e in restored]
    assert all(t - 10 <= f <= t + 10 for f, t in zip(froms, (EVERY, 2 * EVERY))), froms
    # after each restart the agent took part again: it published states beyond the one it restored
    assert max(s.t for kind, s in received if kind == "state") >= STEPS - 10


async def test_the_monitor_publishes_per_link_counters_every_k_ticks() -> None:
    """F3: the monitor's link/* metrics (sent, delivered, dropped … per key class) come from the samples' headers;
    a 30 % loss of acks on the monitor's own ingress shows up as dropped acks, every other class loses nothing."""
    from schemas import FaultSpec, Loss, MetricSample, Scope
    from services.agent.roles import make_agent
    from services.bus import LocalNetwork
    from services.faults.layer import FaultLayer, install
    from services.monitor.service import MonitorService
    from services.runconfig import RunConfig
    from services.sim.service import SimService

    config = RunConfig(run_id="links", scale="tiny", policy="full", seed=3, steps=200, state_every=20)
    net = LocalNetwork()
    monitor_bus = net.session("monitor")
    layer = install(monitor_bus, FaultLayer(config.run_id, base_seed=config.seed))
    # acks are synchronisation and never faulted: the loss is put on the agents' state reports the monitor receives
    layer.set(FaultSpec(id="state-loss", loss=Loss(percent=30), scope=Scope(key_expr="agent/*/state")))
    monitor = MonitorService(config, monitor_bus, record=False, max_rate=1000)
    published: list[MetricSample] = []
    observer = net.session("observer")
    await observer.subscribe(f"morph/{config.run_id}/metrics/link/**",
                             lambda s: published.append(s.decode(MetricSample)))
    agents = [make_agent(config, net.session(f"agent-{i}"), i) for i in range(config.n_agents)]
    tasks = [asyncio.create_task(a.run()) for a in agents] + [asyncio.create_task(monitor.run())]
    try:
        result = await asyncio.wait_for(SimService(config, net.session("sim")).run(), 60)
        await asyncio.wait_for(asyncio.gather(*tasks), 10)
    finally:
        for task in tasks:
            task.cancel()
    assert result.steps == 200
    links = {(s.name, s.labels["key"]): s for s in monitor.latest_links}
    assert {s.t for s in monitor.latest_links} == {180}  # the last multiple of k before the end
    sent, dropped = links[("link/sent", "agent/*/state")].value, links[("link/dropped", "agent/*/state")].value
    assert sent >= 8 * 180 // 20
    assert 0.15 < dropped / sent < 0.45  # 30 % of ~80 reports (± 3 sd)
    assert links[("link/dropped", "agent/*/ack")].value == 0
    assert links[("link/dropped", "sim/tick")].value == 0 and links[("link/sent", "sim/tick")].value >= 180
    # every k-tick snapshot reaches the bus, even when the decimated publish falls on another tick
    assert sorted({s.t for s in published if s.name == "link/sent"}) == list(range(0, 200, 20))
    assert ("link/latency/p50", "sim/tick") in links and all(s.labels["receiver"] == "monitor"
                                                             for s in monitor.latest_links)
    # the monitor's own metric streams come back to it over no link: no key class of theirs is metered
    assert published and not [key for _, key in links if key.startswith("metrics")]
