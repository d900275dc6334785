"""Stage A of TA-RWARE's move-conflict resolution: the move graph.

The original builds a networkx 3.2.1 ``DiGraph`` with one edge (cell -> requested cell) per agent, in agent id
order, and for every weakly connected component commits either the agents on the component's cycle (nobody for a
head-on 2-cycle) or the agents on ``dag_longest_path``. When two chains are equally long, the winner depends on
the order networkx iterates the component's nodes, which for small components is the iteration order of a Python
``set`` of ``(x, y)`` tuples. This module reproduces that order without networkx:

* :func:`networkx_commit_cells` emulates the library calls literally (component BFS, subgraph node order, copy,
  ``find_cycle``, ``topological_generations``, ``dag_longest_path``) on plain dicts, building the same two small
  Python sets the library builds so their iteration order is the library's.
* :func:`commit_cells` is the fast path: most components are a single agent or a chain, where the answer does not
  depend on any order. It only falls back to the order-exact emulation where a tie or a cell with two outgoing moves
  (an AGV and a picker sharing a rack cell) makes order matter.
* :func:`commit_flat` is the same on flat cell indices for the simulator, which settles the lone agents itself and
  passes the other moves with the whole graph's node count.

All three return the cells whose occupant is committed; the caller looks up the AGV on the cell first, then the
picker.
"""

from __future__ import annotations

Cell = tuple[int, int]


class MoveGraph:
    """The DiGraph's insertion-ordered adjacency, as networkx stores it (dicts keep insertion order)."""

    __slots__ = ("succ", "pred", "size")

    def __init__(self, starts: list[Cell], targets: list[Cell], size: int | None = None):
        succ: dict[Cell, dict[Cell, None]] = {}
        pred: dict[Cell, dict[Cell, None]] = {}
        for u, v in zip(starts, targets):
            if u not in succ:
                succ[u] = {}
                pred[u] = {}
            if v not in succ:
                succ[v] = {}
                pred[v] = {}
            succ[u][v] = None
            pred[v][u] = None
        self.succ = succ
        self.pred = pred
        #: node count of the whole graph, of which these moves may be some whole components
        self.size = len(succ) if size is None else size

    def components(self, skip: set[Cell] | frozenset = frozenset()):
        """Weakly connected components as BFS-ordered lists (networkx's ``_plain_bfs``: successors, then
        predecessors), in the order networkx yields them; components holding a node of ``skip`` are left out
        (``skip`` must consist of whole components)."""
        succ, pred = self.succ, self.pred
        seen: set[Cell] = set(skip)
        for v in succ:
            if v in seen:
                continue
            order = [v]
            local = {v}
            level = [v]
            while level:
                nxt = []
                for u in level:
                    for w in succ[u]:
                        if w not in local:
                            local.add(w)
                            nxt.append(w)
                            order.append(w)
                    for w in pred[u]:
                        if w not in local:
                            local.add(w)
                            nxt.append(w)
                            order.append(w)
                level = nxt
            seen.update(local)
            yield order

    def subgraph_order(self, bfs_order: list[Cell]) -> list[Cell]:
        """Node order of ``G.subgraph(c).copy()`` for the component whose BFS order is given.

        networkx builds ``c = set(bfs)``, then the view's filter set ``set(iter(c))``, and iterates that filter set
        when it is less than half the graph, else the graph's insertion order. Both sets are built exactly the way
        the library builds them (element by element from an iterator), so CPython lays them out identically.
        The graph's insertion order restricted to one component does not depend on the other components.
        """
        c = set(iter(bfs_order))
        nodes = set(iter(list(c)))
        if 2 * len(nodes) < self.size:
            return list(nodes)
        return [v for v in self.succ if v in nodes]


def _copy(graph: MoveGraph, order: list[Cell]):
    """Adjacency of the component copy: nodes in ``order``; edges added per node in ``order``, successors in the
    parent's order, so each predecessor list follows ``order``."""
    hsucc: dict[Cell, list[Cell]] = {u: [] for u in order}
    hpred: dict[Cell, list[Cell]] = {u: [] for u in order}
    for u in order:
        for v in graph.succ[u]:
            hsucc[u].append(v)
            hpred[v].append(u)
    return hsucc, hpred


