"""Pure metric computations over numpy arrays (no I/O, no bus).

Used by the monitor (live metric streams), the lab (experiment tables) and the reports. Definitions follow
the reference code and the paper's analysis sections (docs/morph.md); where the paper and the reference code disagree, both
variants are offered and named after their source.

Conventions
-----------
* ``A`` is an (N, N) link matrix (nonzero = link), ``W`` an (N, N) preference matrix; the diagonal is ignored.
* ``is_agv`` is an (N,) bool vector: True for AGVs, False for pickers.
* Positions are (T, N, 2) arrays of (x, y) grid cells, one row per tick.
* Delivery series are per-step counts (deliveries completed in that step), shape (T,).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

# scipy is imported where it is used: scipy.linalg alone costs ≈ 0.4 CPU-s to import, as much again as the rest of a
# run's processes' code, and a run's processes never call it (the monitor's λ₂ is numpy's; scipy.stats,
# scipy.sparse.csgraph and the reference's own eigen-solver serve the lab and the reports).

__all__ = [
    "undirected_link_count",
    "directed_link_count",
    "LinkEvent",
    "LinkTracker",
    "BlockMeans",
    "mean_w_by_block",
    "algebraic_connectivity",
    "reference_normalized_fiedler",
    "is_connected",
    "mean_manhattan_distance",
    "SpearmanResult",
    "spearman_agv_picker",
    "spearman_reference_pairs",
    "rolling_sum",
    "rolling_rate",
    "PhaseRecovery",
    "recovery_time",
    "shift_recoveries",
    "phase_deliveries",
    "MeanStd",
    "mean_std",
    "welch_p",
]


# ---------------------------------------------------------------------------------------------------------------------
# Input checks (bad input gets a message naming the argument, never a numpy broadcast error deep inside)


def _square(name: str, m) -> np.ndarray:
    a = np.asarray(m)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f"{name}: expected a square (N, N) matrix, got shape {a.shape}")
    return a


def _agent_mask(name: str, is_agv, n: int) -> np.ndarray:
    m = np.asarray(is_agv, dtype=bool)
    if m.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {m.shape}")
    return m


def _series(name: str, x) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D per-step series, got shape {a.shape}")
    return a


def _offdiag_links(A) -> np.ndarray:
    """Bool link mask with the diagonal cleared (self-links carry no coordination meaning)."""
    L = _square("A", A) != 0
    L = L.copy()
    np.fill_diagonal(L, False)
    return L


# ---------------------------------------------------------------------------------------------------------------------
# Link counts


def undirected_link_count(A) -> int:
    """Number of unordered pairs i<j linked in either direction (A_ij or A_ji nonzero).

    For the reference preset (A kept symmetric) this equals ΣA/2, the reference's "active links".
    """
    L = _offdiag_links(A)
    return int(np.count_nonzero(np.triu(L | L.T, k=1)))


def directed_link_count(A) -> int:
    """Number of nonzero off-diagonal entries (ordered pairs i→j). Twice the undirected count for symmetric A."""
    return int(np.count_nonzero(_offdiag_links(A)))


# ---------------------------------------------------------------------------------------------------------------------
# Link events and lifetimes


@dataclass(frozen=True)
class LinkEvent:
    """One contiguous stretch during which a pair was linked.

    ``formed`` is the first tick at which the link was observed, ``pruned`` the first tick at which it was observed
    gone (None while still open).  ``lifetime = pruned - formed``; an open event is censored at the end of the
    observation, ``end - formed`` with ``end`` = last observed tick + 1 (the reference's ``T - birth``).
    """

    i: int
    j: int
    formed: int
    pruned: int | None

    @property
    def censored(self) -> bool:
        return self.pruned is None

    def lifetime(self, end: int) -> int:
        return (self.pruned if self.pruned is not None else end) - self.formed


class LinkTracker:
    """Records link formations, prunings and lifetimes from a sequence of link matrices, one per tick.

    Exactly the reference's link-persistence analysis (`emergent.py`): A is recorded after each
    update; a 0→1 transition between consecutive observations starts an event, the matching 1→0 ends it; the state
    before the first observation is all-zero; events open at the end are censored at ``T - birth``; the stable core is
    lifetime ≥ ⌊T/2⌋ with T the number of observed ticks.  A link pruned and re-formed inside one tick is never seen
    to drop, so it stays one event (which is why the reference counts fewer events than formations).

    ``directed=False`` (default) tracks unordered pairs i<j linked in either direction; ``directed=True`` tracks
    ordered pairs i→j (the paper preset's per-agent rows).
    """

    def __init__(self, n_agents: int, directed: bool = False):
        if n_agents < 1:
            raise ValueError(f"n_agents: must be ≥ 1, got {n_agents}")
        self.n_agents = int(n_agents)
        self.directed = bool(directed)
        self._prev = np.zeros((n_agents, n_agents), dtype=bool)
        # the pairs tracked: i < j (undirected) or every i != j (directed), one mask for every update
        self._pairs = np.triu(np.ones((n_agents, n_agents), dtype=bool), k=1) if not directed else ~np.eye(
            n_agents, dtype=bool)
        self._prev_key: tuple | None = None  # the last matrix fed (dtype, shape, bytes)
        self._open: dict[tuple[int, int], int] = {}
        self._closed: list[LinkEvent] = []
        self._first_tick: int | None = None
        self._last_tick: int | None = None
        self.formations = 0
        self.prunings = 0

    def _mask(self, A) -> np.ndarray:
        L = _square("A", A) != 0
        if L.shape != (self.n_agents, self.n_agents):
            raise ValueError(f"A: expected shape ({self.n_agents}, {self.n_agents}), got {L.shape}")
        if not self.directed:
            L |= L.T
        L &= self._pairs
        return L

    def update(self, A, tick: int | None = None) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
        """Feed the link matrix observed at ``tick`` (default: previous tick + 1, starting at 0).

        Returns the pairs formed and the pairs pruned since the previous observation.
        """
        if tick is None:
            tick = 0 if self._last_tick is None else self._last_tick + 1
        tick = int(tick)
        if self._last_tick is not None and tick <= self._last_tick:
            raise ValueError(f"tick: must increase, got {tick} after {self._last_tick}")
        # the links stay as they were on most ticks of a converged run: the same matrix forms and prunes nothing
        arr = np.asarray(A)
        key = (arr.dtype.str, arr.shape, arr.tobytes())
        if self._last_tick is not None and key == self._prev_key:
            self._last_tick = tick
            return [], []
        self._prev_key = key
        cur = self._mask(A)
        changed = cur != self._prev
        # pairs as plain ints (np.nonzero's two index arrays, row-major as np.argwhere lists them)
        formed = list(zip(*(ix.tolist() for ix in np.nonzero(changed & cur))))
        pruned = list(zip(*(ix.tolist() for ix in np.nonzero(changed & self._prev))))
        for p in pruned:
            self._closed.append(LinkEvent(p[0], p[1], self._open.pop(p), tick))
        for p in formed:
            self._open[p] = tick
        self.formations += len(formed)
        self.prunings += len(pruned)
        self._prev = cur
        if self._first_tick is None:
            self._first_tick = tick
        self._last_tick = tick
        return formed, pruned

    @property
    def n_ticks(self) -> int:
        """Observation span T (last tick − first tick + 1), the reference's episode length."""
        if self._first_tick is None:
            return 0
        return self._last_tick - self._first_tick + 1

    @property
    def end(self) -> int:
        """Censoring point: last observed tick + 1."""
        return 0 if self._last_tick is None else self._last_tick + 1

    def events(self) -> list[LinkEvent]:
        """All events, closed ones in order of pruning, then the open (censored) ones in order of formation."""
        open_events = sorted(
            (LinkEvent(i, j, t0, None) for (i, j), t0 in self._open.items()), key=lambda e: (e.formed, e.i, e.j)
        )
        return list(self._closed) + open_events

    def lifetimes(self) -> tuple[np.ndarray, np.ndarray]:
        """(lifetimes, censored) arrays over all events, in :meth:`events` order."""
        ev = self.events()
        end = self.end
        life = np.array([e.lifetime(end) for e in ev], dtype=np.int64)
        cens = np.array([e.censored for e in ev], dtype=bool)
        return life, cens

    def median_lifetime(self) -> float:
        """Median over all events, censored ones at their censored length (as the reference); NaN if none."""
        life, _ = self.lifetimes()
        return float(np.median(life)) if life.size else float("nan")

    def core_periphery(self, threshold: int | None = None) -> tuple[int, int]:
        """(stable core, periphery) event counts: lifetime ≥ threshold (default ⌊T/2⌋) vs shorter."""
        if threshold is None:
            threshold = self.n_ticks // 2
        life, _ = self.lifetimes()
        core = int(np.count_nonzero(life >= threshold))
        return core, int(life.size) - core


# ---------------------------------------------------------------------------------------------------------------------
# Mean W by block


@dataclass(frozen=True)
class BlockMeans:
    """Mean preference weight per role block, diagonal excluded (NaN for an empty block)."""

    agv_agv: float
    agv_picker: float  # both directions pooled: entries W[agv, picker] and W[picker, agv]
    picker_picker: float
    agv_to_picker: float  # entries W[agv, picker] only (AGV rows)
    picker_to_agv: float  # entries W[picker, agv] only (picker rows)


def _block_mean(W: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> float:
    sel = np.outer(rows, cols)
    np.fill_diagonal(sel, False)
    n = np.count_nonzero(sel)
    return float(W[sel].mean()) if n else float("nan")


def mean_w_by_block(W, is_agv) -> BlockMeans:
    """Mean of W over the AGV–AGV, AGV–picker and picker–picker blocks, excluding the diagonal."""
    W = np.asarray(_square("W", W), dtype=float)
    agv = _agent_mask("is_agv", is_agv, W.shape[0])
    pk = ~agv
    a2p = _block_mean(W, agv, pk)
    p2a = _block_mean(W, pk, agv)
    both_sel = np.outer(agv, pk) | np.outer(pk, agv)
    both = float(W[both_sel].mean()) if both_sel.any() else float("nan")
    return BlockMeans(
        agv_agv=_block_mean(W, agv, agv),
        agv_picker=both,
        picker_picker=_block_mean(W, pk, pk),
        agv_to_picker=a2p,
        picker_to_agv=p2a,
    )


# ---------------------------------------------------------------------------------------------------------------------
# Algebraic connectivity


def _symmetric_edges(A, W=None) -> np.ndarray:
    """Undirected edge weights: a pair is an edge if linked either way; weight 1, or the mean of W_ij and W_ji."""
    L = _offdiag_links(A)
    E = L | L.T
    if W is None:
        return E.astype(float)
    Wm = np.asarray(_square("W", W), dtype=float)
    if Wm.shape != E.shape:
        raise ValueError(f"W: expected shape {E.shape}, got {Wm.shape}")
    return np.where(E, 0.5 * (Wm + Wm.T), 0.0)


def algebraic_connectivity(A, W=None) -> float:
    """Textbook algebraic connectivity: λ₂ of the combinatorial Laplacian L = D − S of the symmetrised link graph.

    S_ij = 1 for pairs linked in either direction (unweighted), or, when ``W`` is given, S_ij = (W_ij + W_ji)/2 on
    linked pairs (weighted).  λ₂ > 0 iff the graph is connected (for positive weights); isolated agents make it 0.
    Returns 0.0 for N < 2.  Eigen-solver round-off below 1e−10 × (total edge weight) is reported as exactly 0.
    """
    S = _symmetric_edges(A, W)
    n = S.shape[0]
    if n < 2:
        return 0.0
    Lap = np.diag(S.sum(axis=1)) - S
    ev = np.linalg.eigvalsh(Lap)  # ascending; the whole spectrum of 24 robots takes ~40 µs
    # Round-off can leave a connected graph's λ₁ at −1e−16 and a disconnected graph's λ₂ at ±1e−15: clamp to 0.
    lam = float(ev[1])
    return 0.0 if abs(lam) < 1e-10 * max(1.0, float(np.abs(S).sum())) else lam


def reference_normalized_fiedler(A, symmetrize: bool = True) -> float:
    """The reference code's "Fiedler value" (`MORPH._sg`), reproduced exactly.

    d_i = Σ_j A_ij; if every degree is 0 return 0; D^{-1/2} uses max(d_i, 1e−9); L = I − D^{-1/2} A D^{-1/2};
    return the second-smallest eigenvalue (scipy ``eigvalsh``, lower triangle).  Unlike the textbook value an
    isolated agent contributes eigenvalue 1, not 0, so this is not a connectivity measure when agents are isolated
    (K_N gives N/(N−1)).  The reference only ever passes a symmetric binary A; ``symmetrize=True`` first takes
    A ∨ Aᵀ (no change for symmetric A) so directed per-agent link rows give a well-defined answer.  The diagonal of A
    is used as given, as in the reference.
    """
    A = np.asarray(_square("A", A), dtype=float)
    if symmetrize:
        A = np.maximum(A, A.T)
    n = A.shape[0]
    d = A.sum(axis=1)
    if d.sum() == 0 or n < 2:
        return 0.0
    dis = 1.0 / np.sqrt(np.maximum(d, 1e-9))
    Lap = np.eye(n) - dis[:, None] * A * dis[None, :]
    if not np.isfinite(Lap).all():  # what scipy's eigvalsh refuses, and the reference then reports as 0
        return 0.0
    low = _lowest_two(Lap)
    return 0.0 if low is None else float(low[1])


_SYEVR: dict[int, tuple] = {}


def _lowest_two(sym: np.ndarray) -> np.ndarray | None:
    """The two smallest eigenvalues of the symmetric ``sym`` (its lower triangle), or None if the solver fails.

    ``scipy.linalg.eigvalsh(sym, subset_by_index=[0, 1])`` with its own LAPACK call (``syevr``, range 'I', the
    workspace it asks for), so the same bits; without its argument checks, which cost twice the solve on the 24×24
    Laplacian the record takes every tick."""
    n = sym.shape[0]
    solver = _SYEVR.get(n)
    if solver is None:
        from scipy.linalg.lapack import get_lapack_funcs

        syevr, syevr_lwork = get_lapack_funcs(("syevr", "syevr_lwork"), (sym,))
        work, iwork, info = syevr_lwork(n=n, lower=True)  # the workspace query scipy's eigvalsh makes
        if info != 0:
            return None
        solver = _SYEVR[n] = (syevr, int(work), int(iwork))
    syevr, lwork, liwork = solver
    w, _, found, _, info = syevr(a=sym, compute_v=0, range="I", il=1, iu=2, lower=True, overwrite_a=False,
                                 lwork=lwork, liwork=liwork)
    return w[:found] if info == 0 else None


def is_connected(A) -> bool:
    """True if the symmetrised link graph is connected (a single agent counts as connected)."""
    E = _symmetric_edges(A)
    if E.shape[0] <= 1:
        return True
    from scipy.sparse.csgraph import connected_components

    n_comp, _ = connected_components(E != 0, directed=False)
    return n_comp == 1


# ---------------------------------------------------------------------------------------------------------------------
# Spearman of W against distance


def mean_manhattan_distance(positions) -> np.ndarray:
    """(N, N) mean over ticks of the Manhattan distance between agents; ``positions`` is (T, N, 2) of (x, y)."""
    P = np.asarray(positions, dtype=float)
    if P.ndim != 3 or P.shape[2] != 2 or P.shape[0] < 1:
        raise ValueError(f"positions: expected shape (T≥1, N, 2), got {P.shape}")
    D = np.abs(P[:, :, None, :] - P[:, None, :, :]).sum(axis=3)
    return D.mean(axis=0)


@dataclass(frozen=True)
class SpearmanResult:
    """Spearman ρ of W against mean distance over ``n_pairs`` pairs.

    ``p_value`` is scipy's asymptotic two-sided p; ``p_permutation`` the permutation-test p (None if not run).
    Both are NaN (and ρ NaN) when either variable is constant, e.g. W still all zero.
    """

    rho: float
    p_value: float
    n_pairs: int
    p_permutation: float | None = None
    n_permutations: int = 0


def _spearman(x: np.ndarray, y: np.ndarray, n_permutations: int, rng) -> SpearmanResult:
    n = x.size
    if n < 3 or np.all(x == x[0]) or np.all(y == y[0]):
        nan = float("nan")
        return SpearmanResult(nan, nan, n, nan if n_permutations else None, n_permutations)
    from scipy import stats

    res = stats.spearmanr(x, y)
    rho, p = float(res.statistic), float(res.pvalue)
    p_perm = None
    if n_permutations > 0:
        gen = np.random.default_rng(rng)
        rx = stats.rankdata(x)
        ry = stats.rankdata(y)
        rx = rx - rx.mean()
        ry = ry - ry.mean()
        den = np.sqrt((rx * rx).sum() * (ry * ry).sum())
        # Permuting W over the pairs breaks any W–distance association while keeping both marginals (ties included).
        perms = gen.permuted(np.tile(ry, (n_permutations, 1)), axis=1)
        null = perms @ rx / den
        # Two-sided, counting the observed statistic itself (Phipson & Smyth) so p is never 0.
        hits = np.count_nonzero(np.abs(null) >= abs(rho) - 1e-12)
        p_perm = (hits + 1) / (n_permutations + 1)
    return SpearmanResult(rho, p, n, p_perm, n_permutations)


def spearman_agv_picker(
    W,
    mean_distance,
    is_agv,
    n_permutations: int = 10_000,
    rng: int | np.random.Generator | None = 0,
    direction: str = "agv_to_picker",
) -> SpearmanResult:
    """Spearman of W against mean Manhattan distance over directed AGV–picker pairs, with a permutation p-value.

    ``direction``: "agv_to_picker" (default) uses W[agv, picker] for every AGV→picker pair (n_agv·n_picker pairs,
    72 at Medium); "picker_to_agv" uses W[picker, agv]; "both" pools both directions (2·n_agv·n_picker).  With the
    reference's symmetric W, "agv_to_picker" equals the 72 unordered AGV–picker pairs.  ``rng`` seeds the
    permutation stream (an int seed or a Generator), so the p-value is reproducible.
    """
    W = np.asarray(_square("W", W), dtype=float)
    D = np.asarray(_square("mean_distance", mean_distance), dtype=float)
    if D.shape != W.shape:
        raise ValueError(f"mean_distance: expected shape {W.shape}, got {D.shape}")
    agv = _agent_mask("is_agv", is_agv, W.shape[0])
    a_idx = np.flatnonzero(agv)
    p_idx = np.flatnonzero(~agv)
    if direction == "agv_to_picker":
        sel = [(a_idx, p_idx)]
    elif direction == "picker_to_agv":
        sel = [(p_idx, a_idx)]
    elif direction == "both":
        sel = [(a_idx, p_idx), (p_idx, a_idx)]
    else:
        raise ValueError(f"direction: expected 'agv_to_picker', 'picker_to_agv' or 'both', got {direction!r}")
    ws = np.concatenate([W[np.ix_(r, c)].ravel() for r, c in sel])
    ds = np.concatenate([D[np.ix_(r, c)].ravel() for r, c in sel])
    return _spearman(ds, ws, n_permutations, rng)


def spearman_reference_pairs(
    W, mean_distance, n_permutations: int = 0, rng: int | np.random.Generator | None = 0
) -> SpearmanResult:
    """The reference's variant (`emergent.py`): all unordered pairs i<j, every role combination.

    x = mean Manhattan distance of the pair, y = final W_ij read from the upper triangle (i<j); N(N−1)/2 pairs (153 at
    Medium, N=18), same-role pairs included although they mostly tie at W = 0.  p is scipy's asymptotic p, as the
    reference prints; a permutation p is added if ``n_permutations`` > 0.
    """
    W = np.asarray(_square("W", W), dtype=float)
    D = np.asarray(_square("mean_distance", mean_distance), dtype=float)
    if D.shape != W.shape:
        raise ValueError(f"mean_distance: expected shape {W.shape}, got {D.shape}")
    iu = np.triu_indices(W.shape[0], k=1)
    return _spearman(D[iu], W[iu], n_permutations, rng)


# ---------------------------------------------------------------------------------------------------------------------
# Delivery rate and recovery after a demand shift


def rolling_sum(deliveries, window: int = 50) -> np.ndarray:
    """Trailing-window sum: out[t] = Σ deliveries[t−window+1 … t], steps before 0 counting as zero deliveries."""
    d = _series("deliveries", deliveries)
    if window < 1:
        raise ValueError(f"window: must be ≥ 1, got {window}")
    c = np.concatenate([[0.0], np.cumsum(d)])
    t = np.arange(d.size)
    return c[t + 1] - c[np.maximum(t + 1 - window, 0)]


def rolling_rate(deliveries, window: int = 50) -> np.ndarray:
    """Trailing-window mean delivery rate in deliveries per step: :func:`rolling_sum` / window."""
    return rolling_sum(deliveries, window) / window


def phase_deliveries(deliveries, boundaries: Sequence[int]) -> np.ndarray:
    """Deliveries per phase; ``boundaries`` are the phase start steps (first is 0), the last phase runs to the end."""
    d = _series("deliveries", deliveries)
    b = _boundaries(boundaries, d.size)
    ends = list(b[1:]) + [d.size]
    return np.array([d[s:e].sum() for s, e in zip(b, ends)])


def _boundaries(boundaries: Sequence[int], n: int) -> list[int]:
    b = [int(x) for x in boundaries]
    if not b or b[0] != 0:
        raise ValueError(f"boundaries: must start with 0 (phase start steps), got {b}")
    if any(y <= x for x, y in zip(b, b[1:])) or b[-1] >= n:
        raise ValueError(f"boundaries: must be strictly increasing and below the series length {n}, got {b}")
    return b


@dataclass(frozen=True)
class PhaseRecovery:
    """Recovery after the shift into ``phase`` (0-based), measured against phase ``baseline_phase``.

    ``time`` is in steps from the phase's first step; if the threshold is never reached inside the phase, ``time`` is
    the phase length and ``censored`` is True.
    """

    phase: int
    baseline_phase: int
    baseline: float  # deliveries per step
    threshold: float  # deliveries per step (fraction × baseline)
    time: int
    censored: bool


def recovery_time(rate, start: int, stop: int, level: float) -> tuple[int, bool]:
    """First offset k ≥ 0 with rate[start + k] ≥ level, searching steps start … stop−1.

    Returns (k, False), or (stop − start, True) when the level is never reached (censored at the phase length).
    """
    r = _series("rate", rate)
    if not (0 <= start < stop <= r.size):
        raise ValueError(f"start/stop: need 0 ≤ start < stop ≤ {r.size}, got {start}, {stop}")
    hit = np.flatnonzero(r[start:stop] >= level)
    if hit.size:
        return int(hit[0]), False
    return stop - start, True


def shift_recoveries(
    deliveries,
    boundaries: Sequence[int],
    window: int = 50,
    fraction: float = 0.9,
    baseline_lag: int = 2,
) -> list[PhaseRecovery]:
    """Recovery times of the shift experiment (paper r3–r6), for every phase with a same-side predecessor.

    Exact definition (the paper leaves it open; docs/morph.md):

    * rate(t) = trailing 50-step rolling mean of the per-step delivery series over the whole episode
      (:func:`rolling_rate`), so the rate at a boundary still reflects the previous phase and falls as the window
      fills with post-shift steps — the curve of the paper's figure;
    * the baseline for phase p (0-based) is the same side's previous phase, p − ``baseline_lag`` (demand alternates
      L/R, so lag 2): its mean delivery rate, i.e. deliveries in that phase / its length, in deliveries per step;
    * recovery time r_p = the first k ≥ 0 such that rate(b_p + k) ≥ ``fraction`` × baseline, b_p the phase's first
      step; 0 means the rate never fell below the threshold;
    * if it is not reached before the phase ends, r_p = phase length, flagged ``censored``.

    With six phases, boundaries [0, 400, …, 2000], the result covers phases 2…5, i.e. the paper's r3…r6.
    """
    d = _series("deliveries", deliveries)
    b = _boundaries(boundaries, d.size)
    if not 0 < fraction:
        raise ValueError(f"fraction: must be > 0, got {fraction}")
    if baseline_lag < 1:
        raise ValueError(f"baseline_lag: must be ≥ 1, got {baseline_lag}")
    ends = b[1:] + [d.size]
    rate = rolling_rate(d, window)
    out = []
    for p in range(baseline_lag, len(b)):
        q = p - baseline_lag
        base = float(d[b[q] : ends[q]].mean())
        level = fraction * base
        k, cens = recovery_time(rate, b[p], ends[p], level)
        out.append(PhaseRecovery(p, q, base, level, k, cens))
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Experiment-table statistics


@dataclass(frozen=True)
class MeanStd:
    mean: float
    std: float
    n: int

    def __str__(self) -> str:
        return self.format()

    def format(self, digits: int = 1) -> str:
        return f"{self.mean:.{digits}f} ± {self.std:.{digits}f}"


def mean_std(values: Iterable[float], ddof: int = 0) -> MeanStd:
    """Mean and standard deviation; ddof=0 (population std) as the reference's tables."""
    v = np.asarray(list(values), dtype=float)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"values: expected a non-empty 1-D sequence, got shape {v.shape}")
    if v.size <= ddof:
        raise ValueError(f"ddof: need more than {ddof} values, got {v.size}")
    return MeanStd(float(v.mean()), float(v.std(ddof=ddof)), int(v.size))


def nan_mean(values: Iterable[float]) -> float:
    """The mean of the values that are not NaN (numpy's ``nanmean``); NaN, without numpy's warning, when none is."""
    v = np.asarray(list(values), dtype=float)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def nan_std(values: Iterable[float]) -> float:
    """The population standard deviation of the values that are not NaN (numpy's ``nanstd``); NaN, without numpy's
    warning, when none is."""
    v = np.asarray(list(values), dtype=float)
    v = v[~np.isnan(v)]
    return float(v.std()) if v.size else float("nan")


def welch_p(a: Iterable[float], b: Iterable[float]) -> float:
    """Two-sided Welch t-test p-value (scipy ``ttest_ind(equal_var=False)``), as the reference's statistics.

    NaN when undefined (fewer than 2 values in a group, or both groups with zero variance).
    """
    x = np.asarray(list(a), dtype=float)
    y = np.asarray(list(b), dtype=float)
    if x.size < 2 or y.size < 2:
        return float("nan")
    if x.var() == 0 and y.var() == 0:
        return float("nan")
    from scipy import stats

    return float(stats.ttest_ind(x, y, equal_var=False).pvalue)
