"""TA-RWARE's warehouse dynamics, re-implemented to reproduce the original's trajectories bit for bit.

The original: uoe-agents/task-assignment-robotic-warehouse@6109c33, tarware/warehouse.py. One :class:`Warehouse` is one environment with its own ``np.random.RandomState``, drawn
from in the original's order, so a run equals the original run in a fresh process.

Per-agent state lives in plain Python lists (one entry per agent, id order; agent id = index + 1) and the grid
layers in flat lists indexed ``y * W + x``: the step loop reads and writes single entries, which is several times
faster on lists than on numpy arrays. Read-only numpy copies are offered as properties for controllers and
renderers. The layers are rebuilt only at the end of a step, as in the original, so phases 1-6 of a step see the
positions from the start of the step.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from enum import IntEnum
from itertools import filterfalse
from typing import Literal

import numpy as np
from numpy.random import RandomState  # numpy loads its random module lazily: load it with this module, not in reset
from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas.fields import Heading as Direction  # TA-RWARE's name for a robot's heading, one enum on the wire and here
from services.world.astar import Planner
from services.world.conflicts import commit_flat, merge_winner
from services.world.layout import Layout, LayoutConfig, layout_for


class Action(IntEnum):
    """Micro actions (one per step); the macro actions agents receive are target cell ids."""

    NOOP = 0
    LEFT = 1
    RIGHT = 2
    FORWARD = 3
    TOGGLE_LOAD = 4


NOOP, TURN_LEFT, TURN_RIGHT, FORWARD, TOGGLE = 0, 1, 2, 3, 4
AGV, PICKER, AGENT = 0, 1, 2
FIXING_CLASH_TIME = 4
STUCK_THRESHOLD = 5
STEP_PENALTY = 0.001
# Headings in clockwise order UP, RIGHT, DOWN, LEFT, and each heading's position in it.
_CLOCKWISE = (Direction.UP, Direction.RIGHT, Direction.DOWN, Direction.LEFT)
_CW_INDEX = (0, 2, 3, 1)  # indexed by Direction value
_HEADING_OF_DELTA = {(0, -1): 0, (0, 1): 1, (-1, 0): 2, (1, 0): 3}
_DELTA_OF_HEADING = ((0, -1), (0, 1), (-1, 0), (1, 0))


def _turn_or_move(heading: int, needed: int) -> int:
    d = (_CW_INDEX[heading] - _CW_INDEX[needed]) % 4
    if d == 0:
        return FORWARD
    return TURN_LEFT if d == 1 else TURN_RIGHT


# the heading after a turn: _TURNED[micro action][heading] for TURN_LEFT and TURN_RIGHT
_TURNED = {turn: tuple(int(_CLOCKWISE[(_CW_INDEX[h] + (1 if turn == TURN_RIGHT else -1)) % 4]) for h in range(4))
           for turn in (TURN_LEFT, TURN_RIGHT)}
# (dx, dy) to the next path cell -> the micro action for each current heading (index = heading value)
_MICRO_TOWARDS = {delta: tuple(_turn_or_move(h, needed) for h in range(4)) for delta, needed in _HEADING_OF_DELTA.items()}


class WarehouseConfig(BaseModel):
    """A warehouse run: layout, fleet and episode length."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    layout: LayoutConfig
    agvs: int = Field(ge=0, description="number of AGVs (ids 1..agvs)")
    pickers: int = Field(ge=0, description="number of pickers (ids after the AGVs)")
    max_steps: int = Field(default=500, ge=1, description="episode length in steps (the original registers 500)")
    reward_type: Literal["individual", "global"] = "individual"
    max_inactivity_steps: int | None = Field(default=None, ge=1)

    @model_validator(mode="after")
    def _fleet_fits(self) -> WarehouseConfig:
        if self.agvs + self.pickers < 1:
            raise ValueError("agvs: the fleet needs at least one agent (agvs + pickers >= 1)")
        cells = len(layout_for(self.layout).highway_cells)
        if self.agvs + self.pickers > cells:
            raise ValueError(
                f"agvs: {self.agvs} AGVs + {self.pickers} pickers exceed the {cells} highway cells they spawn on"
            )
        return self

    @classmethod
    def named(cls, scale: str, agvs: int | None = None, pickers: int | None = None, **kw) -> WarehouseConfig:
        """A named size with its default fleet unless counts are given."""
        from services.world.layout import named_sizes

        sizes = named_sizes()
        if scale not in sizes:
            raise ValueError(f"scale: unknown size {scale!r}; choose one of {', '.join(sizes)}")
        layout, d_agvs, d_pickers = sizes[scale]
        return cls(layout=layout, agvs=d_agvs if agvs is None else agvs,
                   pickers=d_pickers if pickers is None else pickers, **kw)


