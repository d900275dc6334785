"""The rotation-aware A* of TA-RWARE's planner fork, re-implemented exactly, and TA-RWARE's path rules.

The search is the fork's (raulsteleac/pyastar2d_TARWARE@ff9257d) greedy
variant, not textbook A*: 4-connected, Manhattan heuristic, neighbours in the order up, left, right, down
(direction codes 1, 3, 4, 6), +1 on a change of direction (never on the first move), and +100 added to a cell's
weight once it is pushed, so a cell is in effect settled when first reached. The open list is a binary heap ordered
only by priority, and ties are decided by how libstdc++'s ``std::priority_queue`` moves entries: :func:`astar`
writes libstdc++'s ``push_heap``/``pop_heap`` out step by step. Python's ``heapq`` moves entries the same way (a pop
moves the last entry to the top, takes the hole down to a leaf through the right child unless the left one is
strictly smaller, then moves the entry up while it is strictly smaller than its parent; a push moves the new entry
up the same way) but compares whole entries, so ties between tuples would go by their later fields: the unit search
gives it entries that compare by priority alone (:class:`_Entry`).
All costs are small integers, exact in both float32 (the fork) and float64 (here).
"""

from __future__ import annotations

from collections.abc import Iterable
from heapq import heappop, heappush

from services.world.layout import Layout

INF = float("inf")
# Static plans (no other agents as obstacles) depend only on the layout, so planners of one layout share them.
# Paths are tuples of shared cell tuples (about 8 bytes per cell); the cache is emptied when it reaches this size.
MAX_CACHED_PLANS = 200_000
_STATIC_PLANS: dict[object, dict[tuple[int, int, bool], tuple[tuple[int, int], ...]]] = {}
# An AGV's static plan on the all-free grid, by the goal's offset from the start (see Planner._shifted_plan).
_SHIFTED_PLANS: dict[object, dict[tuple[int, int], list[tuple[int, int, tuple[int, int, int, int],
                                                              tuple[tuple[int, int], ...]]]]] = {}
SHIFTED_PLANS_PER_OFFSET = 4
# The read-only tables of a layout (neighbours, highway, the AGVs' and the pickers' base weights, flat index -> cell),
# shared by its planners: a warehouse per episode would otherwise rebuild them every episode.
_LAYOUT_TABLES: dict[object, tuple] = {}
# Direction codes of the fork's 8-neighbour table that a 4-connected search uses.
_UP, _LEFT, _RIGHT, _DOWN = 1, 3, 4, 6


def neighbour_table(H: int, W: int) -> list[tuple[tuple[int, int, int, int], ...]]:
    """For each flat cell, its in-grid neighbours as (direction code, flat index, row, col), in the fork's order."""
    table = []
    for idx in range(H * W):
        row, col = divmod(idx, W)
        nbrs = []
        if row > 0:
            nbrs.append((_UP, idx - W, row - 1, col))
        if col > 0:
            nbrs.append((_LEFT, idx - 1, row, col - 1))
        if col + 1 < W:
            nbrs.append((_RIGHT, idx + 1, row, col + 1))
        if row + 1 < H:
            nbrs.append((_DOWN, idx + W, row + 1, col))
        table.append(tuple(nbrs))
    return table


