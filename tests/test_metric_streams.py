"""Metric streams: every documented stream is published by the monitor, versioned, with tick and time."""

from __future__ import annotations

import asyncio

import pytest

from morph_sim.local import run_local
from schemas import MetricSample
from services.bus.local import LocalNetwork
from services.metrics.catalogue import BY_NAME, NAMES
from services.monitor.streams import Decimator, Histogram, MessageStats, subscribe_metrics
from services.runconfig import RunConfig

from _procs import until


async def test_every_documented_stream_is_published_during_a_run(tmp_path):
    config = RunConfig(run_id="streams", scale="tiny", steps=60, policy="morph", output_dir=tmp_path)
    net = LocalNetwork()
    seen: dict[str, list[MetricSample]] = {}
    watcher = net.session("watcher")
    await subscribe_metrics(watcher, config.run_id, lambda m: seen.setdefault(m.name, []).append(m))
    run = await run_local(config, network=net)
    await until(lambda: seen.get("deliveries_total") and seen["deliveries_total"][-1].t == config.steps - 1,
                what="the final samples")
    await watcher.close()
    # net/* exist only under a network profile (--network): tests/test_network_services.py
    missing = set(NAMES) - set(seen) - {n for n in NAMES if n.startswith("net/")}
    assert not missing, f"documented but never published: {sorted(missing)}"
    for name, samples in seen.items():
        assert name in NAMES, name
        assert {s.unit for s in samples} == {BY_NAME[name].unit}, f"{name}: the catalogue's unit on the wire"
        s = samples[-1]
        assert s.v == MetricSample.VERSION and s.t >= 0 and s.sim_time >= 0
    assert seen["deliveries_total"][-1].value == run.monitor.deliveries_total
    assert seen["latency_seconds"][-1].values and len(seen["latency_seconds"][-1].values) == 3
    assert seen["drops_total"][-1].value == 0  # LocalBus loses nothing: the sequence-gap count must say so
    assert int(seen["messages_total"][-1].labels["sim"]) >= 60  # ticks (and resolves) of the sim


async def test_the_monitor_decimates_its_publications(tmp_path):
    config = RunConfig(run_id="decim", scale="tiny", steps=80, policy="full", output_dir=tmp_path)
    net = LocalNetwork()
    count = {"n": 0}
    watcher = net.session("watcher")

    def on(m):
        if m.name == "links":
            count["n"] += 1

    await subscribe_metrics(watcher, config.run_id, on)
    t0 = asyncio.get_running_loop().time()
    await run_local(config, network=net)
    elapsed = asyncio.get_running_loop().time() - t0
    # the monitor's default is 10 updates/s per stream, plus the final flush
    assert 1 <= count["n"] <= 10 * elapsed + 2 < 80


def test_the_decimator_passes_at_most_max_rate_per_stream():
    now = [0.0]
    dec = Decimator(2.0, clock=lambda: now[0])
    passed = []
    for i in range(100):  # 100 samples over 1 s for each of two streams
        now[0] = i / 100
        for name in ("links", "eta"):
            if dec.admit(MetricSample(name=name, t=i, sim_time=float(i), value=1.0)):
                passed.append(name)
    assert passed.count("links") == 2 and passed.count("eta") == 2
    assert dec.pending["links"].t == 99  # the newest suppressed sample is kept for a final flush
    with pytest.raises(ValueError, match="max_rate"):
        Decimator(-1)


def test_message_stats_count_sequence_gaps_dispatch_delay_and_buckets():
    st = MessageStats(n_agents=4, dt=1.0)
    for seq in (1, 2, 5, 6):
        st.observe("ack", "k/a", "agent-0", seq, 0.0)
    assert st.gaps == 2 and st.total == 4
    st.requested(3, agv=1)
    st.requested(4, agv=1)  # still the first request counts
    st.committed(7, agv=1)
    assert st.dispatch.count == 1 and st.dispatch.sum == 4.0
    h = Histogram((0.1, 1.0))
    for v in (0.05, 0.1, 0.5, 3.0):
        h.observe(v)
    assert h.cumulative() == [("0.1", 2), ("1.0", 3), ("+Inf", 4)]


def _sustain(live_run, tmp_path, scale: str, agvs: int, pickers: int, steps: int) -> dict:
    """Run ``up`` with every agent publishing its state every tick; the monitor must count every message."""
    import json
    import time

    run_id = f"sustain-{agvs + pickers}"
    t0 = time.monotonic()
    up = live_run(run_id, "--agvs", str(agvs), "--pickers", str(pickers), "--steps", str(steps), "--state-every",
                  "1", "--phase-timeout", "60", scale=scale, listen=False)
    assert up.wait(1500) == 0, up.stdout()[-2000:] + up.stderr()[-2000:]
    elapsed = time.monotonic() - t0
    summary = json.loads((tmp_path / run_id / "summary.json").read_text())
    n = agvs + pickers
    assert summary["steps"] == steps and summary["rejected"] == 0
    assert summary["sequence_gaps"] == 0  # nothing lost on the way to the monitor, counted per sender and key
    assert summary["messages"]["state"] == n * (steps + 1)  # every state of every agent, every tick
    assert summary["messages"]["ack"] >= n * (steps + 1)
    summary["elapsed"] = elapsed
    print(f"{n} agents, {steps} ticks in {elapsed:.1f} s: {sum(summary['messages'].values())} messages, "
          f"0 gaps, 0 rejects")
    return summary


def test_the_monitor_counts_every_state_of_a_small_run(live_run, tmp_path):
    _sustain(live_run, tmp_path, "tiny", 5, 3, 100)


@pytest.mark.slow
def test_the_monitor_sustains_a_64_agent_run_with_no_drops(live_run, tmp_path):
    _sustain(live_run, tmp_path, "large", 42, 22, 60)


def test_the_run_s_final_samples_go_out_without_loss_even_behind_a_publication_under_way():
    # the run ends while a droppable publication of a backlog is going out: the run's final samples, queued meanwhile,
    # must go out without loss, whichever publication takes them (a client once ended 13 rows short of the run)
    from services.monitor.streams import StreamPublisher, sample

    sent: list[tuple[str, int, bool]] = []

    class Bus:
        async def publish(self, key, s, droppable):
            sent.append((s.name, s.t, droppable))
            await asyncio.sleep(0)  # the transport's turn: other tasks run between samples

    class Keys:
        def metric(self, name):
            return f"metrics/{name}"

    async def scenario():
        pub = StreamPublisher(Bus(), Keys(), None, None, None, dt=0.1, state_every=1, max_rate=0)
        pub._pending = [sample(name, t, t * 0.1, value=float(t)) for t in range(50) for name in ("deliveries", "links")]
        under_way = asyncio.create_task(pub.publish_pending())
        await asyncio.sleep(0)  # the backlog starts going out
        pub.latest_metric = {name: sample(name, 299, 29.9, value=299.0) for name in ("deliveries", "links")}
        pub.finish()
        await pub.publish_pending(force=True, lossless=True)
        await under_way
        return pub

    pub = asyncio.run(scenario())
    finals = [(name, droppable) for name, t, droppable in sent if t == 299]
    assert sorted(finals) == [("deliveries", False), ("links", False)]
    assert sent[0][2] is True  # the backlog went out droppable while the run was on
    assert pub.published_lossless >= 2