@dataclass(slots=True)
class StepResult:
    """What one step produced (the original's ``info`` plus rewards and termination)."""

    deliveries: int
    clashes: int
    stucks: int
    rewards: list[float]
    agvs_distance: int
    pickers_distance: int
    agvs_idle: int
    pickers_idle: int
    done: bool
    loads: int = 0
    unloads: int = 0
    delivered_by: list[int] = field(default_factory=list)  # AGV ids whose delivery was counted, goal x order


# The cell a FORWARD reaches from each flat cell, by heading (index = heading value), clipped to the grid like the
# original's move; built once per layout.
_AHEAD: dict[object, list[tuple[int, int, int, int]]] = {}


def _ahead_table(H: int, W: int) -> list[tuple[int, int, int, int]]:
    table = []
    for c in range(H * W):
        y, x = divmod(c, W)
        table.append((c - W if y > 0 else c, c + W if y < H - 1 else c,  # UP, DOWN
                      c - 1 if x > 0 else c, c + 1 if x < W - 1 else c))  # LEFT, RIGHT
    return table


def micro_action_towards(x: int, y: int, heading: int, nxt: tuple[int, int]) -> int:
    """Turn or move towards the adjacent cell ``nxt``: a 180° turn is two RIGHT turns."""
    try:
        return _MICRO_TOWARDS[(nxt[0] - x, nxt[1] - y)][heading]
    except KeyError:
        raise RuntimeError(f"path cell {nxt} is not adjacent to ({x}, {y})") from None


