"""The position-dependent network model (services/faults/network.py) and its named profiles (schemas/network.py)."""

from __future__ import annotations

import math

import pytest

from schemas.network import NetworkProfile, Placement, Rate, parse_profile
from services.faults.network import NetworkModel, default_access_points, load_profile, profile_names
from services.world.layout import LayoutConfig, layout_for

TINY = layout_for(LayoutConfig.named("tiny"))  # 14 × 15; default APs at x = 3, 10 and y = 3.25, 10.75


def quiet(name: str, **update) -> NetworkProfile:
    """A named profile with its per-leg loss and dead zones off, so only what a test looks at can lose messages."""
    return load_profile(name).model_copy(update={"loss": 0.0, "dead_zones": [], **update})


def drive_along_row(model: NetworkModel, robot: int, y: int, step: float = 1.0) -> None:
    """The robot drives x = 0 .. W-1 along row ``y``, one cell per ``step`` sim seconds."""
    for x in range(TINY.W):
        model.move(robot, x * step, (x, y))


def test_named_profiles_validate_and_bad_ones_name_the_field():
    assert set(profile_names()) >= {"lan", "wifi-fast-roaming", "wifi-legacy-roaming", "congested", "lossy-mesh"}
    for name in profile_names():
        assert load_profile(name).name == name
    with pytest.raises(ValueError, match="unknown profile 'wifi'"):
        load_profile("wifi")
    with pytest.raises(ValueError, match=r"handover\.outage\.delay"):
        parse_profile({"name": "x", "handover": {"outage": {"delay": -1}}})
    with pytest.raises(ValueError, match=r"ap_rate\.rate"):
        parse_profile({"name": "x", "ap_rate": {"rate": 0}})
    with pytest.raises(ValueError, match="dead_zones"):
        parse_profile({"name": "x", "dead_zones": [{"region": "cells", "loss": 5}]})


def test_no_access_points_means_nobody_roams():
    model = NetworkModel(load_profile("lan"), TINY, seed=0)
    drive_along_row(model, 0, y=0)
    assert model.events == [] and not model.fate(3.0, 0, "sim", "m").lost


def test_judged_by_where_the_robot_was_when_it_sent_whatever_was_reported_since():
    """Tick t's cells take effect at (t+1)·Δ: a message of tick t is judged the same whether the receiving process
    has seen tick t's Tick yet or not (distributed runs see them in wall order)."""
    profile = load_profile("wifi-legacy-roaming")
    rack = next((x, y) for y in range(TINY.H) for x in range(TINY.W) if not TINY.highway[y, x])
    cells_t0 = [(0, 0), (13, 0)]
    cells_t1 = [rack, (0, 0)]  # robot 0 drives into a dead zone, robot 1 across to the other AP

    def judged(early: bool):
        model = NetworkModel(profile, TINY, seed=9)
        model.observe_tick(0, 1.0, cells_t0)
        if early:
            model.observe_tick(1, 1.0, cells_t1)
        fates = [model.fate(1.0 + k * 0.1, r, "sim", (r, k)) for r in (0, 1) for k in range(10)]
        if not early:
            model.observe_tick(1, 1.0, cells_t1)
        return fates, [(e.robot, e.time) for e in model.events]

    assert judged(True) == judged(False)
    assert judged(True)[1] == [(1, 2.0)]  # robot 1's hand-over starts one step after the Tick that shows it
    tiny = default_access_points(TINY, 12.0)
    assert tiny.tolist() == [[3.0, 3.25], [10.0, 3.25], [3.0, 10.75], [10.0, 10.75]]
    large = layout_for(LayoutConfig.named("extralarge"))
    aps = default_access_points(large, 12.0)
    assert len(aps) == 12 and aps[:, 0].max() < large.W and aps[:, 1].max() < large.H


def test_crossing_an_ap_boundary_loses_exactly_the_handover_window():
    def run(seed: int):
        model = NetworkModel(quiet("wifi-legacy-roaming"), TINY, seed=seed)
        drive_along_row(model, 0, y=0)
        assert len(model.events) == 1
        event = model.events[0]
        # hysteresis 2 cells: the nearest AP changes past x = 6.5, the hand-over happens at x = 8 (d 5.96 vs 3.82)
        assert (event.from_ap, event.to_ap, event.time) == (0, 1, 8.0)
        assert 1.2 <= event.outage <= 4.7  # the profile's uniform 1.2–4.7 s
        sends = [i * 0.01 for i in range(0, 2000)]  # 0 .. 20 s, a message every 10 ms, robot → sim
        lost = [s for s in sends if model.fate(s, 0, "sim", ("agent/0/ack", round(s * 100))).lost]
        window = [s for s in sends if event.time <= s < event.end]
        assert lost == window
        assert model.stats.lost["handover"] == len(window)
        # and downlink: the sim's messages to the robot are lost in the same window
        down = [s for s in sends if model.fate(s, "sim", 0, ("tick", round(s * 100))).lost]
        assert down == window
        return event.outage

    first = run(7)
    assert run(7) == first  # same seed ⇒ same window
    assert run(8) != first  # the outage is a draw, not a constant