def astar(weights: list[float], H: int, W: int, start: int, goal: int,
          nbr_table: list[tuple[tuple[int, int, int, int], ...]] | None = None) -> list[int] | None:
    """The fork's search on flat ``weights`` (>= 1, ``inf`` = obstacle). ``weights`` is modified (pass a copy).

    Returns the flat cells from start to goal, start included, or None when the goal is unreachable.
    """
    if nbr_table is None:
        nbr_table = neighbour_table(H, W)
    n = H * W
    costs = [INF] * n
    costs[start] = 0.0
    parents = [-1] * n
    g_row, g_col = divmod(goal, W)
    # Heap entries: (priority, cell, direction entered from, path length). Only priority is ever compared.
    heap: list[tuple[float, int, int, int]] = [(0.0, start, -1, 1)]
    path_length = -1
    while heap:
        top = heap[0]
        cur = top[1]
        if cur == goal:  # the fork tests the top before popping
            path_length = top[3]
            break
        # --- pop: libstdc++ pop_heap (move last into the hole left by the top, sift down, then up) ---
        last = heap.pop()
        size = len(heap)
        if size:
            value = last
            hole = 0
            child = 0
            half = (size - 1) // 2
            while child < half:
                child = 2 * (child + 1)
                if heap[child][0] > heap[child - 1][0]:
                    child -= 1
                heap[hole] = heap[child]
                hole = child
            if (size & 1) == 0 and child == (size - 2) // 2:
                child = 2 * (child + 1)
                heap[hole] = heap[child - 1]
                hole = child - 1
            vf = value[0]
            while hole > 0:
                parent = (hole - 1) // 2
                if heap[parent][0] > vf:
                    heap[hole] = heap[parent]
                    hole = parent
                else:
                    break
            heap[hole] = value
        # --- expand ---
        prev_dir = top[2]
        base = costs[cur]
        plen = top[3] + 1
        for code, nb, r, c in nbr_table[cur]:
            w = weights[nb]
            if w == INF:  # an obstacle can never be relaxed (inf < inf is false in the fork too)
                continue
            new_cost = base + w
            if prev_dir > 0 and prev_dir != code and w < 100.0:
                new_cost += 1.0
            if new_cost < costs[nb]:
                entry = (new_cost + (abs(r - g_row) + abs(c - g_col)), nb, code, plen)
                # --- push: libstdc++ push_heap (sift up while the parent is strictly greater) ---
                heap.append(entry)
                hole = len(heap) - 1
                ef = entry[0]
                while hole > 0:
                    parent = (hole - 1) // 2
                    if heap[parent][0] > ef:
                        heap[hole] = heap[parent]
                        hole = parent
                    else:
                        break
                heap[hole] = entry
                costs[nb] = new_cost
                parents[nb] = cur
                weights[nb] = w + 100.0
    if path_length < 0:
        return None
    path = [0] * path_length
    idx = goal
    for i in range(path_length - 1, -1, -1):
        path[i] = idx
        idx = parents[idx]
    return path


# The largest H + W on which :func:`astar_unit` equals :func:`astar` (see there); larger grids use astar().
UNIT_SEARCH_MAX_H_PLUS_W = 101


def astar_unit(weights: list[float], H: int, W: int, start: int, goal: int,
               nbr_table: list[tuple[tuple[int, int, int, int], ...]],
               expanded: list[int] | None = None) -> list[int] | None:
    """:func:`astar`'s answer for weights that are all 1 or ``inf`` (the planner's), on grids with H + W <= 101.

    There a cell is pushed once. A second push of cell n from an expanded cell x needs cost(x) + w(n) < cost(n)
    with w(n) >= 101 after the first push. n was pushed from a cell p expanded before x, so cost(n) <= cost(p) + 2;
    priorities leave the heap in non-decreasing order (the Manhattan heuristic drops by at most the step cost), so
    cost(p) + h(p) <= cost(x) + h(x), and cost(n) <= cost(x) + h(x) + 2 <= cost(x) + H + W <= cost(x) + 101. With
    one push per cell a cell's cost is the one its heap entry carries and its parent the cell that pushed it, so
    this search keeps no cost array, skips obstacles and reached cells in one comparison and follows the parent
    chain for the path; the heap, its ties and so the answer are astar()'s.

    It also stops as soon as the goal is pushed, where astar() goes on until the goal reaches the top of the heap.
    The answer is already fixed then: the goal's entry stays in the heap until it is popped, so the search can only
    end by reaching it (never with "unreachable"), and the path is the goal's parent chain, whose cells were all
    pushed before the goal and, pushed once, never get another parent. What astar() does between the goal's push
    and its pop touches other cells only.
    ``expanded``: if given, the cells whose neighbours the search read are appended to it, in order (the last one
    is the cell that reached the goal; its neighbours after the goal were not read).
    """
    closed = [1 if w >= 100.0 else 0 for w in weights]
    return unit_search(closed, 1, [-1] * (H * W), start, goal, W, nbr_table, expanded)


# Larger than any stamp: the mark of the cells a kind of agent may never enter (see Planner).
WALL = (1 << 30) - 1  # the largest int CPython keeps in one digit, so comparisons with it stay on the fast path


class _Entry(float):
    """An open-list entry of the unit search: its value is the priority, the only thing ``heapq`` compares (floats
    compare by value alone), and it carries the cell it reaches. A cell is pushed once, so the direction it was
    entered from and its cost are kept by cell, beside its parent."""

    __slots__ = ("cell",)