class Warehouse:
    """One warehouse environment. ``reset(seed)`` then ``step(actions)`` with one macro action per agent."""

    def __init__(self, config: WarehouseConfig):
        self.config = config
        self.layout: Layout = layout_for(config.layout)
        self.planner = Planner(self.layout)
        lay = self.layout
        self.H, self.W = lay.H, lay.W
        self.num_agvs = config.agvs
        self.num_pickers = config.pickers
        self.num_agents = config.agvs + config.pickers
        if config.pickers > 0:
            self.types = [AGV] * config.agvs + [PICKER] * config.pickers
        else:
            self.types = [AGENT] * self.num_agents
        self._highway = lay.highway.reshape(-1).tolist()
        self._goal_idx = [gy * self.W + gx for gx, gy in lay.goals]
        self._cell_xy = self.planner.cells
        ahead = _AHEAD.get(config.layout)
        if ahead is None:
            ahead = _AHEAD[config.layout] = _ahead_table(self.H, self.W)
        self._ahead = ahead
        self._goal_cells = set(self._goal_idx)
        # agents of each layer, in id order: AGVs (or agents without a kind) first, then pickers
        self._agv_range = range(self.num_agents if config.pickers == 0 else config.agvs)
        self._picker_range = range(len(self._agv_range), self.num_agents)
        self._rack_action_cells = [(a, lay.action_cells[a][1] * self.W + lay.action_cells[a][0])  # type: ignore[index]
                                   for a in lay.rack_action_ids]
        self._unstick_limit = STUCK_THRESHOLD + config.layout.column_height + 2
        self._global_reward = config.reward_type == "global"
        self.steps = 0
        self._rng: np.random.RandomState | None = None
        #: demand shift: None = requests drawn from every shelf (TA-RWARE); "left"/"right" = replacement
        #: requests drawn only from shelves whose *current* cell has x < split_x ("left") or x >= split_x ("right")
        self.demand_side: str | None = None
        self.demand_split_x = self.W // 2  # shift.py's half_x = floor(W_grid / 2): 11 at Medium, 80/80 shelves

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | None = None) -> None:
        """Spawn agents and draw the initial requests with a fresh RNG seeded by ``seed``.

        ``seed=None`` seeds from OS entropy, like the original; pass a seed for a reproducible episode.
        """
        lay, N, W = self.layout, self.num_agents, self.W
        self._rng = rng = RandomState(seed)
        self.steps = 0
        self.inactive_steps = 0
        spawn = rng.permutation(len(lay.highway_cells))[:N]
        headings = rng.randint(0, 4, N)
        self.x = [lay.highway_cells[k][0] for k in spawn.tolist()]
        self.y = [lay.highway_cells[k][1] for k in spawn.tolist()]
        self.dir = [int(d) for d in headings.tolist()]
        self.req: list[int | None] = [None] * N
        self.busy = [False] * N
        self.carrying = [0] * N  # carried shelf id, 0 = none
        self.path: list[list[tuple[int, int]]] = [[] for _ in range(N)]
        self.fixing = [0] * N
        self.target = [0] * N
        self.has_delivered = [False] * N
        self.stuck_cell = [self.y[i] * W + self.x[i] for i in range(N)]  # flat cell where the stuck count began
        self.stuck_count = [0] * N
        self.shelf_x = [c[0] for c in lay.shelf_cells]
        self.shelf_y = [c[1] for c in lay.shelf_cells]
        n_cells = self.H * W
        self.agv_layer = [0] * n_cells
        self.picker_layer = [0] * n_cells
        self.shelf_layer = [0] * n_cells
        self.carried_layer = [0] * n_cells
        for sid, (sx, sy) in enumerate(lay.shelf_cells, start=1):
            self.shelf_layer[sy * W + sx] = sid
        self._write_agent_layers()
        self.queue: list[int] = [int(k) + 1 for k in rng.permutation(lay.num_shelves)[: lay.config.request_queue_size]]

    def _write_agent_layers(self, cells: list[int] | None = None) -> None:
        """Write the agents and their carried shelves into the layers; the cells written are remembered, both to
        clear them at the next step's end and as the agents' cells (the obstacles of re-plans) until then.

        ``cells``: the agents' flat cells if the caller has them, else they are computed from x and y. Each layer is
        written in id order, as a single loop over all agents would (the layers are separate lists)."""
        if cells is None:
            W = self.W
            cells = [y * W + x for x, y in zip(self.x, self.y)]
        agv_layer = self.agv_layer
        for i in self._agv_range:
            agv_layer[cells[i]] = i + 1
        picker_layer = self.picker_layer
        for i in self._picker_range:
            picker_layer[cells[i]] = i + 1
        carried_layer = self.carried_layer
        for i, sid in enumerate(self.carrying):
            if sid:
                carried_layer[cells[i]] = sid
        self._layer_cells = cells

    def set_demand_side(self, side: str | None) -> None:
        """Demand shift: draw replacement requests from one half of the shelves from now on (None: all).

        Requests already in the queue stay (they are served as usual); the queue turns over one request per
        counted delivery, each replacement drawn from the active half."""
        if side not in (None, "left", "right"):
            raise ValueError(f"demand_side: expected None, 'left' or 'right', got {side!r}")
        self.demand_side = side

    def on_side(self, shelf_id: int, side: str) -> bool:
        """Whether shelf ``shelf_id`` currently stands in the ``side`` half (x < split_x is left)."""
        left = self.shelf_x[shelf_id - 1] < self.demand_split_x
        return left if side == "left" else not left

    @property
    def rng(self) -> np.random.RandomState:
        """This environment's random stream (request replacements draw from it). Controllers that, like the
        reference MORPH code, share the stream with the environment may draw from it; doing so changes later
        replacement requests, exactly as in the original's single global stream."""
        if self._rng is None:
            raise RuntimeError("rng: reset() has not been called")
        return self._rng

    def reseed(self, seed: int) -> None:
        """Re-seed the environment's stream in place (the reference MORPH script calls ``np.random.seed(seed)``
        again right after ``env.reset(seed)``)."""
        self.rng.seed(seed)

    # ------------------------------------------------------------------ scenario set-up
    def place_agent(self, agent_id: int, x: int, y: int, heading: int, carrying: int = 0) -> None:
        """Put agent ``agent_id`` (1-based) on (x, y) facing ``heading``, optionally carrying shelf ``carrying``
        (which then leaves its floor cell). For hand-built scenarios; call between steps, after reset."""
        i = agent_id - 1
        if not (0 <= x < self.W and 0 <= y < self.H):
            raise ValueError(f"x/y: ({x}, {y}) is outside the {self.W}x{self.H} grid")
        if carrying and not 1 <= carrying <= self.layout.num_shelves:
            raise ValueError(f"carrying: no shelf {carrying}")
        self.x[i], self.y[i], self.dir[i] = x, y, int(heading)
        self.carrying[i] = carrying
        if carrying:
            self.shelf_x[carrying - 1], self.shelf_y[carrying - 1] = x, y
        self.stuck_cell[i] = y * self.W + x
        self.stuck_count[i] = 0
        self.rebuild_layers()

    def set_path(self, agent_id: int, cells: list[tuple[int, int]], target: int = 0) -> None:
        """Make agent ``agent_id`` busy following ``cells`` (x, y), as if a macro action had been planned."""
        i = agent_id - 1
        self.path[i] = [(int(cx), int(cy)) for cx, cy in cells]
        self.busy[i] = True
        self.target[i] = target

    def rebuild_layers(self) -> None:
        """Rebuild all four layers from agents and shelves, as the original's ``_recalc_grid`` does."""
        W = self.W
        n = self.H * W
        self.agv_layer = [0] * n
        self.picker_layer = [0] * n
        self.carried_layer = [0] * n
        self.shelf_layer = [0] * n
        carried = {s for s in self.carrying if s}
        for k in range(self.layout.num_shelves):
            if k + 1 not in carried:
                self.shelf_layer[self.shelf_y[k] * W + self.shelf_x[k]] = k + 1
        self._write_agent_layers()

    # ------------------------------------------------------------------ helpers
    def req_location(self, i: int) -> tuple[int, int]:
        """The cell agent ``i`` (index) asks for this step: its own unless moving forward (clipped to the grid)."""
        x, y = self.x[i], self.y[i]
        if self.req[i] != FORWARD:
            return x, y
        d = self.dir[i]
        if d == 0:
            return x, max(0, y - 1)
        if d == 1:
            return x, min(self.H - 1, y + 1)
        if d == 2:
            return max(0, x - 1), y
        return min(self.W - 1, x + 1), y

    def _reset_stuck(self, i: int) -> None:
        self.stuck_count[i] = 0
        self.stuck_cell[i] = self.y[i] * self.W + self.x[i]

    # ------------------------------------------------------------------ step
    def step(self, actions, hold=()) -> StepResult:
        """Advance one step. ``actions``: one macro action per agent (0 = none, 1..G goals, then rack cells).
        ``hold``: agents (0-based) that stand still this step whatever their path — no move, no load or unload —
        and keep their path and mission for the next step (a robot stopped from outside, e.g. a safety stop)."""
        if self._rng is None:
            raise RuntimeError("step() before reset()")
        actions = list(map(int, actions))
        if len(actions) != self.num_agents:
            raise ValueError(f"actions: expected {self.num_agents} macro actions, got {len(actions)}")
        agv_dist, picker_dist = self._attribute(actions)
        for i in hold:
            if not 0 <= i < self.num_agents:
                raise ValueError(f"hold: agent {i} outside 0..{self.num_agents - 1}")
            self.req[i] = NOOP
        clashes = self._resolve_conflicts()
        stucks = self._resolve_stuck()
        N = self.num_agents
        rewards = [0.0 - STEP_PENALTY] * N
        loads, unloads = self._execute(rewards)
        deliveries, delivered_by = self._deliver(rewards)
        self._recalc_layers()
        self.steps += 1
        limit = self.config.max_inactivity_steps
        done = self.steps >= self.config.max_steps or (limit is not None and self.inactive_steps >= limit)
        na = self.num_agvs
        agv_req, picker_req = self.req[:na], self.req[na:]
        return StepResult(
            deliveries=deliveries, clashes=clashes, stucks=stucks, rewards=rewards,
            agvs_distance=agv_dist, pickers_distance=picker_dist,
            agvs_idle=agv_req.count(NOOP) + agv_req.count(TOGGLE),
            pickers_idle=picker_req.count(NOOP) + picker_req.count(TOGGLE), done=done,
            loads=loads, unloads=unloads, delivered_by=delivered_by,
        )

    def _attribute(self, actions: list[int]) -> tuple[int, int]:
        """Phase 1: macro action -> path for idle agents, next micro action for busy ones."""
        W = self.W
        cells = self.layout.action_cells
        n_actions = len(cells)
        agv_dist = picker_dist = 0
        req, types, path, busy, fixing = self.req, self.types, self.path, self.busy, self.fixing
        xs, ys, dirs, target = self.x, self.y, self.dir, self.target
        find_path = self.planner.find_path
        for i in range(self.num_agents):
            req[i] = NOOP
            if fixing[i] > 0:
                fixing[i] -= 1
            if not busy[i]:
                target[i] = 0
                a = actions[i]
                if a != 0:
                    if not 0 < a < n_actions:
                        raise ValueError(f"actions: agent {i + 1} asked for target {a}, valid are 0..{n_actions - 1}")
                    x, y = xs[i], ys[i]
                    p = find_path((x, y), cells[a], types[i] == PICKER)  # type: ignore[arg-type]
                    path[i] = p
                    if p:
                        busy[i] = True
                        target[i] = a
                        req[i] = micro_action_towards(x, y, dirs[i], p[0])
                        self.stuck_count[i] = 0
                        self.stuck_cell[i] = y * W + x
                continue
            p = path[i]
            t = types[i]
            if not p:
                if t == PICKER:
                    busy[i] = False
                else:
                    req[i] = TOGGLE
                continue
            nxt = p[0]
            try:  # micro_action_towards(), inlined
                req[i] = _MICRO_TOWARDS[(nxt[0] - xs[i], nxt[1] - ys[i])][dirs[i]]
            except KeyError:
                raise RuntimeError(f"path cell {nxt} is not adjacent to ({xs[i]}, {ys[i]})") from None
            if t == AGV:
                agv_dist += 1
            elif t == PICKER:
                picker_dist += 1
            if len(p) == 1:
                fx, fy = p[0]
                c = fy * W + fx
                # a loaded agent whose return cell got a shelf meanwhile gives up
                if self.carrying[i] and self.shelf_layer[c]:
                    req[i] = NOOP
                    busy[i] = False
                # a picker steps onto its last cell only once the AGV there is toggling (set earlier this loop)
                if t == PICKER:
                    aid = self.agv_layer[c]
                    if aid == 0 or req[aid - 1] != TOGGLE:
                        req[i] = NOOP
                    else:
                        self._reset_stuck(i)
        return agv_dist, picker_dist

    def _resolve_conflicts(self) -> int:
        """Phase 2: move graph (Stage A), then the pairwise clash loop (Stage B), then the final veto, on flat cell
        indices."""
        req, dirs = self.req, self.dir
        # the agents' cells at the start of the step, where the layers were last written (phase 5 moves them)
        starts = self._layer_cells
        ahead = self._ahead
        # req_location() of every agent, on flat cells
        targets = [ahead[c][d] if r == FORWARD else c for c, d, r in zip(starts, dirs, req)]
        # how many starts and requests name each cell (each key is a node of the move graph); a plain dict, as
        # every cell looked up is a start or a request (a Counter costs twice as much to build)
        uses: dict[int, int] = {}
        count = uses.get
        for c in starts:
            uses[c] = count(c, 0) + 1
        for c in targets:
            uses[c] = count(c, 0) + 1
        committed, rest = self._stage_a(starts, targets, uses)
        if not rest:
            return 0
        clashes = self._clash_loop(starts, targets, uses, committed)
        for i in rest:
            if i + 1 not in committed:
                req[i] = NOOP
        return clashes

    def _stage_a(self, starts: list[int], targets: list[int], uses: dict[int, int]) -> tuple[set[int], list[int]]:
        """Stage A on flat cells: the ids of the agents the move graph commits, and the indices of the agents that
        are not alone in their component (the only ones Stage B and the veto can concern).

        ``uses`` counts the starts and requests naming each cell. An agent whose cell and requested cell nobody else
        names is a component on its own, always committed. A few small components make most of the others, and
        the counts and the layers identify them whole; their answers need no graph (the graph commits cells, and a
        committed cell commits its AGV, else its picker):

        * an AGV and a picker both staying on a cell nobody else names: a 1-cycle, the AGV is committed;
        * an AGV and a picker on a cell nobody else names, one staying, the other asking for a cell nobody else
          names: the staying one's 1-cycle is the component's only cycle, so the cell is committed: its AGV;
        * two agents asking for each other's cells, which nobody else names: a head-on 2-cycle, nobody;
        * an agent asking for the cell of one that stays, both cells named by nobody else: the 1-cycle, the one
          that stays;
        * an agent asking for the cell of one that asks for a cell nobody names, all three cells named by nobody
          else: a chain into a free cell, the longest path, both;
        * an AGV and a picker on a cell nobody else names, both leaving it for cells nobody else names (one cell or
          two): no cycle, and every longest path is one move out of the shared cell, so whichever networkx takes,
          the shared cell is committed, and with it the AGV (the other end is an empty cell);
        * two agents on cells nobody else names asking for one free cell nobody else names: a tie between two
          one-move chains, which networkx's node order decides (:func:`merge_winner`).

        Every other component goes through :func:`commit_flat`.
        """
        N = self.num_agents
        agv_layer, picker_layer = self.agv_layer, self.picker_layer
        committed: set[int] = set()
        rest = []
        for i in range(N):
            u, v = starts[i], targets[i]
            if (uses[u] == 2) if u == v else (uses[u] == 1 and uses[v] == 1):
                committed.add(i + 1)
            else:
                rest.append(i)
        settled: set[int] = set()  # agents of rest whose component was identified whole
        for i in rest:
            if i in settled:
                continue
            u, v = starts[i], targets[i]
            n_u = uses[u]
            if n_u == 4 or n_u == 3:  # maybe an AGV and a picker sharing the cell
                a, p = agv_layer[u] - 1, picker_layer[u] - 1
                if a < 0 or p < 0 or (i != a and i != p):
                    continue
                k = p if i == a else a  # the other one
                w = targets[k]
                if n_u == 4:
                    found = u == v and w == u
                elif u == v:
                    found = w != u and uses[w] == 1
                else:
                    found = w == u and uses[v] == 1
                if found:
                    committed.add(a + 1)
                    settled.add(a)
                    settled.add(p)
            elif u != v:
                n_v = uses[v]
                j = (agv_layer[v] or picker_layer[v]) - 1
                if j < 0:
                    if n_u == 2:  # maybe an AGV and a picker leaving the cell they share
                        a, p = agv_layer[u] - 1, picker_layer[u] - 1
                        if a >= 0 and p >= 0 and (i == a or i == p):
                            w = targets[p if i == a else a]
                            if w != u and ((n_v == 2 and uses[w] == 2) if w == v else (n_v == 1 and uses[w] == 1)):
                                committed.add(a + 1)
                                settled.add(a)
                                settled.add(p)
                    elif n_u == 1 and n_v == 2:  # maybe two agents asking for the same free cell
                        k = targets.index(v)  # nobody stands on v: both namings of v are requests
                        if k == i:
                            k = targets.index(v, i + 1)
                        w = starts[k]
                        if uses[w] == 1:
                            xy = self._cell_xy
                            first, second = (u, w) if i < k else (w, u)
                            win = merge_winner(xy[first], xy[second], xy[v], len(uses))
                            committed.add((i if win == xy[u] else k) + 1)
                            settled.add(i)
                            settled.add(k)
                    continue
                w = targets[j]
                if n_u == 2 and n_v == 2:
                    if w == u:  # head-on
                        settled.add(i)
                        settled.add(j)
                elif n_u == 1 and n_v == 3:
                    if w == v:  # behind one that stays
                        committed.add(j + 1)
                        settled.add(i)
                        settled.add(j)
                elif n_u == 1 and n_v == 2:
                    if w != v and uses[w] == 1:  # a chain into a free cell
                        committed.add(i + 1)
                        committed.add(j + 1)
                        settled.add(i)
                        settled.add(j)
        moves = [i for i in rest if i not in settled] if settled else rest
        if moves:
            for c in commit_flat([starts[i] for i in moves], [targets[i] for i in moves], len(uses), self._cell_xy):
                aid = agv_layer[c]
                if aid:
                    committed.add(aid)
                    continue
                pid = picker_layer[c]
                if pid:
                    committed.add(pid)
        return committed, rest

    def _clash_loop(self, starts: list[int], targets: list[int], uses: dict[int, int], committed: set[int]) -> int:
        """Stage B, literally in id order, on flat cells. Requests change inside the loop, so requested cells are
        kept current in ``targets`` and their counts in ``uses``. A pair can only act when the agent's requested
        cell is another agent's cell or request, so an agent whose requested cell nobody else stands on or asks for
        is skipped, and the others scan every other agent in id order exactly like the original's double loop."""
        N = self.num_agents
        req, types, path, fixing = self.req, self.types, self.path, self.fixing
        highway = self._highway
        agv_layer, picker_layer = self.agv_layer, self.picker_layer
        xy = self._cell_xy
        clashes = 0
        for i in range(N):
            if not path[i]:
                continue
            me = starts[i]
            a_loc = targets[i]
            if uses[a_loc] - (2 if a_loc == me else 1) <= 0:
                continue
            ti = types[i]
            for j in range(N):
                if j == i:
                    continue
                o_loc = targets[j]
                o_pos = starts[j]
                if a_loc != o_pos and a_loc != o_loc:
                    continue
                tj = types[j]
                if not highway[a_loc] and (ti == PICKER or tj == PICKER) and ti != tj:
                    if (ti == PICKER and picker_layer[a_loc] in (0, i + 1)) or (
                        ti == AGV and agv_layer[a_loc] in (0, i + 1)
                    ):
                        committed.add(i + 1)
                        continue
                if a_loc == o_pos:
                    req[i] = NOOP
                    if (o_loc == me or o_loc == a_loc) and req[j] not in (TURN_LEFT, TURN_RIGHT):
                        if fixing[j] == 0:
                            clashes += 1
                            fixing[i] = FIXING_CLASH_TIME
                            new_path = self.planner.find_path(xy[me], path[i][-1], ti == PICKER, starts)
                            if new_path:
                                path[i] = new_path
                            else:
                                fixing[i] = 0
                elif a_loc == o_loc and a_loc != me:
                    if fixing[i] == 0 and fixing[j] == 0:
                        req[i] = NOOP
                        fixing[i] = FIXING_CLASH_TIME
                if req[i] == NOOP and a_loc != me:  # the agent now asks for its own cell
                    uses[a_loc] -= 1
                    uses[me] += 1
                    targets[i] = a_loc = me
        return clashes

    def _resolve_stuck(self) -> int:
        """Phase 3: re-plan or release agents that have not left their cell for too long."""
        goals = self._goal_cells
        req, busy, path = self.req, self.busy, self.path
        stuck_cell, stuck_count = self.stuck_cell, self.stuck_count
        # agents stand where the layers were last written until phase 5 moves them
        cells = self._layer_cells
        stucks = 0
        limit = self._unstick_limit
        # each agent's turn reads and writes only its own state, so the filter of moving agents is applied in turn
        for i in range(self.num_agents):
            if not busy[i]:
                continue
            r = req[i]
            if r == TURN_LEFT or r == TURN_RIGHT:
                continue
            c = cells[i]
            if r == TOGGLE and c not in goals:
                continue
            if c == stuck_cell[i]:
                stuck_count[i] += 1
            else:
                stuck_count[i] = 0
                stuck_cell[i] = c
            count = stuck_count[i]
            if STUCK_THRESHOLD < count < limit:
                req[i] = NOOP
                if path[i]:
                    new_path = self.planner.find_path(self._cell_xy[c], path[i][-1], self.types[i] == PICKER, cells)
                    if new_path:
                        path[i] = new_path
                        if len(new_path) == 1:  # keeps counting: a picker waiting next to its AGV
                            continue
                        self._reset_stuck(i)
                        continue
                else:
                    stucks += 1
                    busy[i] = False
                    stuck_count[i] = 0
            if stuck_count[i] > limit:  # count == limit does nothing: the original's gap
                stucks += 1
                self._reset_stuck(i)
                req[i] = NOOP
                busy[i] = False
        return stucks

    def _execute(self, rewards: list[float]) -> tuple[int, int]:
        """Phase 5: moves, turns, loads and unloads in id order, on start-of-step agent layers. The agents' cells
        after the moves are left in ``self._moved_cells`` for phase 7."""
        loads = unloads = 0
        req, xs, ys, dirs, path, carrying = self.req, self.x, self.y, self.dir, self.path, self.carrying
        cells = self._layer_cells  # each agent's cell until it moves, and it moves at most once
        moved = cells[:]
        ahead, xy = self._ahead, self._cell_xy
        for i in range(self.num_agents):
            r = req[i]
            if r == NOOP:
                continue
            if r == FORWARD:
                c = ahead[cells[i]][dirs[i]]
                moved[i] = c
                xs[i], ys[i] = x, y = xy[c]
                del path[i][0]
                sid = carrying[i]
                if sid:
                    self.shelf_x[sid - 1], self.shelf_y[sid - 1] = x, y
            elif r == TURN_LEFT or r == TURN_RIGHT:
                dirs[i] = _TURNED[r][dirs[i]]
            elif r == TOGGLE:
                c = cells[i]
                t = self.types[i]
                if not carrying[i]:
                    sid = self.shelf_layer[c]
                    pid = self.picker_layer[c]
                    if sid:
                        if (t == AGV and pid) or t == AGENT:
                            carrying[i] = sid
                            self.shelf_layer[c] = 0
                            self.carried_layer[c] = sid
                            self.busy[i] = False
                            loads += 1
                            self._pay_handling(rewards, i, pid)
                    else:
                        self.busy[i] = False
                else:
                    if c in self._goal_cells or self.shelf_layer[c] != 0:
                        self.busy[i] = False
                        continue
                    pid = self.picker_layer[c]
                    if not self._highway[c] and ((t == AGV and pid) or t == AGENT):
                        self.shelf_layer[c] = carrying[i]
                        self.carried_layer[c] = 0
                        carrying[i] = 0
                        self.busy[i] = False
                        self.has_delivered[i] = False
                        unloads += 1
                        self._pay_handling(rewards, i, pid)
        self._moved_cells = moved
        return loads, unloads

    def _pay_handling(self, rewards: list[float], i: int, picker_id: int) -> None:
        if self._global_reward:
            for k in range(len(rewards)):
                rewards[k] += 0.5
        elif self.types[i] == AGENT:
            rewards[i] += 0.1
        else:
            rewards[picker_id - 1] += 0.1

    def _deliver(self, rewards: list[float]) -> tuple[int, list[int]]:
        """Phase 6: requested shelves on goal cells at the start of the step are delivered."""
        deliveries = 0
        delivered_by: list[int] = []
        queue = self.queue
        carried_layer = self.carried_layer
        for c in self._goal_idx:
            sid = carried_layer[c]
            if not sid or sid not in queue:
                continue
            excluded = set(queue)
            excluded.update(s for s in self.carrying if s)
            if self.demand_side is None:
                # the draw's pick among the free shelves in id order, found without listing them: step the drawn
                # rank over every excluded id at or below it
                shelf = int(self._rng.randint(0, self.layout.num_shelves - len(excluded))) + 1  # type: ignore[union-attr]
                for s in sorted(excluded):
                    if s > shelf:
                        break
                    shelf += 1
                new = shelf
            else:
                candidates = list(filterfalse(excluded.__contains__, range(1, self.layout.num_shelves + 1)))
                # Same single draw per counted delivery, over the active half only; if that half has no free
                # shelf left (never at the named sizes) the draw falls back to every free shelf.
                active = [s for s in candidates if self.on_side(s, self.demand_side)]
                candidates = active or candidates
                new = candidates[int(self._rng.randint(0, len(candidates)))]  # type: ignore[union-attr]
            queue[queue.index(sid)] = new
            aid = self.agv_layer[c]
            i = aid - 1
            if not self.has_delivered[i]:
                self.has_delivered[i] = True
                if self._global_reward:
                    for k in range(len(rewards)):
                        rewards[k] += 1
                else:
                    rewards[i] += 1
            deliveries += 1
            delivered_by.append(aid)
        if deliveries:
            self.inactive_steps = 0
        else:
            self.inactive_steps += 1
        return deliveries, delivered_by

    def _recalc_layers(self) -> None:
        """Phase 7: move the agent and carried-shelf layers to the new positions (floor shelves were updated
        in place by loads and unloads, exactly as the original's full rebuild would leave them)."""
        agv_layer, picker_layer, carried_layer = self.agv_layer, self.picker_layer, self.carried_layer
        for c in self._layer_cells:
            agv_layer[c] = picker_layer[c] = carried_layer[c] = 0
        self._write_agent_layers(self._moved_cells)

    # ------------------------------------------------------------------ read access
    @property
    def goals(self) -> list[tuple[int, int]]:
        return self.layout.goals

    def positions(self) -> np.ndarray:
        """(N, 2) int array of (x, y)."""
        return np.array([self.x, self.y], dtype=np.int64).T

    @property
    def is_agv(self) -> np.ndarray:
        return np.array([t != PICKER for t in self.types], dtype=bool)

    @property
    def carried_shelf(self) -> np.ndarray:
        return np.array(self.carrying, dtype=np.int64)

    @property
    def busy_mask(self) -> np.ndarray:
        return np.array(self.busy, dtype=bool)

    @property
    def targets(self) -> np.ndarray:
        return np.array(self.target, dtype=np.int64)

    @property
    def req_actions(self) -> np.ndarray:
        return np.array([NOOP if r is None else r for r in self.req], dtype=np.int64)

    @property
    def request_queue(self) -> np.ndarray:
        return np.array(self.queue, dtype=np.int64)

    @property
    def shelf_positions(self) -> np.ndarray:
        """(S, 2) int array: current (x, y) of shelf id k at row k - 1 (carried shelves ride on their AGV)."""
        return np.array([self.shelf_x, self.shelf_y], dtype=np.int64).T

    def shelf_cell(self, shelf_id: int) -> tuple[int, int]:
        return self.shelf_x[shelf_id - 1], self.shelf_y[shelf_id - 1]

    def is_requested_mask(self) -> np.ndarray:
        """S-long bool array, True for requested shelf ids (index id - 1)."""
        mask = np.zeros(self.layout.num_shelves, dtype=bool)
        mask[np.array(self.queue) - 1] = True
        return mask

    def empty_rack_actions(self) -> list[int]:
        """Rack action ids whose cell counts as empty: no floor shelf, and no carried shelf unless its AGV is
        moving or turning (the original's ``get_empty_shelf_information``), in action id order."""
        shelf_layer, carried_layer, agv_layer, req = self.shelf_layer, self.carried_layer, self.agv_layer, self.req
        return [a for a, c in self._rack_action_cells
                if not shelf_layer[c] and (carried_layer[c] == 0 or req[agv_layer[c] - 1] not in (NOOP, TOGGLE))]

    def action_to_cell(self, action: int) -> tuple[int, int]:
        return self.layout.action_to_cell(action)

    def cell_to_action(self, cell: tuple[int, int]) -> int:
        return self.layout.cell_to_action_id(cell)

    @staticmethod
    def manhattan(a: tuple[int, int], b: tuple[int, int]) -> int:
        return abs(a[0] - b[0]) + abs(a[1] - b[1])

    def frame(self, step: int | None = None, caption: str | None = None, links=()):
        """The current state as a renderer :class:`~services.world.render.Frame` (plain arrays)."""
        from services.world.render import Frame

        H, W, lay = self.H, self.W, self.layout
        floor = np.array(self.shelf_layer, dtype=np.int64).reshape(H, W)
        requested = self.is_requested_mask()
        shelves = floor > 0
        req_grid = np.zeros((H, W), dtype=bool)
        req_grid[shelves] = requested[floor[shelves] - 1]
        carrying = np.array(self.carrying, dtype=np.int64)
        target = np.full((self.num_agents, 2), -1, dtype=np.int64)
        for i, a in enumerate(self.target):
            if a:
                target[i] = lay.action_cells[a]
        return Frame(
            height=H, width=W, highway=lay.highway, goals=np.array(lay.goals, dtype=np.int64),
            shelves=shelves, requested=req_grid,
            agent_x=np.array(self.x, dtype=np.int64), agent_y=np.array(self.y, dtype=np.int64),
            agent_dir=np.array(self.dir, dtype=np.int64), is_agv=self.is_agv, carrying=carrying > 0,
            carrying_requested=(carrying > 0) & requested[np.maximum(carrying, 1) - 1],
            target=target, step=self.steps if step is None else step, caption=caption, links=links,
        )

    def digest_key(self) -> list:
        """The list whose repr() the per-step digest hashes (tests/data/tarware_digests.json)."""
        state: list = [
            (self.x[i], self.y[i], self.dir[i], self.carrying[i], int(self.busy[i]), self.req[i])
            for i in range(self.num_agents)
        ]
        state.append(tuple(self.queue))
        return state

    def digest_row(self) -> str:
        """12-hex per-step digest (sha1 of the repr of :meth:`digest_key`)."""
        return hashlib.sha1(repr(self.digest_key()).encode()).hexdigest()[:12]


def episode_digest(step_digests: list[str]) -> str:
    """Episode digest: first 16 hex of sha1 over the concatenated per-step digests."""
    return hashlib.sha1("".join(step_digests).encode()).hexdigest()[:16]
