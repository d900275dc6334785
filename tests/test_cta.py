"""The reference CTA controller on the warehouse core.

Reference numbers are from our run of the published morph_v2 code on TA-RWARE@6109c33
with the rotation-aware A*): Full-Graph per-seed deliveries for seeds 42, 7, 123, 999, 2024.
"""

import numpy as np
import pytest

from schemas.fields import MissionType
from schemas.tick import NEEDS_PICKER, NO_CELL
from services.protocol.tick import first_in_mission_order
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig


def _controller(scale="tiny", seed=42):
    cta = CTAController(Warehouse(WarehouseConfig.named(scale, max_steps=10_000)))
    cta.reset(seed)
    return cta


def _full_sequential(obs):
    """The reference's Full-Graph dispatch: nearest free picker, P = 1, next-nearest within the tick."""
    free = obs.free_picker.copy()
    cells, commits = set(), []
    for agv in obs.requesters():
        cell = tuple(obs.target[agv])
        if cell in cells or not free.any():
            continue
        p = obs.nearest_free_picker(int(agv), free)
        commits.append((p, int(agv)))
        free[p] = False
        cells.add(cell)
    return commits


def test_nearest_free_picker_is_the_first_minimum_over_free_pickers():
    """The scan gives numpy's answer (argmin over the free pickers' Manhattan distances, ties to the lowest index)
    on crowded fleets with ties, a free mask that overrides the observation's, and none free."""
    import dataclasses

    rng = np.random.default_rng(3)
    obs = _controller("small").begin_tick()
    n = obs.n
    for _ in range(300):
        cells = rng.integers(0, 4, (n, 2))  # a 4 × 4 corner: many equal distances
        target = rng.integers(0, 4, (n, 2))
        view = dataclasses.replace(obs, cells=cells, target=target)
        free = rng.random(n) < 0.3
        for agv in range(obs.n_agvs):
            pickers = np.flatnonzero(free)
            d = np.abs(cells[pickers, 0] - target[agv, 0]) + np.abs(cells[pickers, 1] - target[agv, 1])
            expected = int(pickers[int(np.argmin(d))]) if pickers.size else -1
            assert view.nearest_free_picker(agv, free) == expected
    assert view.nearest_free_picker(0, np.zeros(n, dtype=bool)) == -1


@pytest.mark.parametrize("scale,expected", [("tiny", [57, 48, 57]), ("medium", [69, 88, 90])])
def test_full_graph_reproduces_reference_deliveries(scale, expected):
    got = []
    for seed in (42, 7, 123):
        cta = _controller(scale, seed)
        for _ in range(800):
            obs = cta.begin_tick()
            cta.commit(_full_sequential(obs))
            cta.finish_tick()
        got.append(cta.deliveries)
    assert got == expected


def test_no_dispatch_means_no_delivery():
    cta = _controller("small", 7)
    for _ in range(300):
        cta.begin_tick()
        cta.finish_tick()
    assert cta.deliveries == 0
    assert not cta.picker_missions


def test_observation_invariants_over_an_episode():
    cta = _controller("medium", 123)
    n, na = cta.n, cta.n_agvs
    loaders = []
    for t in range(400):
        obs = cta.begin_tick()
        assert obs.t == t and obs.has_previous == (t > 0)
        assert obs.cells.shape == (n, 2) and obs.target.shape == (n, 2)
        assert not obs.free_picker[:na].any()
        # a requester has a rack-cell mission with no picker there
        for a in obs.requesters():
            assert obs.mission[a] in NEEDS_PICKER
            assert not any(
                tuple(obs.target[p]) == tuple(obs.target[a]) for p in range(na, n) if not obs.free_picker[p]
            )
        # AGVs with a mission have a task; missions without target do not exist
        has = obs.mission != MissionType.NONE
        assert np.all((obs.target[:, 0] != NO_CELL) == has)
        assert np.all(obs.task[:na][has[:na]] > 0)
        loaders += [int(obs.loader[a]) for a in np.flatnonzero(obs.delivered)]
        cta.commit(_full_sequential(obs))
        # one picker per cell
        cells = [m.cell for m in cta.picker_missions.values()]
        assert len(cells) == len(set(cells))
        cta.finish_tick()
        # sticky release: every remaining picker serves an AGV that needs it
        needed = {m.cell for m in cta.agv_missions.values() if m.kind in NEEDS_PICKER}
        assert all(m.cell in needed for m in cta.picker_missions.values())
    assert loaders and all(na <= p < n for p in loaders)  # each delivered shelf was loaded by a picker


def test_commit_rejects_double_assignments():
    cta = _controller("tiny", 42)
    for _ in range(5):
        obs = cta.begin_tick()
        req = obs.requesters()
        if len(req):
            break
        cta.finish_tick()
    agv = int(req[0])
    p1, p2 = cta.n_agvs, cta.n_agvs + 1
    applied = cta.commit([(p1, agv), (p2, agv)])  # second picker to the same cell is dropped
    assert applied == [(p1, agv)]
    assert cta.commit([(p1, agv)]) == []  # busy picker


def test_the_first_request_in_mission_order_wins():
    assert first_in_mission_order([(3, 9), (1, 9), (2, 8)]) == [(9, 3), (8, 2)]
    assert first_in_mission_order([]) == []


def test_controller_needs_pickers():
    with pytest.raises(ValueError, match="pickers"):
        CTAController(Warehouse(WarehouseConfig.named("tiny", pickers=0)))
