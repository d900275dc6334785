"""The reference's CTA controller ("Closest-Target Assignment" with its seven coordination fixes).

Per step the reference runs: (1) assign queued items to the
nearest free AGV, (2) advance every AGV's mission, (3-4) dispatch pickers through a gate, (5) release
pickers no longer needed ("sticky" release), (6) build macro actions, (7) step the warehouse. This class
splits that loop at the dispatch so the decision can be taken by the agents:

* :meth:`CTAController.begin_tick` runs (1)-(2) and returns the tick's :class:`TickObservation`;
* :meth:`CTAController.commit` applies the pickers' commitments (step 4's effect);
* :meth:`CTAController.finish_tick` runs (5)-(7) and records what the next observation reports about
  this step (missions during the step, deliveries, rewards, who loaded each delivered shelf).

Pure: no I/O, no randomness of its own (the warehouse owns the request stream). AGV path lengths are
Manhattan distances: the AGV planner on the obstacle-free grid returns exactly that (see layout.py).
Ties go to the first candidate in the reference's iteration order everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.fields import MissionType
from schemas.tick import NEEDS_PICKER, NO_CELL, TickObservation
from services.world.warehouse import StepResult, Warehouse

PICKING, DELIVERING, RETURNING = MissionType.PICKING, MissionType.DELIVERING, MissionType.RETURNING


@dataclass(slots=True)
class Mission:
    kind: MissionType
    action: int  # the target's macro action id
    x: int
    y: int
    t: int  # step at which it was assigned
    cell: tuple[int, int] = (0, 0)  # (x, y), filled in from x and y
    # what every tick's observation reads of it, as plain values (a mission never changes once made)
    code: int = 0  # kind's value
    needs_picker: bool = False  # kind in NEEDS_PICKER

    def __post_init__(self) -> None:
        self.cell = (self.x, self.y)
        self.code = self.kind.value
        self.needs_picker = self.kind in NEEDS_PICKER


class CTAController:
    """The reference controller around one :class:`Warehouse` (agent index = warehouse index, AGVs first)."""

    def __init__(self, warehouse: Warehouse) -> None:
        if warehouse.num_pickers == 0:
            raise ValueError("pickers: the CTA controller needs at least one picker")
        self.wh = warehouse
        self.n_agvs = warehouse.num_agvs
        self.n_pickers = warehouse.num_pickers
        self.n = warehouse.num_agents
        self.grid_shape = (warehouse.H, warehouse.W)
        self.t = 0
        #: the reference's demand-shift variant (shift.py; docs/morph.md): when set to "left"/"right", queued
        #: items on that half are assigned first and the others only when none of that half is waiting
        self.assignment_side: str | None = None
        #: robots that stand still in the next step whatever their path (the services' network safety stop)
        self.held: set[int] = set()
        #: robots that take no new target in the next step (their driver, a distributed run's agent, is absent)
        self.idle: set[int] = set()
        self._reset_state()

    def _reset_state(self) -> None:
        # insertion-ordered like the reference's OrderedDicts; overwriting a key keeps its slot
        self.agv_missions: dict[int, Mission] = {}
        self.picker_missions: dict[int, Mission] = {}
        self.items: dict[int, int] = {}  # AGV -> requested shelf id it serves (the task id)
        self.loader: dict[int, int] = {}  # AGV -> picker that was at the cell when it loaded
        n = self.n
        self._prev = dict(
            mission=np.zeros(n, dtype=np.int8),
            target=np.full((n, 2), NO_CELL, dtype=np.int64),
            task=np.zeros(n, dtype=np.int64),
            delivered=np.zeros(n, dtype=bool),
            reward=np.zeros(n),
            loader=np.full(n, -1, dtype=np.int64),
            handled=np.zeros(n, dtype=bool),
        )
        self._has_prev = False
        self.deliveries = 0
        self.last_result: StepResult | None = None

    def reset(self, seed: int, reseed_requests: bool = True) -> None:
        """Reset the warehouse with ``seed``, then re-seed its request stream as the reference does.

        The reference calls ``np.random.seed(seed)`` again right after ``env.reset(seed)``, so request
        replacements are drawn from a fresh stream. Doing the same here gives every condition
        the reference's request sequence; whether gate draws also come from that stream (the reference's
        single shared stream) is the lab's switch (:attr:`shared_rng`).
        """
        self.wh.reset(seed)
        if reseed_requests:
            self.wh.reseed(seed)
        self.t = 0
        self._reset_state()

    @property
    def shared_rng(self) -> np.random.RandomState:
        """The warehouse's request stream (used for gate draws only in shared-stream mode)."""
        return self.wh.rng

    # ------------------------------------------------------------------ step 1-2
    def _assign_items(self) -> None:
        wh = self.wh
        taken = set(self.items.values())
        x, y = wh.x, wh.y
        items = wh.queue
        if self.assignment_side is not None:
            # shift.py: iterate over the "preferred" (queued, unassigned, on the active half) if any, else the rest
            free = [it for it in wh.queue if it not in taken]
            preferred = [it for it in free if wh.on_side(it, self.assignment_side)]
            items = preferred or [it for it in free if it not in preferred]
        for item in items:
            if item in taken:
                continue
            avail = [
                a for a in range(self.n_agvs)
                if not wh.busy[a] and not wh.carrying[a] and a not in self.agv_missions
            ]
            if not avail:
                break  # the reference keeps looping, but no AGV can become available within the loop
            ix, iy = wh.shelf_cell(item)
            if wh.layout.highway[iy, ix]:
                continue  # a requested shelf on a highway is being carried: nothing to fetch
            best = min(avail, key=lambda a: abs(x[a] - ix) + abs(y[a] - iy))  # first on ties
            self.agv_missions[best] = Mission(PICKING, wh.cell_to_action((ix, iy)), ix, iy, self.t)
            self.items[best] = item
            taken.add(item)

    def _nearest_empty(self, agv: int, exclude_cell: tuple[int, int] | None) -> Mission | None:
        wh = self.wh
        empty = wh.empty_rack_actions()
        taken = {
            m.action for a, m in self.agv_missions.items() if a != agv and m.kind == RETURNING
        }
        cells = wh.layout.action_cells
        ids = [e for e in empty if e not in taken and (exclude_cell is None or cells[e] != exclude_cell)]
        ids = ids or empty
        if not ids:
            return None
        ax, ay = wh.x[agv], wh.y[agv]
        best = min(ids, key=lambda e: abs(cells[e][0] - ax) + abs(cells[e][1] - ay))
        bx, by = cells[best]
        return Mission(RETURNING, best, bx, by, self.t)

    def _advance_missions(self) -> None:
        wh = self.wh
        for agv in range(self.n_agvs):
            m = self.agv_missions.get(agv)
            if m is None or wh.busy[agv]:
                continue
            at = wh.x[agv] == m.x and wh.y[agv] == m.y
            if not at:
                continue
            carrying = bool(wh.carrying[agv])
            if m.kind == PICKING and carrying:
                helper = next(
                    (p for p, pm in self.picker_missions.items() if pm.cell == m.cell), -1
                )
                self.loader[agv] = helper
                ax, ay = wh.x[agv], wh.y[agv]
                gx, gy = min(wh.goals, key=lambda g: abs(g[0] - ax) + abs(g[1] - ay))
                self.agv_missions[agv] = Mission(DELIVERING, wh.cell_to_action((gx, gy)), gx, gy, self.t)
            elif m.kind == DELIVERING and carrying:
                nm = self._nearest_empty(agv, None)
                if nm is not None:
                    self.agv_missions[agv] = nm
            elif m.kind == RETURNING and not carrying:
                del self.agv_missions[agv]
                self.items.pop(agv, None)
                self.loader.pop(agv, None)
            elif m.kind == RETURNING and carrying:
                nm = self._nearest_empty(agv, (wh.x[agv], wh.y[agv]))
                if nm is not None:
                    self.agv_missions[agv] = nm

    # ------------------------------------------------------------------ observation
    def _targets(self):
        n = self.n
        # filled as lists and made arrays once: item writes into small numpy arrays cost more than the lists
        # (plain ints: numpy converts enum members and tuples one by one)
        mission = [0] * n
        target = [NO_CELL] * (2 * n)  # x0, y0, x1, y1, ...
        task = [0] * n
        serving: dict[tuple[int, int], int] = {}
        items = self.items
        for a, m in self.agv_missions.items():
            mission[a] = m.code
            target[2 * a], target[2 * a + 1] = m.cell
            task[a] = items.get(a, 0)
            if m.needs_picker and m.cell not in serving:
                serving[m.cell] = a
        for p, m in self.picker_missions.items():
            mission[p] = m.code
            target[2 * p], target[2 * p + 1] = m.cell
            a = serving.get(m.cell)
            task[p] = task[a] if a is not None else 0
        return (np.array(mission, dtype=np.int8), np.array(target, dtype=np.int64).reshape(n, 2),
                np.array(task, dtype=np.int64))

    def begin_tick(self) -> TickObservation:
        """Steps 1-2 for tick ``t``; the returned observation is what the agents see."""
        self._assign_items()
        self._advance_missions()
        mission, target, task = self._targets()
        picker_cells = {m.cell for m in self.picker_missions.values()}
        needs = [False] * self.n
        for a, m in self.agv_missions.items():
            needs[a] = m.needs_picker and m.cell not in picker_cells
        free = [False] * self.n_agvs + [p not in self.picker_missions for p in range(self.n_agvs, self.n)]
        prev = self._prev
        return TickObservation(
            t=self.t,
            n_agvs=self.n_agvs,
            n_pickers=self.n_pickers,
            grid_shape=self.grid_shape,
            cells=self.wh.positions(),
            mission=mission,
            target=target,
            task=task,
            needs_picker=np.array(needs, dtype=bool),
            free_picker=np.array(free, dtype=bool),
            request_order=np.fromiter(self.agv_missions.keys(), dtype=np.int64, count=len(self.agv_missions)),
            has_previous=self._has_prev,
            prev_mission=prev["mission"],
            prev_target=prev["target"],
            prev_task=prev["task"],
            delivered=prev["delivered"],
            reward=prev["reward"],
            loader=prev["loader"],
            handled=prev["handled"],
        )

    # ------------------------------------------------------------------ step 4
    def commit(self, commits) -> list[tuple[int, int]]:
        """Send each committed picker to its AGV's target; returns the commitments applied.

        ``commits`` are (picker, agv) pairs in mission order. A commitment is dropped if the picker is
        no longer free, the AGV needs no picker, or another picker was already sent to that cell this
        tick (the reference's one-picker-per-location cap).
        """
        applied = []
        cells = {m.cell for m in self.picker_missions.values()}
        for picker, agv in commits:
            m = self.agv_missions.get(agv)
            if picker in self.picker_missions or m is None or not m.needs_picker or m.cell in cells:
                continue
            self.picker_missions[picker] = Mission(PICKING, m.action, m.x, m.y, self.t)
            cells.add(m.cell)
            applied.append((picker, agv))
        return applied

    # ------------------------------------------------------------------ steps 5-7
    def _release(self) -> None:
        needed = {m.cell for m in self.agv_missions.values() if m.needs_picker}
        for p in [p for p, m in self.picker_missions.items() if m.cell not in needed]:
            del self.picker_missions[p]

    def actions(self) -> list[int]:
        acts = [0] * self.n
        busy = self.wh.busy
        for a, m in self.agv_missions.items():
            acts[a] = 0 if busy[a] else m.action
        for p, m in self.picker_missions.items():
            acts[p] = m.action
        for robot in self.idle:
            acts[robot] = 0  # macro action 0: no target, the robot stays where it is
        return acts

    def finish_tick(self) -> StepResult:
        """Release, act, step the warehouse; returns the warehouse's step result."""
        self._release()
        mission, target, task = self._targets()
        acts = self.actions()
        carried_before = list(self.wh.carrying[: self.n_agvs])
        result = self.wh.step(acts, hold=sorted(self.held))
        rewards = np.asarray(result.rewards, dtype=float)
        na = self.n_agvs
        # per robot in plain Python, made arrays once (a fleet is too small for numpy's calls to pay)
        reward_list = result.rewards
        delivered_list = [r > 0.5 for r in reward_list[:na]] + [False] * (self.n - na)  # the reference's count
        loader = [self.loader.get(a, -1) if d else -1 for a, d in enumerate(delivered_list)]
        carrying = self.wh.carrying
        # an AGV's load or unload, always with a picker here; the picker's +0.1 per load/unload
        handled = [carrying[a] != carried_before[a] for a in range(na)] + [r > 0.05 for r in reward_list[na:]]
        delivered = np.array(delivered_list, dtype=bool)
        self._prev = dict(mission=mission, target=target, task=task, delivered=delivered,
                          reward=rewards, loader=np.array(loader, dtype=np.int64),
                          handled=np.array(handled, dtype=bool))
        self._has_prev = True
        self.deliveries += sum(delivered_list)
        self.last_result = result
        self.t += 1
        return result

    def final_observation(self) -> TickObservation:
        """The observation after the last step, for the agents' last update (no dispatch follows).

        It reports the last step without running the controller for a new tick.
        """
        mission, target, task = self._targets()
        prev = self._prev
        zeros = np.zeros(self.n, dtype=bool)
        return TickObservation(
            t=self.t, n_agvs=self.n_agvs, n_pickers=self.n_pickers, grid_shape=self.grid_shape,
            cells=self.wh.positions(), mission=mission, target=target, task=task,
            needs_picker=zeros, free_picker=zeros, request_order=np.zeros(0, dtype=np.int64),
            has_previous=self._has_prev, prev_mission=prev["mission"], prev_target=prev["target"],
            prev_task=prev["task"], delivered=prev["delivered"], reward=prev["reward"], loader=prev["loader"],
            handled=prev["handled"], final=True,
        )


# ---------------------------------------------------------------------------------------------------
# resolving requests
