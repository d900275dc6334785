"""The bus fault layer: acceptance statistics of loss and latency, reproducibility per link, scopes,
partitions, auto-heal, and the layer installed on a real bus through the interposer seam."""

from __future__ import annotations

import asyncio

import pytest

from schemas import Duplicate, FaultSpec, Latency, Loss, Partition, RunKeys, Scope
from schemas.faults import Crash, Reorder
from services.bus import LocalNetwork
from services.faults.distributions import latency_quantile, pareto_params
from services.faults.layer import FaultLayer

from _procs import until

K = RunKeys("f1")


def fates(layer: FaultLayer, n: int, key: str = K.commit(1), sender: object = 1, receiver: object = "sim"):
    return [layer.fate(key, sender, receiver) for _ in range(n)]


def bursts(lost: list[bool]) -> list[int]:
    runs, current = [], 0
    for x in lost:
        if x:
            current += 1
        elif current:
            runs.append(current)
            current = 0
    if current:
        runs.append(current)
    return runs


@pytest.mark.parametrize("percent", [1.0, 10.0, 30.0, 50.0])
def test_bernoulli_loss_within_one_point_over_10000(percent: float) -> None:
    layer = FaultLayer("f1", base_seed=7)
    layer.set(FaultSpec(loss=Loss(percent=percent)))
    lost = [f == [] for f in fates(layer, 10_000)]
    assert abs(100.0 * sum(lost) / len(lost) - percent) <= 1.0


@pytest.mark.parametrize(("percent", "burst"), [(10.0, 3.0), (20.0, 4.0), (30.0, 8.0)])
def test_gilbert_elliott_burst_length_within_ten_percent(percent: float, burst: float) -> None:
    layer = FaultLayer("f1", base_seed=11)
    layer.set(FaultSpec(loss=Loss(model="gilbert_elliott", percent=percent, burst_length=burst)))
    lost = [f == [] for f in fates(layer, 60_000)]
    runs = bursts(lost)
    assert abs(sum(runs) / len(runs) - burst) <= 0.1 * burst
    assert abs(100.0 * sum(lost) / len(lost) - percent) <= 1.5


def test_gilbert_elliott_four_parameter_form() -> None:
    p, r, one_minus_h, one_minus_k = 0.05, 0.25, 0.8, 0.02
    layer = FaultLayer("f1", base_seed=3)
    layer.set(FaultSpec(loss=Loss(model="gilbert_elliott", p=100 * p, r=100 * r, one_minus_h=100 * one_minus_h,
                                  one_minus_k=100 * one_minus_k)))
    lost = [f == [] for f in fates(layer, 60_000)]
    expected = one_minus_k * r / (p + r) + one_minus_h * p / (p + r)  # stationary loss rate
    assert abs(sum(lost) / len(lost) - expected) <= 0.01


@pytest.mark.parametrize("latency", [
    Latency(delay=1.0, jitter=0.5, distribution="uniform"),
    Latency(delay=1.0, jitter=0.2, distribution="normal"),
    Latency(delay=1.0, jitter=0.5, distribution="pareto"),
    Latency(delay=2.0, jitter=0.0),
], ids=["uniform", "normal", "pareto", "fixed"])
def test_latency_quantiles_within_five_percent(latency: Latency) -> None:
    layer = FaultLayer("f1", base_seed=5)
    layer.set(FaultSpec(latency=latency))
    delays = sorted(f[0] for f in fates(layer, 20_000))
    for q in (0.1, 0.25, 0.5, 0.75, 0.9):
        observed = delays[int(q * len(delays))]
        assert abs(observed - latency_quantile(latency, q)) <= 0.05 * latency_quantile(latency, q), q
    if latency.distribution == "pareto":
        a, xm = pareto_params(1.0, 0.5)
        assert a * xm / (a - 1) == pytest.approx(1.0)  # the parametrisation has the configured mean


def test_same_seed_same_fates_and_links_are_independent() -> None:
    spec = FaultSpec(loss=Loss(percent=30), latency=Latency(delay=0.5, jitter=0.2), duplicate=Duplicate(percent=10))

    def run(seed: int, interleave: bool) -> list:
        layer = FaultLayer("f1", base_seed=seed)
        layer.set(spec)
        out = []
        for _i in range(500):
            out.append(layer.fate(K.commit(1), 1, "sim"))
            if interleave:  # other links' traffic must not shift this link's stream
                layer.fate(K.commit(2), 2, "sim")
                layer.fate(K.request(1, 5), 1, 5)
        return out

    assert run(1, False) == run(1, True) == run(1, False)
    assert run(1, False) != run(2, False)
    seeded = FaultLayer("f1", base_seed=99)
    seeded.set(spec.model_copy(update={"seed": 1}))  # the spec's seed overrides the layer's
    plain = FaultLayer("f1", base_seed=1)
    plain.set(spec)
    assert fates(seeded, 300) == fates(plain, 300)


