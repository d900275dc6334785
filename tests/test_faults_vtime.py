"""Virtual time (docs/faults.md) on the real LocalBus: a message sent at sim time s with latency L is delivered at
the first phase boundary at or after s + L, late if that is after its phase's deadline; runs are deterministic; the
link meter measures what arrived. Wall-time mode sleeps for real."""

from __future__ import annotations

import asyncio
import time

import pytest

from schemas import FaultSpec, Latency, Loss, RunKeys
from schemas.faults import Duplicate
from services.bus import LocalNetwork
from services.faults.layer import FaultLayer, install
from services.faults.linkstats import LinkMeter, key_class
from services.faults.vtime import VirtualTime, boundaries, release_boundary

from _procs import until

K = RunKeys("vt")


async def drain() -> None:
    for _ in range(5):  # LocalBus delivers with call_soon: a few loop turns flush everything in flight
        await asyncio.sleep(0)


async def scripted_run(spec: FaultSpec | None, *, ticks: int = 20, dt: float = 1.0, seed: int = 0,
                       senders: tuple[str, ...] = ("3",)) -> tuple[list[tuple[float, str, int, bool]], LinkMeter]:
    """Senders publish one ack per tick at the tick's start; the receiver ("sim") logs (sim time of delivery,
    sender, seq, late) and the phase loop advances virtual time over every boundary, as the sim clock does."""
    net = LocalNetwork()
    vt = VirtualTime(dt=dt)
    meter = LinkMeter(K.prefix)
    receiver = net.session("sim")
    layer = install(receiver, FaultLayer("vt", base_seed=seed, vtime=vt, meter=meter))
    if spec is not None:
        layer.set(spec)
    pubs = [net.session(s) for s in senders]
    for p in pubs:
        p.set_clock(vt.now)
    log: list[tuple[float, str, int, bool]] = []
    await receiver.subscribe(K.commits, lambda s: log.append((vt.now(), s.sender, s.seq, vt.is_late(s.sent_at))))
    for t in range(ticks):
        start, tick_deadline, _ = boundaries(t, dt)
        vt.advance(start)
        for p in pubs:
            await p.publish(K.commit(int(p.identity)), b"ack")
        await drain()
        vt.advance(tick_deadline)  # the sim closes the TICK phase
        await drain()
    for extra in range(ticks, ticks + 3):  # let what is still in flight land
        vt.advance(boundaries(extra, dt)[0])
    await drain()
    for bus in (receiver, *pubs):
        await bus.close()
    return log, meter


def test_release_boundary_is_the_first_boundary_at_or_after() -> None:
    assert release_boundary(0.0, 1.0) == 0.0
    assert release_boundary(0.3, 1.0) == 0.5
    assert release_boundary(0.5, 1.0) == 0.5
    assert release_boundary(0.1 + 0.2 + 0.2, 1.0) == 0.5  # float sums land on the boundary they mean
    assert release_boundary(0.51, 1.0) == 1.0
    assert release_boundary(7.2, 5.0) == 7.5
    assert boundaries(3, 2.0) == (6.0, 7.0, 8.0)


def test_hold_releases_in_due_then_identity_order_and_time_never_goes_back() -> None:
    vt = VirtualTime(dt=1.0)
    out: list[str] = []
    assert vt.hold(0.0, lambda: out.append("now"))  # due already: runs at once
    vt.hold(0.8, lambda: out.append("b"), order=("b",))
    vt.hold(0.8, lambda: out.append("a"), order=("a",))
    vt.hold(0.4, lambda: out.append("early"))
    assert out == ["now"] and vt.pending == 3
    assert vt.advance(0.5) == 1 and out == ["now", "early"]
    assert vt.advance(0.2) == 0 and vt.now() == 0.5  # an old boundary (a duplicated Tick) changes nothing
    assert vt.advance(1.0) == 2 and out == ["now", "early", "a", "b"]


@pytest.mark.parametrize(("delay", "released_offset", "late"), [
    (0.0, 0.0, False),   # no latency: delivered in its own phase at once
    (0.3, 0.5, False),   # waits for the TICK deadline boundary, still on time
    (0.5, 0.5, False),   # exactly at the deadline is not after it
    (0.6, 1.0, True),    # next boundary is after the phase's deadline: late
    (1.7, 2.0, True),
])
async def test_latency_lands_on_the_first_boundary_at_or_after_send_plus_latency(
        delay: float, released_offset: float, late: bool) -> None:
    log, meter = await scripted_run(FaultSpec(latency=Latency(delay=delay)), ticks=6)
    assert len(log) == 6
    for when, sender, seq, was_late in log:
        assert when == pytest.approx(seq * 1.0 + released_offset)
        assert was_late is late and sender == "3"
    report = meter.report()["agent/*/commit"]
    assert report.sent == report.delivered == 6 and report.late == (6 if late else 0)
    assert report.latency["p50"] == pytest.approx(released_offset)  # measured in sim seconds, boundary-quantised


