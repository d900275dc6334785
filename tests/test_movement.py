"""RWARE-style movement tests: hand-placed states, one step (two where a second step shows the consequence), checked
against outcomes of the ORIGINAL code (tests/data/movement_scenarios.json, source named there); plus the move-graph
tie order against networkx 3.2.1 answers (tests/data/move_graph_cases.json)."""

import json
import random
from collections import Counter
from pathlib import Path

import pytest

from services.world.conflicts import commit_cells, commit_flat, merge_winner, networkx_commit_cells
from services.world.warehouse import FORWARD, NOOP, TOGGLE, Warehouse, WarehouseConfig

DATA = Path(__file__).parent / "data"
SCENARIOS = json.loads((DATA / "movement_scenarios.json").read_text())["scenarios"]
GRAPHS = json.loads((DATA / "move_graph_cases.json").read_text())["cases"]


def _setup(s) -> Warehouse:
    env = Warehouse(WarehouseConfig.named(s["size"], s["agvs"], s["pickers"], max_steps=100))
    env.reset(s["seed"])
    for agent_id, x, y, heading, shelf, path in s["agents"]:
        env.place_agent(agent_id, x, y, heading, shelf)
        if path is not None:
            env.set_path(agent_id, [tuple(c) for c in path])
    if s["queue"]:
        env.queue = list(s["queue"])
    return env


def _state(env, res):
    return {
        "agents": [[env.x[i], env.y[i], env.dir[i], env.carrying[i], int(env.busy[i]), env.req[i]]
                   for i in range(env.num_agents)],
        "deliveries": res.deliveries, "clashes": res.clashes, "stucks": res.stucks, "queue": list(env.queue),
    }


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s["name"] for s in SCENARIOS])
def test_scenario_matches_original(scenario):
    env = _setup(scenario)
    for t, expected in enumerate(scenario["expected"]):
        res = env.step([0] * env.num_agents)
        assert _state(env, res) == expected, f"step {t + 1}"


def _run(name, steps=1):
    s = next(s for s in SCENARIOS if s["name"] == name)
    env = _setup(s)
    results = [env.step([0] * env.num_agents) for _ in range(steps)]
    return env, results


def test_head_on_swap_moves_nobody_and_counts_a_clash():
    env, (res,) = _run("head_on")
    assert (env.x[0], env.y[0]) == (4, 11) and (env.x[1], env.y[1]) == (5, 11)
    assert res.clashes == 1 and env.fixing[0] == 4  # the lower id re-planned around the other


def test_chain_only_the_front_moves():
    env, _ = _run("chain")
    assert [(env.x[i], env.y[i]) for i in range(3)] == [(4, 11), (5, 11), (7, 11)]


def test_rotating_square_blocks_itself():
    env, _ = _run("cycle")
    assert [(env.x[i], env.y[i]) for i in range(4)] == [(4, 11), (5, 11), (5, 12), (4, 12)]


@pytest.mark.parametrize("name, mover", [("same_target_row11", None), ("same_target_row12", 1),
                                         ("same_target_col0", None)])
def test_same_target_winner_follows_networkx_order(name, mover):
    """Two agents want one free cell: the lower id yields, and whether the other moves depends on which of the two
    networkx's set order committed (so sometimes nobody moves)."""
    env, _ = _run(name)
    moved = [i for i in (0, 1) if env.req[i] == FORWARD]
    assert moved == ([] if mover is None else [mover])


def test_agv_and_picker_share_a_rack_cell_and_load_next_step():
    env, (r1, r2) = _run("picker_joins_toggling_agv", steps=2)
    # step 1: the picker steps onto the toggling AGV's cell; the load fails (no picker there at start of step)
    # step 2: the picker was there at the start, so the load succeeds and the picker is paid
    assert (env.x[5], env.y[5]) == (env.x[0], env.y[0]) == (2, 5)
    assert r1.loads == 0 and r2.loads == 1 and env.carrying[0] == 19
    assert r2.rewards[5] == pytest.approx(0.1 - 0.001)


def test_load_needs_picker_present_at_start_of_step():
    env, (res,) = _run("load_with_picker_present")
    assert res.loads == 1 and env.carrying[0] == 19 and not env.busy[0]


def test_picker_waits_next_to_a_cell_whose_agv_is_not_toggling():
    env, _ = _run("picker_waits_for_agv")
    assert (env.x[5], env.y[5]) == (1, 5) and env.req[5] == NOOP


def test_loaded_agv_drives_through_occupied_racks():
    env, _ = _run("loaded_agv_through_racks")
    assert (env.x[0], env.y[0]) == (2, 6) and env.carrying[0] == 19
    assert env.shelf_cell(19) == (2, 6)
    assert env.shelf_layer[6 * env.W + 2] == 25  # the floor shelf stays under the loaded AGV


def test_delivery_counts_on_start_of_step_position():
    env, (r1, r2) = _run("delivery_after_arrival", steps=2)
    assert r1.deliveries == 0 and r2.deliveries == 1 and 19 not in env.queue
    assert env.req[0] == TOGGLE and not env.busy[0]
    env, (r,) = _run("delivery_while_leaving_goal")
    assert r.deliveries == 1 and (env.x[0], env.y[0]) == (3, 14)


def _cells(lst):
    return [tuple(c) for c in lst]


def test_move_graph_matches_networkx_cases():
    for case in GRAPHS:
        starts, targets = _cells(case["starts"]), _cells(case["targets"])
        expected = _cells(case["commit"])
        assert sorted(set(networkx_commit_cells(starts, targets))) == expected
        assert sorted(set(commit_cells(starts, targets))) == expected


