"""Trajectory fidelity with the ORIGINAL TA-RWARE (tests/data/tarware_digests.json):
the reset vector, and 12 whole heuristic episodes whose per-step state digests and cumulative deliveries must be
bit-identical. All 12 run in a few seconds, so all are in the default suite."""

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from services.world.heuristic import run_episode
from services.world.layout import LayoutConfig
from services.world.warehouse import Direction, Warehouse, WarehouseConfig, episode_digest

DATA = json.loads((Path(__file__).parent / "data" / "tarware_digests.json").read_text())
EPISODES = DATA["episodes"]


def test_reset_vector():
    rv = DATA["reset_vector"]
    env = Warehouse(WarehouseConfig.named(rv["size"], rv["agvs"], rv["pickers"]))
    env.reset(rv["seed"])
    got = [[env.x[i], env.y[i], Direction(env.dir[i]).name] for i in range(env.num_agents)]
    assert got == rv["agents_x_y_dir"]
    assert env.queue[:10] == rv["first_requests"]
    assert [list(env.shelf_cell(s)) for s in env.queue[:10]] == rv["first_request_cells_x_y"]
    assert len(env.queue) == len(set(env.queue)) == 20


def test_reset_is_deterministic_and_seed_dependent():
    cfg = WarehouseConfig.named("small")
    a, b, c = Warehouse(cfg), Warehouse(cfg), Warehouse(cfg)
    a.reset(5)
    b.reset(5)
    c.reset(6)
    assert a.digest_key() == b.digest_key() != c.digest_key()


@pytest.mark.parametrize("ep", EPISODES, ids=[f"{e['size']}-{e['agvs']}+{e['pickers']}-s{e['seed']}" for e in EPISODES])
def test_episode_is_bit_identical(ep):
    cfg = WarehouseConfig.named(ep["size"], ep["agvs"], ep["pickers"], max_steps=DATA["steps"])
    result = run_episode(cfg, ep["seed"], digests=True)
    assert result.cumulative(100) == ep["cumulative"]
    assert result.deliveries == ep["deliveries"]
    assert result.digest == ep["digest"]
    assert result.global_return == pytest.approx(ep["global_return"], abs=0.05)


def test_global_reward_mode_pays_everyone():
    cfg = WarehouseConfig.named("tiny", max_steps=200, reward_type="global")
    res = run_episode(cfg, 0)
    ind = run_episode(WarehouseConfig.named("tiny", max_steps=200), 0)
    assert res.deliveries == ind.deliveries  # rewards never feed back into the dynamics
    assert res.global_return > ind.global_return


def test_episode_digest_definition():
    assert episode_digest(["abc", "def"]) == __import__("hashlib").sha1(b"abcdef").hexdigest()[:16]


def test_step_result_counters():
    env = Warehouse(WarehouseConfig.named("tiny", max_steps=3))
    env.reset(0)
    from services.world.heuristic import HeuristicController

    ctrl = HeuristicController(env)
    res = [env.step(ctrl.actions()) for _ in range(3)]
    assert [r.done for r in res] == [False, False, True]
    assert all(r.agvs_idle + (5 - r.agvs_idle) == 5 for r in res)
    assert res[0].agvs_distance >= 0 and len(res[0].rewards) == 8
    assert all(r == pytest.approx(-0.001) for r in res[0].rewards)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(agvs=-1, pickers=3), "agvs"),
        (dict(agvs=5, pickers=-2), "pickers"),
        (dict(agvs=0, pickers=0), "agvs"),
        (dict(agvs=160, pickers=3), "agvs"),
        (dict(agvs=5, pickers=3, max_steps=-5), "max_steps"),
        (dict(agvs=5, pickers=3, reward_type="two_stage"), "reward_type"),
    ],
)
def test_bad_warehouse_config_names_the_field(kwargs, field):
    with pytest.raises(ValidationError, match=field):
        WarehouseConfig(layout=LayoutConfig.named("tiny"), **kwargs)