def test_directional_partition_and_scope() -> None:
    layer = FaultLayer("f1")
    layer.set(FaultSpec(partition=Partition(from_agents=[1, 2], to_agents=["sim"], direction="to")))
    assert layer.fate(K.commit(1), 1, "sim") == []
    assert layer.fate(K.tick, "sim", 1) == [0.0]  # the other direction still flows
    assert layer.fate(K.request(1, 5), 1, 5) == [0.0]
    layer.reset()
    layer.set(FaultSpec(loss=Loss(percent=100), scope=Scope(key_expr="agent/*/commit", agents=[2])))
    assert layer.fate(K.commit(2), 2, "sim") == []
    assert layer.fate(K.commit(1), 1, "sim") == [0.0]  # agent out of scope
    assert layer.fate(K.agent_state(2), 2, "monitor") == [0.0]  # key out of scope
    assert layer.fate("morph/other/agent/2/ack", 2, "sim") == [0.0]  # another run's traffic


def test_a_fault_s_scope_answers_every_key_as_its_key_expression_does_and_its_memory_stays_bounded() -> None:
    from schemas.keys import matches
    from services.faults.layer import ActiveFault

    fault = ActiveFault(FaultSpec(loss=Loss(percent=100), scope=Scope(key_expr="agent/*/request/**", agents=[2, 3])),
                        "f", 0.0, None)
    keys = [f"agent/{a}/{kind}/{b}" for a in range(5) for kind in ("request", "reply", "ack") for b in range(5)]
    for _ in range(2):  # the second pass answers from what the first one kept
        for key in keys:
            for sender, receiver in ((2, "sim"), (1, 3), (1, 4)):
                expect = matches("agent/*/request/**", key) and (sender in (2, 3) or receiver in (2, 3))
                assert fault.applies(key, sender, receiver) is expect, (key, sender, receiver)
    for i in range(5000):  # keys nobody planned
        fault.applies(f"agent/1/request/x{i}", 2, "sim")
    assert len(fault._matched) <= 4096


def test_duplicate_and_reorder() -> None:
    layer = FaultLayer("f1")
    layer.set(FaultSpec(duplicate=Duplicate(percent=100)))
    assert layer.fate(K.tick, "sim", 1) == [0.0, 0.0]
    layer.reset()
    layer.set(FaultSpec(latency=Latency(delay=1.0), reorder=Reorder(percent=100, gap=3)))
    assert [f[0] for f in fates(layer, 6)] == [1.0, 1.0, 0.0, 1.0, 1.0, 0.0]  # every 3rd skips the delay


def test_duration_auto_heals_and_reset_always_works() -> None:
    now = [0.0]
    changes: list[tuple[str, str]] = []
    layer = FaultLayer("f1", clock=lambda: now[0], on_change=lambda what, f: changes.append((what, f.fault_id)))
    fid = layer.set(FaultSpec(id="cut", loss=Loss(percent=100), duration=5.0))
    other = layer.set(FaultSpec(latency=Latency(delay=1.0)))
    assert fid == "cut" and [s.id for s in layer.active()] == ["cut", other]
    assert layer.fate(K.commit(1), 1, "sim") == []
    now[0] = 5.0
    assert layer.fate(K.commit(1), 1, "sim") == [1.0]  # healed at its end; the latency fault remains
    assert changes == [("set", "cut"), ("set", other), ("healed", "cut")]
    assert layer.reset() == [other] and layer.active() == [] and layer.reset() == []
    with pytest.raises(ValueError, match="supervisor"):
        layer.set(FaultSpec(crash=Crash(agent=1, at_tick=10)))


def test_fault_commands() -> None:
    from schemas import FaultCommand

    layer = FaultLayer("f1")
    reply = layer.apply(FaultCommand(op="set", spec=FaultSpec(id="slow", latency=Latency(delay=0.1))))
    assert reply.ok and [s.id for s in reply.active] == ["slow"]
    assert [s.id for s in layer.apply(FaultCommand(op="list")).active] == ["slow"]
    bad = layer.apply(FaultCommand(op="set", spec=FaultSpec(crash=Crash(agent=1, at_tick=3))))
    assert not bad.ok and "supervisor" in bad.error
    assert not layer.apply(FaultCommand(op="reset", fault_id="nope")).ok
    assert layer.apply(FaultCommand(op="reset")).active == []


async def test_fault_layer_on_a_bus_through_the_seam() -> None:
    net = LocalNetwork()
    sender, receiver = net.session("3"), net.session("sim")
    layer = FaultLayer("f1", base_seed=4)
    layer.set(FaultSpec(loss=Loss(percent=40), latency=Latency(delay=0.02, jitter=0.01)))
    twin = FaultLayer("f1", base_seed=4)
    twin.set(FaultSpec(loss=Loss(percent=40), latency=Latency(delay=0.02, jitter=0.01)))
    receiver.set_interposer(layer)
    got: list[int] = []
    await receiver.subscribe(K.commits, lambda s: got.append(s.seq))
    for _ in range(200):
        await sender.publish(K.commit(3), b"a")
    await asyncio.sleep(0)
    assert got == []  # everything that survived is still in flight
    expected = [i for i, f in enumerate(fates(twin, 200, K.commit(3), 3, "sim")) if f]
    await until(lambda: len(got) >= len(expected), what="every surviving message delivered")
    assert sorted(got) == expected and 90 <= len(got) <= 150
    assert layer.stats.dropped == 200 - len(expected)
    await sender.close()
    await receiver.close()
