"""The shared air's pure core (services/faults/air.py): one judge of a rate-limited radio, in one order whatever
order its messages reach it in; the medium's bookkeeping of what the sim announced; a receiver's hold of a radio
message until its verdict; what the sim counts from the acks."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from schemas import RunKeys
from schemas.codec import encode
from services.faults.air import (
    ROBOTS_PART,
    SIM_PART,
    Ledger,
    Medium,
    Publication,
    VerdictBook,
    dispatch_size,
    has_shared_capacity,
    kind_of,
    receivers_of,
)
from services.faults.network import Fate, NetworkModel, load_profile
from services.sim import air as sim_air
from services.world.layout import LayoutConfig, layout_for

SATURATED = str(Path(__file__).parent / "data" / "saturated.toml")
N = 8  # tiny: 5 AGVs, 3 pickers


def _model(seed: int = 3) -> NetworkModel:
    model = NetworkModel(load_profile(SATURATED), layout_for(LayoutConfig.named("tiny")), seed=seed)
    model.observe_tick(0, 1.0, [(1 + r, 2) for r in range(N)])
    return model


def _traffic(ticks: int = 6) -> list[Publication]:
    """A few ticks of a tiny fleet's radio: a fleet broadcast per tick (big enough to fill the queues), every AGV's
    request to one picker, the pickers' replies."""
    pubs = []
    for t in range(ticks):
        pubs.append(Publication(float(t), "sim", "sim/fleet", t, tuple(range(N)), 420))
        for agv in range(5):
            pubs.append(Publication(float(t), agv, f"agent/{agv}/request/{5 + agv % 3}", t, (5 + agv % 3,),
                                    dispatch_size("request")))
        for picker in range(5, 8):
            pubs.append(Publication(t + 0.5, picker, f"agent/{picker}/reply/{picker - 5}", t, (picker - 5,),
                                    dispatch_size("reply")))
    return pubs


def test_the_medium_gives_the_same_verdicts_whatever_order_it_is_given_them():
    pubs = _traffic()
    first = Medium(_model()).judge(pubs)
    shuffled = pubs[:]
    random.Random(7).shuffle(shuffled)
    assert Medium(_model()).judge(shuffled) == first
    causes = {v.cause for v in first}
    assert {"link_queue", "ap_queue"} & causes, causes  # queues overflowed: the order decides who gets in
    # ... and it does: the same messages fed to the model in another order get other verdicts
    model = _model()
    other = [model.fate(p.sent_at, p.publisher, r, ((p.publisher, p.seq), p.key), size=p.size)
             for p in reversed(sorted(pubs, key=Publication.order)) for r in p.receivers]
    assert sorted(map(str, other)) != sorted(str(v.fate) for v in first)


def test_a_part_is_judged_once_all_it_announced_has_arrived_and_parts_in_their_order():
    pubs = _traffic(2)
    ledger = Ledger(Medium(_model()))
    fleet0, *robots0 = [p for p in pubs if p.sent_at == 0.0]
    # the robots' requests arrive before anything was announced: nothing is judged
    assert all(ledger.arrive(p) == [] for p in robots0)
    assert ledger.announce(0.0, SIM_PART, {("sim", "sim/fleet"): 1}) == []  # the fleet broadcast is not here yet
    assert ledger.waiting_for() == {("sim", "sim/fleet"): 1}
    sim_part = ledger.arrive(fleet0)
    assert {v.key for v in sim_part} == {"sim/fleet"} and len(sim_part) == N
    counts = {}
    for p in robots0:
        counts[(p.publisher, p.key)] = counts.get((p.publisher, p.key), 0) + 1
    robots_part = ledger.announce(0.0, ROBOTS_PART, counts)
    assert len(robots_part) == len(robots0) and ledger.judged == 1 + len(robots0)
    # the same verdicts as one judge of everything in order
    assert sim_part + robots_part == Medium(_model()).judge([fleet0, *robots0])


def test_a_ledger_equals_the_one_judge_of_the_whole_traffic():
    pubs = _traffic(4)
    ledger = Ledger(Medium(_model()))
    got = []
    for instant in sorted({p.sent_at for p in pubs}):
        here = [p for p in pubs if p.sent_at == instant]
        for part in (SIM_PART, ROBOTS_PART):
            mine = [p for p in here if (p.publisher == "sim") == (part == SIM_PART)]
            counts = {}
            for p in mine:
                counts[(p.publisher, p.key)] = counts.get((p.publisher, p.key), 0) + 1
            for p in reversed(mine):  # arrivals in any order, before their announcement
                got += ledger.arrive(p)
            got += ledger.announce(instant, part, counts)
    assert got == Medium(_model()).judge(pubs) and ledger.strays == 0


