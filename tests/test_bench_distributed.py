"""``morph-sim bench distributed``: the CPU-per-tick accounting (no timing is asserted)."""

from __future__ import annotations

import os
from types import SimpleNamespace

from morph_sim.bench.distributed import CpuMeter


def _meter() -> CpuMeter:
    children = {name: SimpleNamespace(pid=pid, alive=lambda: True)
                for name, pid in (("sim", 10), ("monitor", 11), ("agent-0", 20), ("agent-1", 21), ("agent-2", 22))}
    sup = SimpleNamespace(children=children, config=SimpleNamespace(steps=100), progress=SimpleNamespace(t=-1))
    return CpuMeter(sup, n_agvs=2)


def test_cpu_per_tick_by_role_over_the_window():
    meter = _meter()
    assert meter._role("agent-1") == "agv" and meter._role("agent-2") == "picker" and meter._role("sim") == "sim"
    meter.first = (20, {"sim:10": 1.0, "monitor:11": 2.0, "agv:20": 0.5, "agv:21": 0.5, "picker:22": 0.1,
                        "supervisor:1": 3.0})
    meter.last = (70, {"sim:10": 1.2, "monitor:11": 2.1, "agv:20": 0.55, "agv:21": 0.57, "picker:22": 0.13,
                       "supervisor:1": 3.01, "agv:99": 5.0})  # pid 99: restarted inside the window, left out
    cpu = meter.per_tick_ms()
    expect = {"sim": 4.0, "monitor": 2.0, "agv": 1.2, "picker": 0.6, "supervisor": 0.2}
    for role, ms in expect.items():
        assert abs(cpu[role] - ms) < 1e-9, role
    assert abs(cpu["total"] - (4.0 + 2.0 + 1.0 + 1.4 + 0.6 + 0.2)) < 1e-9  # agents summed, not averaged


def test_no_window_no_figures():
    meter = _meter()
    assert meter.per_tick_ms() == {}
    meter.first = meter.last = (30, {"sim:10": 1.0})
    assert meter.per_tick_ms() == {}


def test_samples_read_the_live_processes():
    meter = _meter()
    meter.sup.children = {"sim": SimpleNamespace(pid=os.getpid(), alive=lambda: True),
                          "agent-0": SimpleNamespace(pid=None, alive=lambda: False)}
    sample = meter._sample()
    assert set(sample) == {f"sim:{os.getpid()}", f"supervisor:{os.getpid()}"} and all(v > 0 for v in sample.values())
