"""TA-RWARE's shipped heuristic controller (original: tarware/heuristic.py).

FIFO order assignment: each requested shelf, in queue order, gets the closest free AGV; AGVs then deliver to the
closest goal and return the shelf to the closest empty rack cell; each picker serves its zone (a contiguous chunk
of rack blocks), always the oldest AGV job there. Distances are the planner's path lengths on the obstacle-free
AGV grid, which equal Manhattan distances (verified for every layout in tests/test_astar.py), so they are computed
in closed form here; ties go to the first candidate, as ``np.argmin`` does.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from services.world.warehouse import PICKER, STEP_PENALTY, StepResult, Warehouse, WarehouseConfig, episode_digest


class MissionType(Enum):
    PICKING = 1
    RETURNING = 2
    DELIVERING = 3


@dataclass(slots=True)
class Mission:
    kind: MissionType
    location_id: int
    x: int
    y: int
    assigned_time: int
    at_location: bool = False
    picker: int | None = None  # the picker whose zone holds the cell, for jobs that need one (picking, returning)


def split_list(items: list, n_groups: int) -> list[list]:
    """Contiguous chunks whose lengths differ by at most one; the first ``len % n`` chunks are the longer ones."""
    k, m = divmod(len(items), n_groups)
    return [items[i * k + min(i, m):(i + 1) * k + min(i + 1, m)] for i in range(n_groups)]


class HeuristicController:
    """Produces one macro action per agent per step for a :class:`Warehouse` that has been reset."""

    def __init__(self, env: Warehouse):
        if env.num_pickers == 0:
            raise ValueError("pickers: the heuristic controller needs at least one picker (it splits zones by picker)")
        self.env = env
        self.agvs = [i for i in range(env.num_agents) if env.types[i] != PICKER]
        self.pickers = [i for i in range(env.num_agents) if env.types[i] == PICKER]
        zones = [[c for group in chunk for c in group] for chunk in split_list(env.layout.rack_groups,
                                                                                 len(self.pickers))]
        # zones are disjoint, so "the first picker whose zone holds the cell" is a plain lookup
        self.zone_picker: dict[tuple[int, int], int] = {}
        for k, zone in enumerate(zones):
            for cell in zone:
                self.zone_picker.setdefault(cell, self.pickers[k])
        self.zones = zones
        self.assigned_agvs: dict[int, Mission] = {}  # insertion-ordered, like the original's OrderedDict
        self.assigned_pickers: dict[int, Mission] = {}
        self.assigned_items: dict[int, int] = {}  # AGV index -> shelf id
        self._item_ids: set[int] = set()
        self.timestep = 0

    def actions(self) -> list[int]:
        env = self.env
        xs, ys, busy, carrying = env.x, env.y, env.busy, env.carrying
        lay = env.layout
        t = self.timestep
        assigned_agvs = self.assigned_agvs

        # 1. order assignment: queue order, closest free AGV (first minimum)
        available = [a for a in self.agvs if not busy[a] and not carrying[a] and a not in assigned_agvs]
        if available:
            for sid in env.queue:
                if sid in self._item_ids:
                    continue
                if not available:
                    break
                ix, iy = env.shelf_x[sid - 1], env.shelf_y[sid - 1]
                best = available[0]
                best_d = abs(xs[best] - ix) + abs(ys[best] - iy)
                for a in available[1:]:
                    d = abs(xs[a] - ix) + abs(ys[a] - iy)
                    if d < best_d:
                        best, best_d = a, d
                loc = lay.cell_to_action_id((ix, iy))
                assigned_agvs[best] = Mission(MissionType.PICKING, loc, ix, iy, t, picker=self.zone_picker[(ix, iy)])
                self.assigned_items[best] = sid
                self._item_ids.add(sid)
                available.remove(best)

        # 2. AGV transitions
        for a in self.agvs:
            m = assigned_agvs.get(a)
            if m is None:
                continue
            if xs[a] == m.x and ys[a] == m.y:
                m.at_location = True
            if busy[a]:
                continue
            if m.kind is MissionType.PICKING and m.at_location and carrying[a]:
                gx, gy = min(lay.goals, key=lambda g: abs(xs[a] - g[0]) + abs(ys[a] - g[1]))
                del assigned_agvs[a]
                m = assigned_agvs[a] = Mission(MissionType.DELIVERING, lay.cell_to_action_id((gx, gy)), gx, gy, t)
            if m.kind is MissionType.DELIVERING and m.at_location and carrying[a]:
                taken = {mm.location_id for mm in assigned_agvs.values()}
                empty = [loc for loc in env.empty_rack_actions() if loc not in taken]
                if not empty:
                    raise RuntimeError(f"heuristic: AGV {a + 1} has no empty rack cell to return its shelf to")
                best_loc = min(empty, key=lambda loc: abs(xs[a] - lay.action_cells[loc][0])
                               + abs(ys[a] - lay.action_cells[loc][1]))
                cx, cy = lay.action_cells[best_loc]
                del assigned_agvs[a]
                m = assigned_agvs[a] = Mission(MissionType.RETURNING, best_loc, cx, cy, t,
                                               picker=self.zone_picker[(cx, cy)])
            if m.kind is MissionType.RETURNING and m.at_location and not carrying[a]:
                del assigned_agvs[a]
                self._item_ids.discard(self.assigned_items.pop(a))

        # 3. each picker takes the oldest AGV job in its zone
        assigned_pickers = self.assigned_pickers
        if len(assigned_pickers) < len(self.pickers):  # else no picker is free to take a job
            for m in assigned_agvs.values():
                p = m.picker
                if p is not None and p not in assigned_pickers:
                    assigned_pickers[p] = Mission(MissionType.PICKING, m.location_id, m.x, m.y, t)

        # 4. a picker that reached its cell drops the mission
        for p in self.pickers:
            m = assigned_pickers.get(p)
            if m is not None and xs[p] == m.x and ys[p] == m.y:
                m.at_location = True
                del assigned_pickers[p]

        # 5. actions
        out = [0] * env.num_agents
        for a, m in assigned_agvs.items():
            out[a] = 0 if busy[a] else m.location_id
        for p, m in assigned_pickers.items():
            out[p] = m.location_id
        self.timestep += 1
        return out


@dataclass
class EpisodeResult:
    deliveries: int
    deliveries_per_step: list[int]
    clashes: int
    stucks: int
    global_return: float
    steps: int
    seconds: float
    step_digests: list[str] = field(default_factory=list)

    @property
    def digest(self) -> str:
        return episode_digest(self.step_digests)

    def cumulative(self, every: int = 100) -> list[int]:
        total, out = 0, []
        for t, d in enumerate(self.deliveries_per_step, start=1):
            total += d
            if t % every == 0:
                out.append(total)
        return out

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("inf")


def run_episode(config: WarehouseConfig, seed: int | None, *, digests: bool = False,
                on_step: Callable[[Warehouse, StepResult], None] | None = None) -> EpisodeResult:
    """One episode of ``config.max_steps`` steps under the heuristic, timed (controller included)."""
    env = Warehouse(config)
    t0 = time.perf_counter()
    env.reset(seed)
    ctrl = HeuristicController(env)
    per_step: list[int] = []
    rows: list[str] = []
    clashes = stucks = 0
    ret = 0.0
    # Most steps pay every agent the step penalty only, and the other reward rows repeat too: each distinct row
    # is summed once (np.add.reduce is what np.sum computes for a list, without its Python wrapper). No reward is
    # ever zero, so equal rows hold bit-equal floats and have bit-equal sums.
    penalty_row = [0.0 - STEP_PENALTY] * env.num_agents
    penalty_sum = float(np.sum(penalty_row))
    row_sums: dict[tuple[float, ...], float] = {}
    done = False
    while not done:
        res = env.step(ctrl.actions())
        per_step.append(res.deliveries)
        clashes += res.clashes
        stucks += res.stucks
        if res.rewards == penalty_row:
            ret += penalty_sum
        else:
            row = tuple(res.rewards)
            row_sum = row_sums.get(row)
            if row_sum is None:
                row_sum = row_sums[row] = float(np.add.reduce(res.rewards, axis=None))
            ret += row_sum
        if digests:
            rows.append(env.digest_row())
        if on_step is not None:
            on_step(env, res)
        done = res.done
    seconds = time.perf_counter() - t0
    return EpisodeResult(sum(per_step), per_step, clashes, stucks, ret, env.steps, seconds, rows)