async def test_same_seed_same_faults_give_the_same_run_twice() -> None:
    spec = FaultSpec(loss=Loss(percent=30), latency=Latency(delay=0.6, jitter=0.5, distribution="normal"),
                     duplicate=Duplicate(percent=10))
    senders = ("1", "2", "3", "4")
    first, m1 = await scripted_run(spec, ticks=60, seed=9, senders=senders)
    second, m2 = await scripted_run(spec, ticks=60, seed=9, senders=senders)
    other, _ = await scripted_run(spec, ticks=60, seed=10, senders=senders)
    assert first == second and m1.report() == m2.report()
    assert first != other
    r = m1.report()["agent/*/commit"]
    assert r.dropped > 0 and r.duplicated > 0 and 0 < r.late < r.delivered


async def test_meter_counts_match_the_fault_layer() -> None:
    log, meter = await scripted_run(FaultSpec(loss=Loss(percent=25)), ticks=400, seed=3)
    r = meter.report()["agent/*/commit"]
    # the last message may be lost unseen; otherwise sent is exact
    assert r.sent in (399, 400) and r.delivered == len(log) and r.duplicated == 0
    assert r.dropped == r.sent - len(log) and abs(r.loss_rate - 0.25) < 0.06
    names = {(m.name, m.labels["key"]) for m in meter.metrics(400, 400.0)}
    assert ("link/dropped", "agent/*/commit") in names and ("link/latency/p90", "agent/*/commit") in names


def test_link_meter_from_sequence_numbers_alone() -> None:
    m = LinkMeter("morph/r")
    for seq in (0, 1, 1, 4, 3):  # 2 missing, 1 duplicated, 4 before 3 (reordered)
        m.record("morph/r/agent/5/request/9", "5", seq, sent_at=float(seq), received_at=seq + 0.5, late=seq == 4)
    m.record("morph/r/agent/6/request/9", "6", 0, sent_at=0.0, received_at=2.0)
    r = m.report()["agent/*/request/*"]
    assert (r.sent, r.delivered, r.dropped, r.duplicated, r.late) == (6, 6, 1, 1, 1)
    assert r.latency["max"] == 2.0 and r.latency["p50"] == 0.5
    assert key_class(["sim", "tick"]) == "sim/tick"


async def test_auto_heal_happens_at_a_boundary_in_sim_seconds() -> None:
    changes: list[tuple[str, float]] = []
    vt = VirtualTime(dt=1.0)
    layer = FaultLayer("vt", vtime=vt, on_change=lambda what, f: changes.append((what, vt.now())))
    layer.set(FaultSpec(id="cut", loss=Loss(percent=100), duration=2.5))
    for b in (0.5, 1.0, 1.5, 2.0, 2.5, 3.0):
        vt.advance(b)
    assert changes == [("set", 0.0), ("healed", 2.5)]


async def test_wall_time_mode_sleeps_for_real() -> None:
    net = LocalNetwork()
    sender, receiver = net.session("2"), net.session("sim")
    layer = install(receiver, FaultLayer("vt", meter=LinkMeter(K.prefix)))
    layer.set(FaultSpec(latency=Latency(delay=0.05)))
    got: list[float] = []
    await receiver.subscribe(K.commits, lambda s: got.append(time.monotonic()))
    t0 = time.monotonic()
    await sender.publish(K.commit(2), b"x")
    await asyncio.sleep(0.01)
    assert got == []
    await until(lambda: got, what="the delayed message")
    assert len(got) == 1 and got[0] - t0 >= 0.045
    assert layer.meter.report()["agent/*/commit"].latency["max"] >= 0.045
    await sender.close()
    await receiver.close()


async def test_a_sessions_own_publications_are_delivered_but_not_metered_as_a_link() -> None:
    net = LocalNetwork()
    vt = VirtualTime(dt=1.0)
    meter = LinkMeter(K.prefix, "sim")
    sim = net.session("sim")
    install(sim, FaultLayer("vt", base_seed=0, vtime=vt, meter=meter))
    agent = net.session("3")
    agent.set_clock(vt.now)
    got: list[str] = []
    await sim.subscribe(K.commits, lambda s: got.append(s.sender))
    await agent.publish(K.commit(3), b"x")
    await sim.publish(K.commit(4), b"y")  # a key anyone may subscribe to, here published by the receiver itself
    await drain()
    assert sorted(got) == ["3", "sim"]
    assert meter.report()["agent/*/commit"].delivered == 1
    for bus in (sim, agent):
        await bus.close()