def test_hysteresis_stops_ping_pong_on_the_bisector():
    model = NetworkModel(quiet("wifi-legacy-roaming"), TINY, seed=1)
    for k in range(50):  # back and forth across the bisector x = 6.5 between the two upper APs
        model.move(0, float(k), (6 + k % 2, 0))
    assert model.events == []
    zero = NetworkModel(quiet("wifi-legacy-roaming",
                              handover=load_profile("wifi-legacy-roaming").handover.model_copy(
                                  update={"hysteresis": 0.0})), TINY, seed=1)
    for k in range(50):
        zero.move(0, float(k), (6 + k % 2, 0))
    assert len(zero.events) == 49


def test_delayed_handover_holds_messages_until_the_radio_is_back():
    profile = quiet("lossy-mesh", latency=load_profile("lan").latency)
    assert profile.handover.during == "delayed"
    model = NetworkModel(profile, TINY, seed=3)
    drive_along_row(model, 0, y=0)
    event = model.events[0]
    fate = model.fate(event.time + 0.001, 0, "sim", "m1")
    assert fate.delivered_at == pytest.approx(event.end)
    assert model.fate(event.end + 0.5, 0, "sim", "m2").delivered_at == pytest.approx(event.end + 0.5)


@pytest.mark.parametrize("zone_loss", [5.0, 10.0, 30.0])
def test_dead_zone_loss_within_one_point_over_10000_messages(zone_loss):
    base = quiet("wifi-legacy-roaming")
    zone = load_profile("wifi-legacy-roaming").dead_zones[0].model_copy(update={"loss": zone_loss})
    model = NetworkModel(base.model_copy(update={"dead_zones": [zone]}), TINY, seed=11)
    rack = next((x, y) for y in range(TINY.H) for x in range(TINY.W) if not TINY.highway[y, x])
    model.move(0, 0.0, rack)
    n = 10_000
    lost = sum(model.fate(i * 0.1, 0, "sim", ("agent/0/ack", i)).lost for i in range(n))
    assert abs(100.0 * lost / n - zone_loss) <= 1.0
    assert model.stats.lost["dead_zone"] == lost
    # on the highway next to it, nothing is lost
    model.move(0, n * 0.1, (0, 0))
    assert not any(model.fate(n * 0.1 + i * 0.1, 0, "sim", ("agent/0/ack", n + i)).lost for i in range(1000))


def test_draws_do_not_depend_on_the_order_messages_are_judged():
    profile = load_profile("wifi-legacy-roaming")
    msgs = [(i * 0.05, i % 5, "sim" if i % 3 else (i + 1) % 5, ("k", i)) for i in range(2000)]

    def fates(order):
        model = NetworkModel(profile, TINY, seed=5)
        for r in range(5):
            model.move(r, 0.0, (1 + 2 * r, 5))  # robots 0..4 parked; robot 1's cell (3, 5) is a rack cell
        return {m[3]: model.fate(*m) for m in order}

    assert fates(msgs) == fates(list(reversed(msgs)))


def test_link_rate_delivers_at_most_r_per_second_and_queues_or_drops_the_rest():
    rate = 10.0  # messages per sim second (1-byte messages at 10 B/s)
    offered = 50  # per sim second, for 10 s
    sends = [i / offered for i in range(offered * 10)]

    def run(limit: int):
        profile = quiet("lan", link_rate=Rate(rate=rate, limit=limit))
        model = NetworkModel(profile, TINY, seed=0)
        model.move(0, 0.0, (0, 0))
        return model, [model.fate(s, 0, "sim", ("m", i), size=1) for i, s in enumerate(sends)]

    model, fates = run(limit=5)
    delivered = [f.delivered_at for f in fates if not f.lost]
    per_second: dict[int, int] = {}
    for t in delivered:
        per_second[math.floor(t - 1e-9)] = per_second.get(math.floor(t - 1e-9), 0) + 1
    assert max(per_second.values()) <= rate
    assert len(delivered) >= rate * 10 - 1  # the link stays busy: it delivers close to R every second
    assert model.stats.lost["link_queue"] == len(sends) - len(delivered) > 0
    waits = [f.delivered_at - s for f, s in zip(fates, sends) if not f.lost]
    assert max(waits) <= 5 / rate + 1e-9  # a full queue of 5 drains in 0.5 s

    # a long queue drops nothing: the messages wait, and the wait grows with the backlog
    model, fates = run(limit=10_000)
    assert not any(f.lost for f in fates)
    waits = [f.delivered_at - s for f, s in zip(fates, sends)]
    assert waits[-1] == pytest.approx(len(sends) / rate - sends[-1])
    assert all(b >= a - 1e-9 for a, b in zip(waits, waits[1:]))