def unit_search(closed: list[int], stamp: int, parents: list[int], start: int, goal: int, W: int,
                nbr_table: list[tuple[tuple[int, int, int, int], ...]],
                expanded: list[int] | None = None, dirs: list[int] | None = None,
                costs: list[int] | None = None) -> list[int] | None:
    """:func:`astar_unit`'s search on reusable lists: a cell is closed (an obstacle, or reached by this search) when
    ``closed[c] >= stamp``, and the search marks the cells it reaches with ``stamp``, so a caller that raises the
    stamp for each search needs no fresh weights. ``parents``, ``dirs`` and ``costs`` are any lists of H * W ints
    (fresh ones when not given): the search writes a cell's entries when it reaches the cell, before anything reads
    them, so stale entries are never read.

    The open list is ``heapq``'s, on :class:`_Entry` priorities: the same moves as libstdc++'s heap (module
    docstring), so the same cell comes to the top at every step.
    """
    if start == goal:  # the goal is the first top
        return [start]
    if dirs is None or costs is None:
        dirs, costs = [0] * len(parents), [0] * len(parents)
    closed[start] = stamp  # reached
    g_row, g_col = divmod(goal, W)
    heap: list[_Entry] = []
    cur, prev_dir, base = start, -1, 0  # the start: entered from nowhere, so no move from it pays for a turn
    while True:
        if expanded is not None:
            expanded.append(cur)
        # --- expand: cells not reached yet, at cost + 1, + 1 more on a change of direction ---
        for code, nb, row, col in nbr_table[cur]:
            if closed[nb] >= stamp:  # an obstacle or a reached cell
                continue
            if nb == goal:  # the answer is fixed (see astar_unit)
                path = [goal, cur]
                while cur != start:
                    cur = parents[cur]
                    path.append(cur)
                path.reverse()
                return path
            cost = base + 1 if (code == prev_dir or prev_dir < 0) else base + 2
            entry = _Entry(cost + (abs(row - g_row) + abs(col - g_col)))
            entry.cell = nb
            heappush(heap, entry)
            parents[nb] = cur
            dirs[nb] = code
            costs[nb] = cost
            closed[nb] = stamp
        if not heap:
            return None
        cur = heappop(heap).cell
        prev_dir = dirs[cur]
        base = costs[cur]