def _find_cycle(hsucc: dict[Cell, list[Cell]]) -> list[tuple[Cell, Cell]] | None:
    """networkx ``find_cycle(G)`` (orientation None) over the copy: edge DFS from each node in order."""
    explored: set[Cell] = set()
    for start in hsucc:
        if start in explored:
            continue
        edges: list[tuple[Cell, Cell]] = []
        seen = {start}
        active = {start}
        previous_head = None
        cycle = None
        for tail, head in _edge_dfs(hsucc, start):
            if head in explored:
                continue
            if previous_head is not None and tail != previous_head:
                while True:
                    try:
                        popped = edges.pop()
                    except IndexError:
                        edges = []
                        active = {tail}
                        break
                    else:
                        active.remove(popped[1])
                    if edges and tail == edges[-1][1]:
                        break
            edges.append((tail, head))
            if head in active:
                cycle = edges
                final = head
                break
            seen.add(head)
            active.add(head)
            previous_head = head
        if cycle:
            for i, (tail, _head) in enumerate(cycle):  # noqa: B007 (i is the cycle's start, used below)
                if tail == final:
                    break
            return cycle[i:]
        explored.update(seen)
    return None


def _edge_dfs(hsucc: dict[Cell, list[Cell]], source: Cell):
    visited_edges: set[tuple[Cell, Cell]] = set()
    visited_nodes: set[Cell] = set()
    iters: dict[Cell, object] = {}
    stack = [source]
    while stack:
        cur = stack[-1]
        if cur not in visited_nodes:
            iters[cur] = iter([(cur, v) for v in hsucc[cur]])
            visited_nodes.add(cur)
        try:
            edge = next(iters[cur])  # type: ignore[call-overload]
        except StopIteration:
            stack.pop()
        else:
            if edge not in visited_edges:
                visited_edges.add(edge)
                stack.append(edge[1])
                yield edge


def _dag_longest_path(hsucc: dict[Cell, list[Cell]], hpred: dict[Cell, list[Cell]]) -> list[Cell]:
    """networkx ``dag_longest_path`` with the default topological order (``topological_generations``)."""
    indegree = {v: len(p) for v, p in hpred.items() if len(p) > 0}
    zero = [v for v, p in hpred.items() if len(p) == 0]
    topo: list[Cell] = []
    while zero:
        generation = zero
        zero = []
        for node in generation:
            for child in hsucc[node]:
                indegree[child] -= 1
                if indegree[child] == 0:
                    zero.append(child)
                    del indegree[child]
        topo.extend(generation)
    dist: dict[Cell, tuple[int, Cell]] = {}
    for v in topo:
        best = None
        for u in hpred[v]:
            cand = dist[u][0] + 1
            if best is None or cand > best[0]:  # max() keeps the first maximum
                best = (cand, u)
        dist[v] = best if best is not None and best[0] >= 0 else (0, v)
    v = None
    best_len = None
    for node, (length, _u) in dist.items():
        if best_len is None or length > best_len:
            best_len, v = length, node
    path = []
    u = None
    while u != v:
        path.append(v)
        u = v
        v = dist[v][1]
    path.reverse()
    return path


def _emulate_component(graph: MoveGraph, bfs_order: list[Cell]) -> list[Cell]:
    hsucc, hpred = _copy(graph, graph.subgraph_order(bfs_order))
    cycle = _find_cycle(hsucc)
    if cycle is not None:
        if len(cycle) == 2:  # head-on swap: nobody in this component moves
            return []
        return [edge[0] for edge in cycle]
    return _dag_longest_path(hsucc, hpred)


def networkx_commit_cells(starts: list[Cell], targets: list[Cell]) -> list[Cell]:
    """Order-exact emulation of the original's Stage A for every component (reference implementation)."""
    graph = MoveGraph(starts, targets)
    out: list[Cell] = []
    for comp in graph.components():
        out.extend(_emulate_component(graph, comp))
    return out


def commit_cells(starts: list[Cell], targets: list[Cell]) -> list[Cell]:
    """Same result as :func:`networkx_commit_cells`, computing order-free cases directly."""
    # An agent whose cell and requested cell touch no other move is a component on its own: a self-loop (1-cycle)
    # or one edge into a free cell (longest path = that edge). Either way it is committed; no order is involved.
    touch: dict[Cell, int] = {}
    edges = dict.fromkeys(zip(starts, targets))  # networkx merges duplicate edges
    for u, v in edges:
        touch[u] = touch.get(u, 0) + 1
        if v != u:
            touch[v] = touch.get(v, 0) + 1
    out: list[Cell] = []
    isolated: set[Cell] = set()
    for u, v in edges:
        if touch[u] == 1 and touch[v] == 1:
            out.append(u)
            if v != u:
                out.append(v)
            isolated.add(u)
            isolated.add(v)
    if len(isolated) == len(touch):
        return out
    graph = MoveGraph(starts, targets)
    for comp in graph.components(isolated):
        out.extend(_commit_component(graph, comp, None))
    return out