def test_bad_actions_are_clear_errors():
    env = Warehouse(WarehouseConfig.named("tiny"))
    with pytest.raises(RuntimeError, match="reset"):
        env.step([0] * 8)
    env.reset(0)
    with pytest.raises(ValueError, match="actions: expected 8"):
        env.step([0] * 7)
    with pytest.raises(ValueError, match="actions: agent 1"):
        env.step([999] + [0] * 7)


SEEDS20 = json.loads((Path(__file__).parent / "data" / "tarware_digests_20seeds.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("size", ["tiny", "small", "medium", "large"])
def test_twenty_seeds_bit_identical(size):
    """Beyond the 12 episodes: 20 seeds per size, including the jammed episodes, equal the original's."""
    for ep in [e for e in SEEDS20["episodes"] if e["size"] == size]:
        cfg = WarehouseConfig.named(size, ep["agvs"], ep["pickers"], max_steps=SEEDS20["steps"])
        result = run_episode(cfg, ep["seed"], digests=True)
        got = (result.digest, result.deliveries, result.clashes, result.stucks)
        assert got == (ep["digest"], ep["deliveries"], ep["clashes"], ep["stucks"]), ep


def test_empty_rack_cells_and_maps():
    env = Warehouse(WarehouseConfig.named("tiny"))
    env.reset(0)
    assert env.empty_rack_actions() == []
    env.place_agent(1, 2, 5, Direction.DOWN, carrying=19)  # shelf 19 stands at (2, 5)
    env.set_path(1, [(2, 6), (2, 7)])
    env.step([0] * 8)
    assert (env.x[0], env.y[0]) == (2, 6)
    assert env.empty_rack_actions() == [env.cell_to_action((2, 5))]
    assert env.action_to_cell(env.cell_to_action((2, 5))) == (2, 5)
    assert env.manhattan((0, 0), (3, 4)) == 7


def test_state_arrays_and_frame():
    env = Warehouse(WarehouseConfig.named("small"))
    env.reset(3)
    assert env.positions().shape == (12, 2) and env.is_agv.sum() == 8
    assert env.request_queue.tolist() == env.queue and env.is_requested_mask().sum() == 20
    assert env.shelf_positions.shape == (96, 2) and env.req_actions.shape == (12,)
    frame = env.frame(caption="x")
    assert frame.shelves.sum() == 96 and frame.requested.sum() == 20
    assert frame.agent_x.tolist() == env.x and not frame.carrying.any()


def test_reseed_replays_the_request_stream():
    def deliveries_with_reseed(seed):
        from services.world.heuristic import HeuristicController

        env = Warehouse(WarehouseConfig.named("tiny", max_steps=150))
        env.reset(0)
        env.reseed(seed)
        ctrl = HeuristicController(env)
        return [env.step(ctrl.actions()).deliveries for _ in range(150)], list(env.queue)

    assert deliveries_with_reseed(7) == deliveries_with_reseed(7)
    assert isinstance(Warehouse(WarehouseConfig.named("tiny")).config, WarehouseConfig)
    with pytest.raises(RuntimeError, match="rng"):
        _ = Warehouse(WarehouseConfig.named("tiny")).rng


RANDOM = json.loads((Path(__file__).parent / "data" / "random_action_digests.json").read_text())


@pytest.mark.parametrize("run", RANDOM["runs"], ids=[f"{r['size']}-{r['agvs']}+{r['pickers']}-s{r['seed']}"
                                                      for r in RANDOM["runs"]])
def test_random_macro_actions_bit_identical(run):
    """Random targets stress paths the heuristic never asks for (pickers sent to goals, AGVs to random cells, agents
    without pickers loading alone); every step's digest must equal the original's."""
    import random

    cfg = WarehouseConfig.named(run["size"], run["agvs"], run["pickers"], max_steps=RANDOM["steps"])
    env = Warehouse(cfg)
    env.reset(run["seed"])
    rng = random.Random(run["seed"] * 7 + 1)
    n = env.layout.action_size
    for t, expected in enumerate(run["digests"], start=1):
        env.step([rng.randrange(n) if rng.random() < 0.3 else 0 for _ in range(env.num_agents)])
        assert env.digest_row() == expected, f"first divergence at step {t}"