def test_access_point_rate_is_shared_by_its_robots():
    profile = quiet("lan", ap_rate=Rate(rate=10.0, limit=10_000), access_points=Placement())  # default grid
    model = NetworkModel(profile, TINY, seed=0)
    model.move(0, 0.0, (0, 0))
    model.move(1, 0.0, (1, 0))  # same AP as robot 0
    model.move(2, 0.0, (13, 0))  # another AP
    assert model.ap_of(0) == model.ap_of(1) != model.ap_of(2)
    fates: dict[int, list] = {0: [], 1: [], 2: []}
    for i in range(100):  # a queue is fed in send-time order, as a discrete-event driver does
        for r in (0, 1, 2):
            fates[r].append(model.fate(i * 0.01, r, "sim", (r, i), size=1))
    last = {r: max(f.delivered_at for f in fates[r]) for r in fates}
    assert last[0] == pytest.approx(19.9, abs=0.2) and last[1] == pytest.approx(20.0, abs=0.2)  # 200 msgs at 10/s
    assert last[2] == pytest.approx(10.0, abs=0.1)  # alone on its AP


def test_an_access_point_may_budget_its_uplink_and_downlink_apart():
    """Separate airtime per direction: one chatty robot's uplink slows its neighbour's uplink (a shared medium), and
    neither their downlink; a direction without a budget is not limited."""
    profile = quiet("lan", ap_uplink_rate=Rate(rate=10.0, limit=10_000), access_points=Placement())
    model = NetworkModel(profile, TINY, seed=0)
    model.move(0, 0.0, (0, 0))
    model.move(1, 0.0, (1, 0))  # same AP as robot 0
    up = [model.fate(i * 0.01, 0, "sim", (0, i), size=1) for i in range(100)]  # robot 0 floods its uplink
    neighbour = model.fate(1.0, 1, "sim", (1, 0), size=1)
    assert max(f.delivered_at for f in up) == pytest.approx(10.0, abs=0.2)
    assert neighbour.delivered_at > 9.9  # behind robot 0's backlog on their access point's uplink
    down = model.fate(1.0, "sim", 1, ("sim", 0), size=1)
    assert down.delivered_at == pytest.approx(1.0)  # the downlink has its own airtime: no budget, no wait
    assert model.ap_bytes[model.ap_of(0)] == 101 and model.ap_queue_depths(1.0)[model.ap_of(0)] > 0
    both = quiet("lan", ap_uplink_rate=Rate(rate=10.0, limit=2), ap_downlink_rate=Rate(rate=10.0, limit=2))
    model = NetworkModel(both.model_copy(update={"access_points": Placement()}), TINY, seed=0)
    model.move(0, 0.0, (0, 0))
    fates = [model.fate(0.0, "sim", 0, ("sim", i), size=1) for i in range(3)]
    assert [f.cause for f in fates] == [None, None, "ap_queue"] and sum(model.ap_drops) == 1


def test_a_profile_gives_one_access_point_budget_or_one_per_direction():
    from schemas.network import parse_profile

    with pytest.raises(ValueError, match="ap_rate shares one queue"):
        parse_profile({"name": "x", "ap_rate": {"rate": 10}, "ap_downlink_rate": {"rate": 10}}, "network x")


def test_robot_to_robot_crosses_two_legs():
    model = NetworkModel(quiet("wifi-legacy-roaming"), TINY, seed=2)
    drive_along_row(model, 0, y=0)
    event = model.events[0]
    model.move(1, 0.0, (0, 14))
    # robot 1 → robot 0 during robot 0's outage: lost on robot 0's downlink
    assert model.fate(event.time + 0.1, 1, 0, "m").cause == "handover"
    ok = model.fate(event.end + 1.0, 1, 0, "m2")
    assert not ok.lost and ok.delivered_at > event.end + 1.0  # two legs of 5 ± 3 ms


def test_silence_stop_needs_an_outage_longer_than_it():
    """Legacy roaming's outages (≥ 1.2 s) outlast the 0.1 s safety stop; fast roaming's (≤ 45 ms) never do."""
    for name, stops in (("wifi-legacy-roaming", True), ("wifi-fast-roaming", False)):
        model = NetworkModel(quiet(name), TINY, seed=4)
        drive_along_row(model, 0, y=0)
        event = model.events[0]
        stop = load_profile(name).silence_stop
        assert stop == 0.1
        times = [event.time + k * 0.01 for k in range(-10, 500)]
        silenced = [at for at in times if model.silenced(at, stop)]
        if stops:
            assert silenced and min(silenced) >= event.time + stop - 1e-9 and max(silenced) < event.end
        else:
            assert silenced == []