def commit_flat(starts: list[int], targets: list[int], nodes: int, cell_of: list[Cell]) -> list[int]:
    """:func:`commit_cells` on flat cell indices (``cell_of[i]`` is index i's (x, y)): the same cells, as indices.

    The caller passes only moves that touch another move's cell (no component of a single agent on its own) and
    ``nodes``, the whole move graph's number of distinct cells. Integer cells are cheaper to hash and compare; a
    component whose answer depends on networkx's node order is rebuilt on (x, y) cells, as the library sees them.
    """
    graph = MoveGraph(starts, targets, nodes)
    out: list[int] = []

    def on_cells(comp: list[int]):
        members = set(comp)
        moves = [(cell_of[u], cell_of[v]) for u, v in zip(starts, targets) if u in members]
        # the component's moves in their order give its nodes and adjacency in the whole graph's order
        sub = MoveGraph([m[0] for m in moves], [m[1] for m in moves], nodes)
        return sub, [cell_of[c] for c in comp], {cell_of[c]: c for c in comp}

    for comp in graph.components():
        out.extend(_commit_component(graph, comp, on_cells))
    return out


def merge_winner(first: Cell, second: Cell, sink: Cell, size: int) -> Cell:
    """The start cell networkx commits when two moves, ``first`` -> ``sink`` then ``second`` -> ``sink``, make a
    component on their own in a move graph of ``size`` cells.

    Both chains are one move long, so the tie goes to the start cell that comes first in the component copy's node
    order (see :func:`_commit_component`). The component's BFS order is first, sink, second: the first move's cells
    enter the graph first, and the second start is the sink's second predecessor.
    """
    for cell in MoveGraph([first, second], [sink, sink], size).subgraph_order([first, sink, second]):
        if cell == first or cell == second:
            return cell
    raise AssertionError("unreachable: both start cells are in the component")


def _commit_component(graph: MoveGraph, comp: list, on_cells) -> list:
    """The committed cells of one component (BFS order ``comp``), computing order-free cases directly.

    ``on_cells``: None when the graph's nodes are (x, y) cells; else a function giving, for a component of another
    kind of node, the component as a graph on (x, y) cells, its BFS order there and the map back to its nodes.
    """
    if len(comp) == 1:  # a lone self-loop (waiting or turning agent): a 1-cycle commits it
        return comp
    succ, pred = graph.succ, graph.pred
    functional = True
    sink = None
    for u in comp:
        k = len(succ[u])
        if k > 1:
            functional = False
            break
        if k == 0:
            sink = u
    if not functional:
        if on_cells is None:
            return _emulate_component(graph, comp)
        sub, cells, back = on_cells(comp)
        return [back[c] for c in _emulate_component(sub, cells)]
    if sink is None:
        # every node has one successor: exactly one cycle, found whatever the start
        u = comp[0]
        visited: dict = {}
        walk: list = []
        while u not in visited:
            visited[u] = len(walk)
            walk.append(u)
            u = next(iter(succ[u]))
        cycle = walk[visited[u]:]
        return cycle if len(cycle) != 2 else []
    # an in-tree towards the unique sink: longest path = deepest leaf chain; ties need networkx's order
    depth: dict = {}
    stack = [sink]
    post: list = []
    while stack:
        v = stack.pop()
        post.append(v)
        stack.extend(pred[v])
    for v in reversed(post):
        ps = pred[v]
        depth[v] = 1 + max(depth[p] for p in ps) if ps else 0
    path = [sink]
    v = sink
    rank = None
    while pred[v]:
        best = depth[v] - 1
        cands = [p for p in pred[v] if depth[p] == best]
        if len(cands) > 1:
            if rank is None:
                if on_cells is None:
                    order = graph.subgraph_order(comp)
                else:
                    sub, cells, back = on_cells(comp)
                    order = [back[c] for c in sub.subgraph_order(cells)]
                rank = {n: i for i, n in enumerate(order)}
            cands.sort(key=rank.__getitem__)
        v = cands[0]
        path.append(v)
    return path