def test_an_unannounced_publication_is_judged_late_and_counted_and_a_missing_one_can_be_given_up():
    ledger = Ledger(Medium(_model()))
    fleet = Publication(0.0, "sim", "sim/fleet", 0, tuple(range(N)), 420)
    ledger.announce(0.0, SIM_PART, {("sim", "sim/fleet"): 1})
    assert len(ledger.arrive(fleet)) == N
    late = Publication(0.0, "sim", "sim/refusal/3", 0, (3,), dispatch_size("refusal"))
    assert len(ledger.arrive(late)) == 1 and ledger.strays == 1  # its instant's sim part was judged: at once
    # a robot announced a request it never sent: the part waits until the driver gives up on it
    assert ledger.announce(0.0, ROBOTS_PART, {(2, "agent/2/request/6"): 1}) == []
    assert ledger.waiting_for() == {(2, "agent/2/request/6"): 1}
    assert ledger.force() == [] and ledger.parts == [] and ledger.waiting_for() == {}


def test_a_receiver_holds_a_message_until_its_verdict_and_keeps_both_bounded():
    book = VerdictBook(limit=4)
    ident = ("sim", "sim/fleet", 7)
    assert book.take(ident) is None
    book.park(ident, "copy-a")
    book.park(ident, "copy-b")  # two subscriptions of one process that take the same message
    assert book.verdict(ident, Fate(7.3)) == ["copy-a", "copy-b"]
    assert book.take(ident) == Fate(7.3)  # a later copy finds it
    for seq in range(10):
        book.verdict(("sim", "sim/fleet", 100 + seq), Fate(None, "ap_queue"))
        book.park((3, "agent/3/request/6", seq), "x")
    assert len(book.verdicts) <= 4 and len(book.parked) <= 4 and book.dropped > 0


def test_kinds_receivers_and_capacity():
    assert [kind_of(k) for k in ("sim/fleet", "sim/refusal/3", "agent/1/request/6", "agent/6/reply/1",
                                 "agent/6/commit", "agent/2/policy/all", "agent/1/ack", "sim/tick")] == [
        "fleet", "refusal", "request", "reply", "commit", "policy", "", ""]
    assert receivers_of("sim/fleet", "sim", 3) == (0, 1, 2)
    assert receivers_of("agent/1/policy/all", 1, 3) == (0, 2)
    assert receivers_of("agent/6/commit", 6, 8) == ("sim",)
    assert receivers_of("agent/1/request/6", 1, 8) == (6,)
    assert has_shared_capacity(load_profile("congested")) and has_shared_capacity(load_profile(SATURATED))
    assert not has_shared_capacity(load_profile("wifi-legacy-roaming")) and not has_shared_capacity(None)


def test_the_sim_announces_what_the_acks_say_was_published():
    counts: dict = {}
    keys = RunKeys("r")
    sim_air.tick_publications(keys, 2, [6, 7, 99], [-1, 5, 1000], N, counts)  # ids outside the fleet sent nothing
    sim_air.resolve_publications(keys, 6, 2, [2, 3], N, counts)
    sim_air.refusal_publications(keys, [2, 6], counts)
    (msg,) = sim_air.announcements(4.0, ROBOTS_PART, counts)
    got = {(p, k): c for p, k, c in zip(msg.publishers, msg.keys, msg.counts)}
    assert got == {(2, "agent/2/request/6"): 1, (2, "agent/2/request/7"): 1, (2, "agent/2/policy/all"): 1,
                   (2, "agent/2/policy/5"): 1, (6, "agent/6/commit"): 1, (6, "agent/6/reply/2"): 1,
                   (6, "agent/6/reply/3"): 1, (-1, "sim/refusal/2"): 1, (-1, "sim/refusal/6"): 1}
    assert msg.publishers == sorted(msg.publishers) and not msg.more
    # a broadcasting policy's requests at 128 robots: thousands of keys, in messages of bounded size
    many = {(agv, f"agent/{agv}/request/{p}"): 1 for agv in range(96) for p in range(96, 128)}
    msgs = sim_air.announcements(4.0, ROBOTS_PART, many)
    assert [m.more for m in msgs] == [True] * (len(msgs) - 1) + [False] and len(msgs) == 12
    assert sum(len(m.keys) for m in msgs) == len(many) and all(len(encode(m)) < 32 * 1024 for m in msgs)