def test_link_rate_holds_through_the_labs_event_network():
    """The lab's discrete-event network carries the profile's queues: at rate R a robot's link delivers at most R per
    sim second, the rest waits (delivery later than sent) or is dropped when the queue is full."""
    from morph_sim.lab.network import EventNetwork
    from services.protocol.dispatch import Commitment

    rate, offered, limit = 10.0, 50, 5
    model = NetworkModel(quiet("lan", link_rate=Rate(rate=rate, limit=limit)), TINY, seed=0)
    model.move(0, 0.0, (0, 0))
    net = EventNetwork(model=model)
    sends = [i / offered for i in range(offered * 10)]
    for i, s in enumerate(sends):
        net.send(net.keys.commit(0), 0, "sim", Commitment(0, 1, (0, 0), s, i), s, size=1)
    per_second: dict[int, int] = {}
    for t in range(1, 13):
        for due, _, msg in net.until(float(t)):
            assert due >= msg.sent_at
            per_second[t - 1] = per_second.get(t - 1, 0) + 1
    delivered = sum(per_second.values())
    assert max(per_second.values()) <= rate
    assert delivered >= rate * 10 - 1 and net.stats.dropped == len(sends) - delivered > 0
    assert model.stats.lost["link_queue"] == net.stats.dropped


def test_lab_episode_takes_a_profile_and_names_the_field_when_bad():
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    with pytest.raises(ValueError, match=r"network\n.*unknown profile 'wifi'"):
        EpisodeSpec(scale="tiny", condition="full", seed=1, network="wifi")
    with pytest.raises(ValueError, match="network: network faults act on the dispatch protocol"):
        run_episode(EpisodeSpec(scale="tiny", condition="full", seed=1, steps=5, dispatch="sequential",
                                network="lan"))
    s = run_episode(EpisodeSpec(scale="tiny", condition="full", seed=3, steps=120,
                                network="wifi-legacy-roaming")).summary
    assert s["network_handovers"] > 0 and s["network_lost_handover"] > 0 and s["network_stops"] > 0
    again = run_episode(EpisodeSpec(scale="tiny", condition="full", seed=3, steps=120,
                                    network="wifi-legacy-roaming")).summary
    assert {k: v for k, v in s.items() if k != "wall_s"} == {k: v for k, v in again.items() if k != "wall_s"}


@pytest.mark.parametrize("name, faulted", [("congested", False), ("wifi-fast-roaming", False), ("lossy-mesh", False),
                                           ("wifi-fast-roaming", True), (None, True)])
def test_one_publications_copies_judged_together_equal_one_call_per_copy(name, faulted):
    # a fleet broadcast has a copy per robot: judged together (the key, identity and faults in force read once)
    # every copy must have the verdict, and leave the queues, streams and counters, that judging them one by one gives
    from schemas.faults import Duplicate, FaultSpec, Latency, Loss, Reorder
    from services.faults.layer import FaultLayer

    specs = [FaultSpec(id="lossy", loss=Loss(model="gilbert_elliott", percent=20, burst_length=3), seed=2),
             FaultSpec(id="late", latency=Latency(delay=0.4, jitter=0.2, correlation=30), duplicate=Duplicate(percent=10),
                       reorder=Reorder(percent=25, gap=2), duration=20.0)]

    def run(together: bool):
        model = NetworkModel(load_profile(name), TINY, seed=5) if name else None
        layer = FaultLayer("r", base_seed=5, clock=lambda: 0.0, per_key=True)
        layer.network = model
        for spec in specs if faulted else ():
            layer.set(spec, at=0.0)
        robots = list(range(8))
        verdicts = []
        for t in range(60):
            for robot in robots if model is not None else ():  # the robots wander, roaming between access points
                model.move(robot, t * 0.5, ((robot * 3 + t) % TINY.W, (robot + t // 4) % TINY.H))
            for key, sender in (("morph/r/sim/fleet", "sim"), (f"morph/r/agent/{t % 8}/policy", t % 8)):
                msg = (sender, t)
                if together:
                    verdicts.append(layer.fate_copies(key, sender, robots, t * 0.5, msg=msg, size=900))
                else:
                    verdicts.append([layer.fate(key, sender, r, t * 0.5, msg=msg, size=900) for r in robots])
        radio = (model.stats, model.ap_drops, model.ap_bytes) if model is not None else None
        return verdicts, layer.stats, radio, {k: (v.count, v.rng.getstate()) for k, v in layer._links.items()}

    one_by_one, together = run(False), run(True)
    assert together == one_by_one
    verdicts = [v for copies in one_by_one[0] for v in copies]
    assert [] in verdicts and any(v and v[0] > 0 for v in verdicts)  # some copies lost, some late: not vacuous
    if faulted:
        assert any(len(v) == 2 for v in verdicts)  # duplicated