class Planner:
    """TA-RWARE's ``find_path`` cost-grid rules on top of :func:`astar` (the original's ``find_path``).

    AGVs plan on an all-free grid; pickers only on highways outside the goal row, plus their target rack cell, and
    a picker on a rack cell whose target is the other half of the same 2-wide rack must leave through the highway.
    Plans that ignore other agents depend only on (start, goal, agent kind), so they are cached; plans around
    other agents always run the exact search. ``cells`` maps a flat index to its cell (x, y) (shared, read-only).
    """

    def __init__(self, layout: Layout):
        self.layout = layout
        H, W = layout.H, layout.W
        self.H, self.W = H, W
        tables = _LAYOUT_TABLES.get(layout.config)
        if tables is None:
            highway = layout.highway.reshape(-1).tolist()
            picker = [1.0 if hw else INF for hw in highway]
            for x in range(W):
                picker[(H - 1) * W + x] = INF
            cells = [(c % W, c // W) for c in range(H * W)]
            tables = _LAYOUT_TABLES[layout.config] = (neighbour_table(H, W), highway, [1.0] * (H * W), picker, cells)
        self._nbrs, self._highway, self._agv_base, self._picker_base, self.cells = tables
        self._cache = _STATIC_PLANS.setdefault(layout.config, {})
        self._shifted = _SHIFTED_PLANS.setdefault(layout.config, {})
        # the planner's weights are all 1 or inf: the unit search gives astar()'s answers where it is exact
        self._unit = H + W <= UNIT_SEARCH_MAX_H_PLUS_W
        self._search = astar_unit if self._unit else astar
        # The unit search's closed marks, one list per kind of agent, reused from search to search: cells a kind
        # may never enter hold WALL, every other cell the stamp of the last search that reached or blocked it.
        self._picker_walls = [w == INF for w in self._picker_base]
        self._stamp = 0
        self._closed = {False: [0] * (H * W), True: [WALL if wall else 0 for wall in self._picker_walls]}
        self._parents = [-1] * (H * W)
        self._dirs = [0] * (H * W)
        self._costs = [0] * (H * W)
        self.searches = 0  # exact searches run (cache misses included)

    def find_path(self, start: tuple[int, int], goal: tuple[int, int], picker: bool,
                  occupied: Iterable[int] | None = None) -> list[tuple[int, int]]:
        """Cells (x, y) from the cell after ``start`` to ``goal``; [] when there is no path or start == goal.

        ``occupied``: flat indices of cells holding agents (the original's ``care_for_agents=True``), or None.
        """
        W = self.W
        s = start[1] * W + start[0]
        g = goal[1] * W + goal[0]
        if occupied is None:
            key = (s, g, picker)
            hit = self._cache.get(key)
            if hit is None:
                hit = self._shifted_plan(s, g) if not picker and self._search is astar_unit else None
                if hit is None:
                    hit = tuple(self._plan(s, g, picker, None))
                if len(self._cache) >= MAX_CACHED_PLANS:
                    self._cache.clear()
                    self._shifted.clear()
                self._cache[key] = hit
            return list(hit)
        return self._plan(s, g, picker, occupied)

    def _shifted_plan(self, s: int, g: int) -> tuple[tuple[int, int], ...]:
        """An AGV's static plan from flat cell ``s`` to ``g``, reused from a plan with the same offset where exact.

        On the all-free grid every weight is 1, so the search depends on the cells only through which neighbours
        its expanded cells have: shifted by (dx, dy), a search expands the shifted cells, in the same order, as long
        as every expanded cell keeps the same neighbours, and answers the shifted path. That holds when on each
        side of the grid the expanded cells either stay off the border in both places or do not move across it
        (dx = 0 for the left and right borders, dy = 0 for the top and bottom ones); their bounding box tells.
        """
        W, H = self.W, self.H
        sy, sx = divmod(s, W)
        gy, gx = divmod(g, W)
        plans = self._shifted.setdefault((gx - sx, gy - sy), [])
        for x0, y0, (left, right, top, bottom), path in plans:
            dx, dy = sx - x0, sy - y0
            if ((dx == 0 or (left > 0 and left + dx > 0 and right < W - 1 and right + dx < W - 1))
                    and (dy == 0 or (top > 0 and top + dy > 0 and bottom < H - 1 and bottom + dy < H - 1))):
                return tuple([(x + dx, y + dy) for x, y in path])
        expanded: list[int] = []
        path = tuple(self._plan(s, g, False, None, expanded))
        if expanded and len(plans) < SHIFTED_PLANS_PER_OFFSET:
            cols = [c % W for c in expanded]
            rows = [c // W for c in expanded]
            plans.append((sx, sy, (min(cols), max(cols), min(rows), max(rows)), path))
        return path

    def _plan(self, s: int, g: int, picker: bool, occupied: Iterable[int] | None,
              expanded: list[int] | None = None) -> list[tuple[int, int]]:
        W = self.W
        s_eff = s
        hw = self._highway
        if picker and not hw[s] and g // W == s // W and abs(g - s) == 1:
            if hw[s - 1]:
                s_eff = s - 1
            if hw[s + 1]:
                s_eff = s + 1
        self.searches += 1
        if self._unit:
            raw = self._unit_plan(s, s_eff, g, picker, occupied, expanded)
        else:
            raw = self._weights_plan(s, s_eff, g, picker, occupied)
        if raw is None:
            return []
        if s_eff == s:  # the original keeps a shifted start as the first path cell
            raw = raw[1:]
        cells = self.cells
        return [cells[c] for c in raw]

    def _unit_plan(self, s: int, s_eff: int, g: int, picker: bool, occupied: Iterable[int] | None,
                   expanded: list[int] | None) -> list[int] | None:
        """The search on the kind's closed list: the same cells are closed as in the weights
        :meth:`_weights_plan` builds (a cell is closed where its weight is inf), and WALL cells opened for this
        search (the start and a picker's rack goal) are walled again afterwards."""
        stamp = self._stamp + 1
        if stamp >= WALL:  # start the stamps afresh (after about a billion searches)
            self._closed = {False: [0] * len(self._picker_walls),
                            True: [WALL if wall else 0 for wall in self._picker_walls]}
            stamp = 1
        self._stamp = stamp
        closed = self._closed[picker]
        if occupied is not None:
            for c in occupied:
                if closed[c] < stamp:
                    closed[c] = stamp
        if not picker or g < (self.H - 1) * self.W:  # a picker's goal in the goal row stays walled
            closed[g] = 0
        if s_eff != s and closed[s] < stamp:
            closed[s] = stamp
        raw = unit_search(closed, stamp, self._parents, s_eff, g, self.W, self._nbrs, expanded, self._dirs,
                          self._costs)
        if picker:
            walls = self._picker_walls
            if walls[g]:
                closed[g] = WALL
            if walls[s_eff]:
                closed[s_eff] = WALL
        return raw

    def _weights_plan(self, s: int, s_eff: int, g: int, picker: bool,
                      occupied: Iterable[int] | None) -> list[int] | None:
        """The search on a weights grid built afresh (grids too wide for the unit search)."""
        W = self.W
        weights = list(self._picker_base if picker else self._agv_base)
        if occupied is not None:
            for c in occupied:
                weights[c] = INF
        if picker:
            # the goal is free unless it lies in the goal row, which is closed to pickers
            weights[g] = INF if g >= (self.H - 1) * W else 1.0
        else:
            weights[g] = 1.0
        if s_eff != s:
            weights[s] = INF
        weights[s_eff] = 1.0
        return astar(weights, self.H, W, s_eff, g, self._nbrs)