def test_fast_path_equals_emulation_on_random_graphs():
    rng = random.Random(11)
    for _ in range(3000):
        starts, targets, _, _ = _random_moves(rng, [(14, 15), (6, 5), (22, 35)], shared=0.08)
        assert sorted(set(commit_cells(starts, targets))) == sorted(set(networkx_commit_cells(starts, targets)))


def _random_moves(rng: random.Random, sizes, shared: float):
    """(starts, targets, W, H): up to 24 agents on a random grid of ``sizes``, a share ``shared`` of them on a cell
    another holds too, each staying or asking for a neighbouring cell."""
    W, H = rng.choice(sizes)
    starts = rng.sample([(x, y) for x in range(W) for y in range(H)], rng.randint(1, min(24, W * H)))
    for i in range(1, len(starts)):
        if rng.random() < shared:
            starts.append(starts[rng.randrange(i)])
    targets = []
    for x, y in starts:
        if rng.random() < 0.3:
            targets.append((x, y))
        else:
            dx, dy = rng.choice([(0, 1), (0, -1), (1, 0), (-1, 0)])
            targets.append((min(max(x + dx, 0), W - 1), min(max(y + dy, 0), H - 1)))
    return starts, targets, W, H


def _commit_as_the_warehouse_does(starts, targets, W, H):
    """The warehouse's Stage A: lone moves (cell and request nobody else names) directly, the rest by commit_flat
    on flat cells with the whole graph's node count; the committed cells as (x, y)."""
    flat_s = [y * W + x for x, y in starts]
    flat_t = [y * W + x for x, y in targets]
    uses = Counter(flat_s)
    uses.update(flat_t)
    out, rest = set(), []
    for k, (u, v) in enumerate(zip(flat_s, flat_t)):
        if (uses[u] == 2) if u == v else (uses[u] == 1 and uses[v] == 1):
            out.update((u, v))
        else:
            rest.append(k)
    cell_of = [(c % W, c // W) for c in range(W * H)]
    if rest:
        out.update(commit_flat([flat_s[k] for k in rest], [flat_t[k] for k in rest], len(uses), cell_of))
    return sorted(cell_of[c] for c in out)


def test_flat_cells_equal_emulation():
    for case in GRAPHS:
        starts, targets = _cells(case["starts"]), _cells(case["targets"])
        W = 1 + max(x for x, _ in starts + targets)
        H = 1 + max(y for _, y in starts + targets)
        assert _commit_as_the_warehouse_does(starts, targets, W, H) == _cells(case["commit"])
    rng = random.Random(12)
    for _ in range(3000):
        starts, targets, W, H = _random_moves(rng, [(14, 15), (6, 5), (22, 35), (3, 3)], shared=0.1)
        expected = sorted(set(networkx_commit_cells(starts, targets)))
        assert _commit_as_the_warehouse_does(starts, targets, W, H) == expected, (starts, targets)


def test_warehouse_stage_a_equals_emulation():
    """The warehouse's Stage A (lone agents and the small components it recognises from cell counts and layers,
    the rest through commit_flat) commits the agents the emulated networkx graph commits: crowded random states,
    AGVs and pickers sharing cells, agents staying, swapping and queueing."""
    rng = random.Random(13)
    env = Warehouse(WarehouseConfig.named("tiny", 6, 4, max_steps=10))
    env.reset(0)
    W, H = env.W, env.H
    for _ in range(3000):
        x0, y0 = rng.randrange(W - 3), rng.randrange(H - 3)
        area = [(x, y) for x in range(x0, x0 + 4) for y in range(y0, y0 + 4)]
        agv_cells = rng.sample(area, env.num_agvs)
        for i, (x, y) in enumerate(agv_cells):
            env.place_agent(i + 1, x, y, rng.randrange(4))
        free = [c for c in area if c not in agv_cells]
        picker_cells = rng.sample(free, env.num_pickers)
        for k in range(env.num_pickers):
            x, y = agv_cells[k] if rng.random() < 0.4 else picker_cells[k]
            env.place_agent(env.num_agvs + k + 1, x, y, rng.randrange(4))
        starts = list(env._layer_cells)
        targets = []
        for c in starts:
            x, y = c % W, c // W
            if rng.random() < 0.35:
                targets.append(c)
            else:
                dx, dy = rng.choice([(0, 1), (0, -1), (1, 0), (-1, 0)])
                targets.append(min(max(y + dy, 0), H - 1) * W + min(max(x + dx, 0), W - 1))
        committed, rest = env._stage_a(starts, targets, Counter(starts + targets))
        expected = set()
        for cx, cy in networkx_commit_cells([(c % W, c // W) for c in starts], [(c % W, c // W) for c in targets]):
            aid = env.agv_layer[cy * W + cx] or env.picker_layer[cy * W + cx]
            if aid:
                expected.add(aid)
        assert committed == expected, (starts, targets)



def test_merge_winner_equals_emulation():
    """Two one-move chains into one free cell, alone in their component among other agents: merge_winner names the
    start cell the emulated networkx graph commits (small graphs iterate a set, larger ones insertion order)."""
    rng = random.Random(3)
    grid = [(x, y) for x in range(40) for y in range(40)]
    won_second = 0
    for _ in range(3000):
        cells = rng.sample(grid, 3 + rng.randint(0, 6))
        first, second, sink = cells[:3]
        others = cells[3:]  # agents staying on their own cells: components of their own
        starts, targets = [first, second, *others], [sink, sink, *others]
        committed = set(networkx_commit_cells(starts, targets)) & {first, second}
        assert len(committed) == 1
        winner = merge_winner(first, second, sink, len(set(starts + targets)))
        assert {winner} == committed, (first, second, sink, others)
        won_second += winner == second
    assert 300 < won_second < 2700