@pytest.mark.parametrize("value", ["congested", SATURATED])
def test_a_shared_air_profile_is_refused_only_in_a_paced_run(value, tmp_path):
    from services.runconfig import RunConfig

    assert RunConfig(network=value, output_dir=tmp_path).shared_air
    with pytest.raises(ValueError, match="use --mode lockstep"):
        RunConfig(network=value, mode="paced", output_dir=tmp_path)


def test_a_verdict_counts_only_from_the_air():
    """A robot's own session publishing on another receiver's verdict key (the access control forbids it over Zenoh;
    in one process nothing does) releases nothing and is counted."""
    from schemas import AirVerdicts
    from schemas.codec import encode as enc
    from services.bus.base import Sample
    from services.faults.layer import FaultLayer

    layer = FaultLayer("r")
    layer.air = VerdictBook()
    released = []
    layer.air.park(("sim", "sim/fleet", 3), (Sample("k", b"", "sim", 3, 3.0), "agent-1", released.append))
    forged = enc(AirVerdicts(publishers=[-1], keys=["sim/fleet"], seqs=[3], at=[3.5], causes=[None]))
    layer.on_verdicts(Sample("morph/r/air/verdict/1", forged, "agent-4", 0, 3.0))
    assert layer.air_refused == 1 and layer.air.take(("sim", "sim/fleet", 3)) is None and not released


async def test_the_air_refuses_a_stamp_beyond_the_run_and_keeps_nothing_of_it(tmp_path):
    """A robot stamping its message far in the future (its own key, its own credentials) would keep it waiting in
    the air for a part that never comes: refused on arrival, counted. Its event claiming the sim's end of the run
    does not stop the air."""
    import asyncio

    from schemas import Event, HelpRequest, RunKeys
    from services.air.service import AirService
    from services.bus import LocalNetwork
    from services.runconfig import RunConfig

    cfg = RunConfig(run_id="r", network="congested", output_dir=tmp_path)
    net = LocalNetwork()
    air = AirService(cfg, net.session("air"))
    task = asyncio.create_task(air.run())
    robot = net.session("agent-2")
    robot.set_clock(lambda: 1e6)
    await asyncio.sleep(0.05)
    robot.put(RunKeys("r").request(2, 6), HelpRequest(t=5, agv=2, picker=6, target_x=1, target_y=1, seq=0))
    await asyncio.sleep(0.05)
    assert air.intake.refused == 1 and not air.ledger.arrived
    robot.put(RunKeys("r").event(2), Event(kind="run.finished", source="sim"))
    await asyncio.sleep(0.05)
    assert not task.done()
    air.stop()
    await asyncio.wait_for(task, 5)


async def test_a_part_announced_and_never_whole_is_judged_after_a_phase_timeout(tmp_path):
    """A robot whose ack claims a request it never sent (its own credentials) holds the air's instant open: after a
    phase timeout the air judges the part with what arrived, and the next part gets its own clock."""
    import asyncio

    from schemas import RunKeys
    from services.air.service import AirService
    from services.bus import LocalNetwork
    from services.runconfig import RunConfig
    from services.sim.air import announcements

    cfg = RunConfig(run_id="r", network="congested", output_dir=tmp_path, phase_timeout=0.4)
    net = LocalNetwork()
    air = AirService(cfg, net.session("air"))
    task = asyncio.create_task(air.run())
    sim = net.session("sim")
    await asyncio.sleep(0.05)
    keys = RunKeys("r")
    for msg in announcements(0.0, ROBOTS_PART, {(2, "agent/2/request/6"): 1}):  # claimed, never sent
        sim.put(keys.air_parts, msg)
    for msg in announcements(0.5, ROBOTS_PART, {}):  # whole at once, behind it
        sim.put(keys.air_parts, msg)
    await asyncio.sleep(0.1)
    assert air.ledger.waiting_for() == {(2, "agent/2/request/6"): 1}  # held open, for now
    for _ in range(40):
        await asyncio.sleep(0.05)
        if not air.ledger.parts:
            break
    assert not air.ledger.parts and air.ledger.judged_through == (0.5, ROBOTS_PART)
    air.stop()
    await asyncio.wait_for(task, 5)
