"""The shipped heuristic controller."""

import pytest

from services.world.heuristic import HeuristicController, MissionType, run_episode, split_list
from services.world.warehouse import Warehouse, WarehouseConfig


@pytest.mark.parametrize(
    "scale, sizes",
    [
        ("tiny", [1, 1, 1]),
        ("small", [2, 2, 1, 1]),
        ("medium", [2, 2, 2, 2, 1, 1]),
        ("large", [2] * 7 + [1]),
        ("extralarge", [4] * 7),
    ],
)
def test_zone_sizes_in_rack_groups(scale, sizes):
    env = Warehouse(WarehouseConfig.named(scale))
    env.reset(0)
    ctrl = HeuristicController(env)
    per_group = len(env.layout.rack_groups[0])
    assert [len(z) // per_group for z in ctrl.zones] == sizes
    # every rack cell belongs to exactly one picker
    assert len(ctrl.zone_picker) == env.layout.num_shelves


def test_split_list_front_loads_the_remainder():
    assert split_list(list(range(7)), 3) == [[0, 1, 2], [3, 4], [5, 6]]
    assert split_list([], 2) == [[], []]


def test_first_actions_match_original_tiny_seed0():
    """Macro actions the original heuristic sent at its first step (reference trace tiny 5+3 seed 0)."""
    env = Warehouse(WarehouseConfig.named("tiny"))
    env.reset(0)
    ctrl = HeuristicController(env)
    assert ctrl.actions() == [12, 46, 27, 25, 13, 13, 25, 46]
    # every AGV got the PICKING mission of a requested shelf, each shelf at most once
    items = list(ctrl.assigned_items.values())
    assert len(items) == 5 == len(set(items)) and set(items) <= set(env.queue)
    assert all(m.kind is MissionType.PICKING for m in ctrl.assigned_agvs.values())


def test_closest_free_agv_first_minimum():
    env = Warehouse(WarehouseConfig.named("tiny", 2, 1))
    env.reset(0)
    env.place_agent(1, 0, 0, 0)
    env.place_agent(2, 13, 0, 0)
    env.place_agent(3, 0, 13, 0)
    env.queue[0] = 6  # shelf 6 sits at (11, 2): AGV 2 is closer
    ctrl = HeuristicController(env)
    ctrl.actions()
    assert ctrl.assigned_items[1] == 6


def test_missions_cycle_through_delivery_and_return():
    env = Warehouse(WarehouseConfig.named("tiny", max_steps=300))
    env.reset(1)
    ctrl = HeuristicController(env)
    seen = set()
    for _ in range(300):
        env.step(ctrl.actions())
        seen.update(m.kind for m in ctrl.assigned_agvs.values())
    assert seen == {MissionType.PICKING, MissionType.DELIVERING, MissionType.RETURNING}


def test_needs_a_picker():
    env = Warehouse(WarehouseConfig.named("tiny", 3, 0))
    env.reset(0)
    with pytest.raises(ValueError, match="pickers"):
        HeuristicController(env)


def test_run_episode_reports():
    res = run_episode(WarehouseConfig.named("tiny", max_steps=250), 0, digests=True)
    assert res.steps == 250 == len(res.deliveries_per_step) == len(res.step_digests)
    assert res.cumulative(100) == [8, 14]  # the original's cumulative deliveries for tiny 5+3 seed 0
    assert res.steps_per_second > 0
