"""MORPH plasticity rules: pure numpy state and updates, no I/O.

Where numba is installed, a state of many replicas (the lab's fleet brain) takes the reference rule set's update in one
compiled loop (:mod:`.reference_kernel`) with the numpy update's bits; one replica (an agent) always runs numpy.

Two rule sets share the parameter model (:mod:`.presets`):

* :class:`ReferenceState` reproduces the reference code (docs/morph.md): symmetric W and A,
  the η → BCM → decay → Hebbian → burst → clip → homeostasis → structural → ageing order, MI of the
  current positions, greedy ``max_new`` formation. It is batched over *replicas*: every agent that runs
  the reference preset owns one full replica (shape ``(B, n, n)``), so a process holding one agent has
  B = 1 and the in-process lab holds all agents with B = n. Replicas see the same inputs and stay equal.
* :class:`PaperState` implements the paper as written (Eq. 1-4, Algorithm 1): each agent owns only its
  directed out-row (shape ``(B, n)`` for B owned agents), learns from its own reward, credits the partner
  that shared the delivered task, estimates MI from task-assignment histories, forms links against a
  binding threshold and runs homeostasis every k steps from h = 0. docs/morph.md lists every choice. What the rows
  learn from the ticks (the task history, update count, d̂, baseline, η) is one replica shared by every row, or one per
  row where each robot takes views of its own.

Both are updated with arrays derived from a :class:`~.observation.TickObservation`; the translation
lives in :mod:`.policies`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from services.policies.presets import MorphParams

_EPS = 1e-9


def theta_form(params: MorphParams, t: int) -> float:
    """The annealed formation threshold at update count ``t``."""
    p = min(t / params.theta_form_anneal, 1.0)
    return params.theta_form_start - (params.theta_form_start - params.theta_form_end) * p


def neuromodulation(params: MorphParams, dhat: float, delivery: float, d_exp: float, t: int):
    """One step of the arousal signal: returns (new d̂, η, effective α, adjusted θ_form)."""
    dhat = params.neuromod_ema * delivery + (1.0 - params.neuromod_ema) * dhat
    # np.clip's value in plain floats (NaN passes through, as with np.clip): this runs every tick in every agent
    eta = float(min(max((dhat - d_exp) / (d_exp + _EPS), -1.0), 1.0))
    alpha_eff = params.alpha * (1.0 + params.neuromod_gain * max(eta, 0.0))
    theta_adj = theta_form(params, t) - params.neuromod_explore * max(-eta, 0.0)
    theta_adj = max(theta_adj, params.theta_adj_floor * params.theta_form_end)
    return dhat, eta, alpha_eff, theta_adj


def neuromodulation_rows(params: MorphParams, dhat: np.ndarray, delivery: float, d_exp, t: np.ndarray):
    """:func:`neuromodulation` of many replicas at once (``dhat``, ``t`` and optionally ``d_exp``: one per replica):
    the same operations in the same order on arrays, so every value has the bits the scalar function gives it."""
    dhat = params.neuromod_ema * delivery + (1.0 - params.neuromod_ema) * dhat
    eta = np.minimum(np.maximum((dhat - d_exp) / (d_exp + _EPS), -1.0), 1.0)
    alpha_eff = params.alpha * (1.0 + params.neuromod_gain * np.maximum(eta, 0.0))
    annealed = params.theta_form_start - (params.theta_form_start - params.theta_form_end) * np.minimum(
        t / params.theta_form_anneal, 1.0)
    theta_adj = annealed - params.neuromod_explore * np.maximum(-eta, 0.0)
    theta_adj = np.maximum(theta_adj, params.theta_adj_floor * params.theta_form_end)
    return dhat, eta, alpha_eff, theta_adj


def position_mi(positions: np.ndarray) -> np.ndarray:
    """The reference's "MI": |Pearson correlation| of the agents' normalised position rows.

    Identically 1 off the diagonal unless an agent's x/cols equals its y/rows. Computed
    the way the reference does (centre, divide by std + 1e-9) because the last bits of it break the
    formation ties.
    """
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise ValueError(f"positions: expected (n, 2) normalised cells, got shape {positions.shape}")
    # numpy's mean and std of each row, written out for rows of two: a sum of two numbers is one addition whichever
    # way a reduction orders it, so every value keeps the bits of positions.mean(axis=1) and oc.std(axis=1), at a
    # fraction of their cost (the fleet brain builds this every tick)
    x, y = positions[:, 0], positions[:, 1]
    mean = (x + y) / 2.0
    oc = positions - mean[:, None]
    ox, oy = oc[:, 0], oc[:, 1]
    centre = (ox + oy) / 2.0
    dx, dy = ox - centre, oy - centre
    std = np.sqrt((dx * dx + dy * dy) / 2.0)
    on = oc / (std + _EPS)[:, None]
    mi = np.abs(on @ on.T) / 2
    np.fill_diagonal(mi, 0.0)
    return mi


def _clip(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``np.clip(x, lo, hi, out=x)`` as two ufunc calls (same values, NaN included; np.clip's Python wrappers cost more
    than the clipping on the small arrays of one agent)."""
    return np.minimum(np.maximum(x, lo, out=x), hi, out=x)


_DIAGONALS: dict[int, tuple] = {}


def _zero_diagonal(x: np.ndarray) -> None:
    """``x[..., i, i] = 0`` for every i of a (..., n, n) array."""
    n = x.shape[-1]
    diagonal = _DIAGONALS.get(n)
    if diagonal is None:  # one index per fleet size, built once: every agent zeroes two diagonals every tick
        idx = np.arange(n)
        diagonal = _DIAGONALS[n] = (Ellipsis, idx, idx)
    x[diagonal] = 0.0


# --------------------------------------------------------------------------------------------------
# reference rule set

_NO_MI: dict[int, np.ndarray] = {}
_KERNEL: list = []


def compiled_kernels():
    """:mod:`.reference_kernel`, or None where numba is not installed or ``MORPH_SIM_KERNEL=numpy`` asks for numpy
    (both give the same bits; the compiled functions are the faster for many replicas)."""
    if not _KERNEL:
        kernels = None
        if os.environ.get("MORPH_SIM_KERNEL", "") != "numpy":
            try:
                from services.policies import reference_kernel as kernels
            except ImportError:
                kernels = None
        _KERNEL.append(kernels)
    return _KERNEL[0]


@dataclass
class ReferenceState:
    """B replicas of the reference's symmetric n×n state."""

    params: MorphParams
    n: int
    replicas: int
    d_exp: float
    W: np.ndarray = field(init=False)
    A: np.ndarray = field(init=False)
    age: np.ndarray = field(init=False)
    theta_bcm: np.ndarray = field(init=False)
    j_prev: np.ndarray = field(init=False)
    h: np.ndarray = field(init=False)
    # per replica: the delivery average d̂, the update count t and the last update's η. A replica that missed a
    # view (its robot's broadcast was lost) has taken fewer updates than the others, so these differ between
    # replicas once robots hold views of their own
    dhat: np.ndarray = field(init=False)
    t: np.ndarray = field(init=False)
    eta: np.ndarray = field(init=False)
    # last update's bookkeeping, for metrics
    formed: np.ndarray = field(init=False)
    pruned: np.ndarray = field(init=False)

    _ARRAYS = ("W", "A", "age", "theta_bcm", "j_prev", "h", "dhat", "t", "eta", "formed", "pruned")

    def __post_init__(self) -> None:
        shape = (self.replicas, self.n, self.n)
        self.W = np.zeros(shape)
        self.A = np.zeros(shape)
        self.age = np.zeros(shape)
        self.theta_bcm = np.zeros(shape)
        self.j_prev = np.zeros(shape)
        self.h = np.full((self.replicas, self.n), self.params.rho_target)
        self.dhat = np.full(self.replicas, float(self.d_exp))
        self.t = np.zeros(self.replicas, dtype=np.int64)
        self.eta = np.zeros(self.replicas)
        self.formed = np.zeros(self.replicas, dtype=int)
        self.pruned = np.zeros(self.replicas, dtype=int)
        self._setup()

    def _setup(self) -> None:
        self._eye = np.eye(self.n, dtype=bool)
        self._offdiag = ~self._eye

    def _take(self, rows: np.ndarray) -> ReferenceState:
        """The replicas ``rows`` as a state of their own (copies), to be stepped and put back with :meth:`_put`."""
        part = object.__new__(ReferenceState)
        part.params, part.n, part.replicas, part.d_exp = self.params, self.n, len(rows), self.d_exp
        for name in self._ARRAYS:
            setattr(part, name, getattr(self, name)[rows])
        part._setup()
        return part

    def _put(self, rows: np.ndarray, part: ReferenceState) -> None:
        for name in self._ARRAYS:
            getattr(self, name)[rows] = getattr(part, name)

    def _some(self, rows) -> np.ndarray | None:
        """``rows`` as an index array, or None when they are every replica (in order): the whole state is stepped."""
        if rows is None:
            return None
        rows = np.asarray(rows, dtype=int)
        if len(rows) == self.replicas and (rows == np.arange(self.replicas)).all():
            return None
        return rows

    def reset_links(self, rows=None) -> None:
        """MORPH-reset of the replicas ``rows`` (default all): clear W, A, θ_bcm, age and J_prev, h back to
        ρ_target; keep d̂ and t."""
        where = slice(None) if (rows := self._some(rows)) is None else rows
        for arr in (self.W, self.A, self.age, self.theta_bcm, self.j_prev):
            arr[where] = 0.0
        self.h[where] = self.params.rho_target

    def _neuromodulation(self, delivery: int):
        """Advance d̂ and η of every replica; returns (α_eff, θ_adj): floats when every replica has the same d̂ and t
        (always so for one replica, or replicas fed the same views), else per replica ((B, 1, 1) and (B,))."""
        p, t, dhat = self.params, self.t, self.dhat
        if self.replicas == 1 or ((t == t[0]).all() and (dhat == dhat[0]).all()):
            d, eta, alpha_eff, theta_adj = neuromodulation(p, float(dhat[0]), delivery, self.d_exp, int(t[0]))
            self.dhat[:] = d
            self.eta[:] = eta
            return alpha_eff, theta_adj
        self.dhat[:], self.eta[:], alpha, theta = neuromodulation_rows(p, dhat, delivery, self.d_exp, t)
        return alpha[:, None, None], theta

    def step(
        self,
        positions: np.ndarray,
        jaccard: np.ndarray,
        delivery: int,
        pred: np.ndarray | None,
        rows=None,
    ) -> None:
        """One ``MORPH.step`` of the reference code applied to the replicas ``rows`` (default every one).

        positions: (n, 2) normalised (x/cols, y/rows); jaccard: (n, n) co-assignment of this step;
        delivery: deliveries in this step; pred: the predictive hint or None. Only the structural update reads
        ``positions`` and ``pred``: on the other steps (:meth:`structural_due` false) they may be None.
        Each replica's arithmetic is the same whether it steps alone or with others.
        """
        if self.replicas > 1 and (kernels := compiled_kernels()) is not None:
            self._step_compiled(kernels.step_rows, positions, jaccard, delivery, pred, self._some(rows))
            return
        if (rows := self._some(rows)) is not None:
            if 2 * len(rows) <= self.replicas:
                part = self._take(rows)
                part.step(positions, jaccard, delivery, pred)
                self._put(rows, part)
            else:  # most replicas: step them all in place and put the few others back as they were
                stepped = np.zeros(self.replicas, dtype=bool)
                stepped[rows] = True
                others = np.flatnonzero(~stepped)
                kept = self._take(others)
                self._step(positions, jaccard, delivery, pred, stepped)
                self._put(others, kept)
            return
        self._step(positions, jaccard, delivery, pred, None)

    def _step_compiled(self, kernel, positions, jaccard, delivery, pred, rows: np.ndarray | None) -> None:
        """:meth:`step` of the replicas ``rows`` (None: all) by :func:`.reference_kernel.step_rows`: the same
        values, bit for bit, as :meth:`_step`."""
        p = self.params
        rows = np.arange(self.replicas) if rows is None else rows
        self.t[rows] += 1
        t = self.t[rows]
        self.dhat[rows], self.eta[rows], alpha, theta_adj = neuromodulation_rows(
            p, self.dhat[rows], delivery, self.d_exp, t)
        due = t % p.k == 0
        if due.any():
            mi = self._formation_mi(positions, pred)
        else:  # read by no replica
            mi = _NO_MI.get(self.n)
            if mi is None:
                mi = _NO_MI[self.n] = np.zeros((self.n, self.n))
        credit_gain = p.reward_alpha * delivery if (delivery > 0 and p.reward_alpha > 0.0) else 0.0
        kernel(rows, self.W, self.A, self.age, self.theta_bcm, self.j_prev, self.h, np.asarray(jaccard, dtype=float),
               alpha, float(credit_gain), p.bcm_tau, 1.0 - p.bcm_tau, float(p.bcm_gain), 1.0 - p.gamma, p.gamma,
               min(max(p.gamma, 0.5), 1.0), float(p.grace), p.cov, p.credit_threshold, p.beta,
               p.rho_target * (self.n - 1), float(self.n - 1), _EPS, due, mi, theta_adj, p.max_new(self.n),
               p.theta_prune, self.formed, self.pruned)

    def _step(self, positions, jaccard, delivery, pred, stepped: np.ndarray | None) -> None:
        """:meth:`step` of every replica; the structural update only of those ``stepped`` (a mask; None: all), the
        others being put back afterwards."""
        p = self.params
        self.t += 1
        alpha_eff, theta_adj = self._neuromodulation(delivery)
        W, theta, A = self.W, self.theta_bcm, self.A
        # Element for element the reference's arithmetic, in the same order; fewer calls and no temporaries, because
        # each agent process runs this on a small (n, n) array every tick, where the per-call overhead is the cost.

        # BCM threshold tracks W before this step's decay
        theta *= p.bcm_tau
        scratch = np.multiply(W, 1.0 - p.bcm_tau)
        theta += scratch
        _zero_diagonal(theta)

        # decay, with extra decay on mature links that rise above their threshold
        if p.bcm_gain > 0.0:
            # extra = bcm_gain · clip(W / (θ + ε) − 1, 0, 3) · (1 − γ) · mature;  W *= clip(γ − extra, 0.5, 1)
            np.add(theta, _EPS, out=scratch)
            np.divide(W, scratch, out=scratch)
            scratch -= 1.0
            _clip(scratch, 0.0, 3.0)
            np.multiply(p.bcm_gain, scratch, out=scratch)
            scratch *= 1.0 - p.gamma
            scratch *= self.age > p.grace
            np.subtract(p.gamma, scratch, out=scratch)
            W *= _clip(scratch, 0.5, 1.0)
        else:
            W *= min(max(p.gamma, 0.5), 1.0)

        # Hebbian term with the constant r^t = cov
        np.multiply(alpha_eff, jaccard, out=scratch)
        scratch *= p.cov
        scratch *= A
        W += scratch
        # delivery burst credits the pairs co-assigned on the previous step
        if delivery > 0 and p.reward_alpha > 0.0:
            credit = np.where(self.j_prev > p.credit_threshold, self.j_prev, 0.0)
            self.W += p.reward_alpha * delivery * credit * self.A
        self.j_prev[...] = jaccard
        _clip(W, 0.0, 1.0)
        _zero_diagonal(W)

        # homeostasis every step, from the degrees before the structural update
        deg = A.sum(axis=2)
        self.h += p.beta * (p.rho_target * (self.n - 1) - deg) / (self.n - 1)
        _clip(self.h, 0.0, 1.0)

        self.formed[:] = 0
        self.pruned[:] = 0
        due = self.t % p.k == 0
        if stepped is not None:
            due &= stepped
        if due.all():
            self._structural(positions, pred, theta_adj)
        elif due.any():  # replicas that missed views run their structural steps at other ticks
            self._structural(positions, pred, theta_adj, due)

        # age + 1 on links, 0 elsewhere (the reference's np.where, in place: age ≥ 0, so no −0.0 appears)
        age = self.age
        age += 1.0
        age *= A > 0

    def structural_due(self, rows=None) -> bool:
        """Whether the next :meth:`step` of the replicas ``rows`` (default all) runs the structural update of one of
        them (every k-th step), the only reader of the positions and the hint: an agent builds them only then."""
        if rows is None and self.replicas == 1:  # one brain (every tick of a team brain): a plain int
            return (int(self.t[0]) + 1) % self.params.k == 0
        t = self.t if (rows := self._some(rows)) is None else self.t[rows]
        return bool(((t + 1) % self.params.k == 0).any())

    def _formation_mi(self, positions: np.ndarray | None, pred: np.ndarray | None) -> np.ndarray:
        """The MI the formation scores: of the positions, boosted by the predictive hint where it is on."""
        if positions is None:
            raise ValueError("the structural update needs the positions (structural_due() was true)")
        mi = position_mi(positions)
        if pred is not None and self.params.pred_boost > 0.0:
            mi = _clip(mi + self.params.pred_boost * pred, 0.0, 1.0)
            np.fill_diagonal(mi, 0.0)
        return mi

    def _structural(self, positions: np.ndarray | None, pred: np.ndarray | None, theta_adj,
                    due: np.ndarray | None = None) -> None:
        """Prune and form in every replica, or in those ``due`` (a mask); ``theta_adj`` is one threshold or one per
        replica."""
        p = self.params
        n = self.n
        mi = self._formation_mi(positions, pred)

        prune = (self.A > 0) & (self.W < p.theta_prune) & (self.age > p.grace)
        if due is not None:
            prune &= due[:, None, None]
        if prune.any():  # rare: most structural steps prune nothing (self.pruned is 0 already)
            self.pruned[:] = prune.sum(axis=(1, 2)) // 2
            for arr in (self.A, self.W, self.theta_bcm, self.age):
                arr[prune] = 0.0

        # the replicas that form links now: every one, or those due (the score of the others is never read)
        sel = np.arange(self.replicas) if due is None else np.flatnonzero(due)
        h = self.h if due is None else self.h[sel]
        gain = h[:, :, None] + h[:, None, :]
        score = mi[None, :, :] * (1.0 + gain)
        score[((self.A if due is None else self.A[sel]) != 0) | self._eye] = -1.0
        if self.replicas == 1:
            self._form_one(score[0], p.max_new(n), float(np.reshape(theta_adj, -1)[0]))
            return
        if due is not None and not np.isscalar(theta_adj):
            theta_adj = theta_adj[sel]
        flat = score.reshape(len(sel), n * n)
        rows = np.arange(len(sel))
        active = np.ones(len(sel), dtype=bool)
        picks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (replicas, i, j) of each round
        for _ in range(p.max_new(n)):
            idx = flat.argmax(axis=1)
            ok = active & (flat[rows, idx] >= theta_adj)
            active = ok
            if not ok.any():
                break
            b = rows[ok]
            i, j = np.divmod(idx[ok], n)
            for x in (i, j):  # each agent gains at most one new link per structural step
                score[b, x, :] = -1.0
                score[b, :, x] = -1.0
            picks.append((sel[b], i, j))
        if picks:  # the rounds read only the scores: the links they picked are set at once
            r, i, j = (np.concatenate(part) for part in zip(*picks))
            self.A[r, i, j] = 1.0
            self.A[r, j, i] = 1.0
            self.age[r, i, j] = 0.0
            self.age[r, j, i] = 0.0
            self.formed += np.bincount(r, minlength=self.replicas)  # a replica picks once a round

    def _form_one(self, score: np.ndarray, max_new: int, theta_adj: float) -> None:
        """The greedy formation above for a single replica (an agent process): the same picks with scalar indices."""
        n = self.n
        flat = score.reshape(n * n)
        A, age = self.A[0], self.age[0]
        formed = 0
        for _ in range(max_new):
            idx = int(flat.argmax())
            if not flat[idx] >= theta_adj:
                break
            i, j = divmod(idx, n)
            A[i, j] = A[j, i] = 1.0
            age[i, j] = age[j, i] = 0.0
            for x in (i, j):  # each agent gains at most one new link per structural step
                score[x, :] = -1.0
                score[:, x] = -1.0
            formed += 1
        self.formed[0] = formed


# --------------------------------------------------------------------------------------------------
# paper rule set


def entropy_columns(labels: np.ndarray) -> np.ndarray:
    """Plug-in entropy (nats) of each column of an integer (T, M) array."""
    T = labels.shape[0]
    s = np.sort(labels, axis=0)
    # Σ_values c·log c = Σ_positions log(run length of the position's value)
    new = np.ones_like(s, dtype=bool)
    new[1:] = s[1:] != s[:-1]
    idx = np.arange(T)[:, None]
    start = np.maximum.accumulate(np.where(new, idx, 0), axis=0)
    end_marker = np.ones_like(s, dtype=bool)
    end_marker[:-1] = new[1:]
    end = np.minimum.accumulate(np.where(end_marker, idx, T - 1)[::-1], axis=0)[::-1]
    counts = end - start + 1
    return np.log(T) - np.log(counts).sum(axis=0) / T


def coassignment_rate(history: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(len(rows), n): share of agent i's busy ticks in the window on which agent j held the same task.

    The plug-in estimate of P(T_j = T_i | T_i ≠ ∅) over the history; 0 for an agent idle all window. (Every row
    reads the one history: :func:`coassignment_rates` with that history as each row's own.)
    """
    rows = np.asarray(rows)
    return coassignment_rates(np.broadcast_to(history, (len(rows), *history.shape)), rows)


def history_nmi(history: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Normalised mutual information between task-label histories.

    history: (T, n) task ids (0 = idle) over the last T ticks. Returns (len(rows), n):
    MI(X_i; X_j) / sqrt(H(X_i) H(X_j)) for i in ``rows`` (0 where either history is constant).
    """
    T, n = history.shape
    hx = np.maximum(entropy_columns(history), 0.0)
    big = int(history.max()) + 1
    joint = history[:, rows, None].astype(np.int64) * big + history[:, None, :]
    hj = entropy_columns(joint.reshape(T, -1)).reshape(len(rows), n)
    mi = hx[rows, None] + hx[None, :] - hj
    denom = np.sqrt(hx[rows, None] * hx[None, :])
    out = np.where(denom > 1e-12, mi / np.maximum(denom, 1e-12), 0.0)
    out = np.clip(out, 0.0, 1.0)
    out[np.arange(len(rows)), rows] = 0.0
    return out


@dataclass
class PaperInputs:
    """What one paper-preset update needs, derived from a tick (arrays over all n agents)."""

    task: np.ndarray  # (n,) task ids during the step (0 idle); T_i is built from them over a window
    reward: np.ndarray  # (n,) each agent's step reward (see PaperState.step)
    delivered: np.ndarray  # (n,) bool
    loader: np.ndarray  # (n,) int picker that loaded each delivered shelf
    deliveries: int
    hint: np.ndarray  # (n, n) 0/1 anticipated co-assignment (non-spatial)


_COLUMNS: dict[int, np.ndarray] = {}


def _columns(n: int, ticks: int) -> np.ndarray:
    """``np.tile(np.arange(n), ticks)``: the column of each label of a (ticks, n) history, flattened; kept per fleet
    size and grown as needed, because every agent builds its task sets from it every tick."""
    cols = _COLUMNS.get(n)
    if cols is None or cols.size < n * ticks:
        cols = _COLUMNS[n] = np.tile(np.arange(n), max(ticks, 64))
    return cols[: n * ticks]


_DENSE_LABELS = 1 << 16  # task ids up to this are indexed by counting; larger ones by sorting


def _distinct(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` with a flat inverse: the sorted distinct labels and each value's
    index among them. Task ids are small non-negative integers, which a count sorts faster than np.unique does (the
    task sets are rebuilt from the whole window every tick)."""
    flat = values.reshape(-1)
    if flat.size and 0 <= flat.min() and flat.max() <= _DENSE_LABELS:
        used = np.bincount(flat) > 0
        return np.flatnonzero(used), np.cumsum(used)[flat] - 1
    labels, inv = np.unique(flat, return_inverse=True)
    return labels, inv.reshape(-1)


def coassignment_rates(histories: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """:func:`coassignment_rate` of each row b from a history of its own: histories (B, T, n), rows (B,) → (B, n).

    A window shorter than T is given with its older ticks set to 0 (idle), which count in neither the busy ticks nor
    the shared ones: the counts, and so the rates, are those of the short window alone.
    """
    b = np.arange(len(rows))
    own = histories[b, :, rows]  # (B, T)
    same = (own[:, :, None] == histories) & (own[:, :, None] > 0)
    busy = (own > 0).sum(axis=1)
    rate = same.sum(axis=1) / np.maximum(busy, 1)[:, None]
    rate[b, rows] = 0.0
    return rate


@dataclass
class PaperState:
    """Directed out-rows of the agents ``owners`` (B of the n agents), and the task history they learn from.

    ``replicas`` is how many task histories (with the update count t, d̂, the delivery baseline and η) the rows
    share: 1 — every row learns from the same ticks (a team brain, or one agent's brain) — or B, one per row, each
    row stepped from the views its own robot took (:meth:`step`'s ``rows``; a fleet whose robots hold views of their
    own). A row's arithmetic is the same whether it steps alone, with others, or with a history of its own.
    """

    params: MorphParams
    n: int
    owners: np.ndarray
    d_exp: float
    replicas: int = 1
    W: np.ndarray = field(init=False)
    A: np.ndarray = field(init=False)
    age: np.ndarray = field(init=False)
    theta_bcm: np.ndarray = field(init=False)
    h: np.ndarray = field(init=False)
    # per replica
    history: np.ndarray = field(init=False)  # (replicas, window, n) task labels seen in ticks
    filled: np.ndarray = field(init=False)  # how many of the window's ticks have been seen
    dhat: np.ndarray = field(init=False)
    baseline: np.ndarray = field(init=False)
    t: np.ndarray = field(init=False)
    eta: np.ndarray = field(init=False)
    # last update's bookkeeping, per row
    formed: np.ndarray = field(init=False)
    pruned: np.ndarray = field(init=False)

    _ROWS = ("owners", "W", "A", "age", "theta_bcm", "h", "formed", "pruned")
    _REPLICA = ("history", "filled", "dhat", "baseline", "t", "eta")

    def __post_init__(self) -> None:
        self.owners = np.asarray(self.owners, dtype=int)
        b = len(self.owners)
        if self.replicas not in (1, b):
            raise ValueError(f"replicas: {self.replicas} (1, shared by the rows, or one per row: {b})")
        shape = (b, self.n)
        self.W = np.zeros(shape)
        self.A = np.zeros(shape)
        self.age = np.zeros(shape)
        self.theta_bcm = np.zeros(shape)
        self.h = np.zeros(b)
        r = self.replicas
        self.history = np.zeros((r, self.params.mi_window, self.n), dtype=np.int64)
        self.filled = np.zeros(r, dtype=np.int64)
        self.dhat = np.full(r, float(self.d_exp))
        self.baseline = np.full(r, float(self.d_exp))
        self.t = np.zeros(r, dtype=np.int64)
        self.eta = np.zeros(r)
        self.formed = np.zeros(b, dtype=int)
        self.pruned = np.zeros(b, dtype=int)
        self._setup()

    def _setup(self) -> None:
        self._self = (np.arange(len(self.owners)), self.owners)

    @property
    def rep(self) -> np.ndarray:
        """(B,) the replica of each row."""
        return np.zeros(len(self.owners), dtype=int) if self.replicas == 1 else np.arange(self.replicas)

    def _take(self, rows: np.ndarray) -> PaperState:
        """The rows ``rows`` with their replicas (one per row) as a state of their own (copies), to be stepped and put
        back with :meth:`_put`."""
        part = object.__new__(PaperState)
        part.params, part.n, part.d_exp, part.replicas = self.params, self.n, self.d_exp, len(rows)
        for name in self._ROWS + self._REPLICA:
            setattr(part, name, getattr(self, name)[rows])
        part._setup()
        return part

    def _put(self, rows: np.ndarray, part: PaperState) -> None:
        for name in self._ROWS[1:] + self._REPLICA:
            getattr(self, name)[rows] = getattr(part, name)

    def reset_links(self, rows=None) -> None:
        """Clear the links of the rows ``rows`` (default all): W, A, ages, BCM thresholds, h = 0; the task history, d̂,
        the baseline and t stay."""
        where = slice(None) if rows is None else np.asarray(rows, dtype=int)
        for arr in (self.W, self.A, self.age, self.theta_bcm):
            arr[where] = 0.0
        self.h[where] = 0.0

    def _window(self, length: np.ndarray, size: int, history: np.ndarray | None = None) -> np.ndarray:
        """(replicas, size, n): the last ``size`` ticks of each replica's history (or of ``history``, some replicas'
        histories) with the ticks before its own last ``length`` (per replica) set to 0, idle: what every rule below
        ignores."""
        hist = (self.history if history is None else history)[:, -size:]
        old = np.arange(size)[None, :] < (size - length)[:, None]
        return np.where(old[:, :, None], 0, hist) if old.any() else hist

    def task_jaccard(self) -> np.ndarray:
        """(B, n) Jaccard of task sets: T_i = the distinct tasks agent i held in the last ``task_window`` ticks (of
        its row's replica)."""
        p = self.params
        n = self.n
        if self.replicas == 1:
            f = int(self.filled[0])
            hist = self.history[0, -min(f, p.task_window):] if f else self.history[0, -1:]
            labels, inv = _distinct(hist)
            member = np.zeros((n, labels.size), dtype=bool)
            member[_columns(n, hist.shape[0]), inv] = True
            member[:, labels == 0] = False  # idle is not a task
            m = member.astype(float)
            inter = m[self.owners] @ m.T
            size = m.sum(axis=1)
            union = size[self.owners][:, None] + size[None, :] - inter
        else:
            kernels = compiled_kernels()
            if kernels is not None:
                jac = np.empty((self.replicas, n))
                if kernels.task_jaccard_rows(self.history, self.filled, p.task_window, self.owners, jac,
                                             _DENSE_LABELS):
                    return jac
            # each replica's window as long as it alone takes (at least one tick), padded with idle ticks; the
            # intersections and sizes are counts (sums of 0/1 products), so exact, the same numbers as alone
            hist = self._window(np.maximum(np.minimum(self.filled, p.task_window), 1), p.task_window)
            r, ticks = hist.shape[:2]
            labels, inv = _distinct(hist)
            u = labels.size
            m = np.zeros((r, n, u))  # replica × agent × task: 1.0 where the agent held the task in the window
            m.reshape(-1)[(np.repeat(np.arange(r) * n, ticks * n) + _columns(n, r * ticks)) * u + inv] = 1.0
            m[:, :, labels == 0] = 0.0
            rows = np.arange(r)
            inter = (m @ m[rows, self.owners][:, :, None])[:, :, 0]
            size = m.sum(axis=2)
            union = size[rows, self.owners][:, None] + size - inter
        jac = np.where(union > 0, inter / np.maximum(union, 1.0), 0.0)
        jac[self._self] = 0.0
        return jac

    def step(self, x: PaperInputs, rows=None) -> None:
        """One update of the rows ``rows`` (default every row) from ``x``. With ``rows``, each row has a replica of its
        own (``replicas`` = B) and the other rows are untouched."""
        if self.replicas > 1 and (kernels := compiled_kernels()) is not None:
            if rows is not None:
                rows = np.asarray(rows, dtype=int)
                if len(rows) == self.replicas and (rows == np.arange(self.replicas)).all():
                    rows = None
            self._step_compiled(kernels, x, rows)
            return
        if rows is not None:
            rows = np.asarray(rows, dtype=int)
            if len(rows) != self.replicas or (rows != np.arange(self.replicas)).any():
                if self.replicas != len(self.owners):
                    raise ValueError("step: rows need a replica per row")
                if 2 * len(rows) <= self.replicas:
                    part = self._take(rows)
                    part._step(x)
                    self._put(rows, part)
                else:  # most rows (each row's update reads only its own row and replica): step them all in place
                    # and put the few others back as they were
                    stepped = np.zeros(self.replicas, dtype=bool)
                    stepped[rows] = True
                    others = np.flatnonzero(~stepped)
                    kept = self._take(others)
                    self._step(x)
                    self._put(others, kept)
                return
        self._step(x)

    def _neuromodulation(self, deliveries: int):
        """Advance d̂, η and the baseline of every replica; returns θ_adj: a float with one replica, else (B,)."""
        p = self.params
        if self.replicas == 1:  # plain floats: this runs every tick in every agent
            baseline = float(self.baseline[0])
            d, eta, _, theta_adj = neuromodulation(p, float(self.dhat[0]), deliveries, baseline, int(self.t[0]))
            self.dhat[0], self.eta[0] = d, eta
            self.baseline[0] = baseline + p.baseline_ema * (deliveries - baseline)
            return theta_adj
        self.dhat[:], self.eta[:], _, theta_adj = neuromodulation_rows(p, self.dhat, deliveries, self.baseline, self.t)
        self.baseline += p.baseline_ema * (deliveries - self.baseline)
        return theta_adj

    def _step_compiled(self, kernels, x: PaperInputs, rows: np.ndarray | None) -> None:
        """:meth:`_step` of the rows ``rows`` (None: every row), each with its replica, in place: the element-wise
        update by :func:`.reference_kernel.paper_step_rows`, the rest as :meth:`_step` does it, on those rows only.
        The same values, bit for bit, as :meth:`_step` of the rows taken apart."""
        p = self.params
        every = rows is None
        if every:
            rows = np.arange(self.replicas)
            self.t += 1
            self.history[:, :-1] = self.history[:, 1:]
            self.history[:, -1] = x.task
            np.minimum(self.filled + 1, p.mi_window, out=self.filled)
            jac = self.task_jaccard()
        else:
            self.t[rows] += 1
            history = self.history[rows]
            history[:, :-1] = history[:, 1:].copy()
            history[:, -1] = x.task
            self.history[rows] = history
            self.filled[rows] = np.minimum(self.filled[rows] + 1, p.mi_window)
            jac = np.empty((len(rows), self.n))
            if not kernels.task_jaccard_rows(history, self.filled[rows], p.task_window, self.owners[rows], jac,
                                             _DENSE_LABELS):
                jac = self._take(rows).task_jaccard()
        eta = self.eta[rows]
        alpha_eff = p.alpha * (1.0 + p.neuromod_gain * np.maximum(eta, 0.0))
        reward = (x.reward[self.owners[rows]].astype(float) if p.use_step_reward
                  else np.full(len(rows), float(p.cov)))
        kernels.paper_step_rows(rows, self.W, self.A, self.age, self.theta_bcm, jac, alpha_eff, reward, self.owners,
                                np.asarray(x.loader, dtype=np.int64), np.asarray(x.delivered, dtype=np.bool_),
                                bool(p.reward_alpha > 0.0 and x.deliveries > 0), float(p.reward_alpha), p.bcm_tau,
                                1.0 - p.bcm_tau, float(p.bcm_gain), 1.0 - p.gamma, p.gamma, float(p.grace),
                                float(p.credit_threshold), _EPS)
        # R4b, then the structural step of the rows at a k-th update, then ageing
        baseline = self.baseline[rows]
        self.dhat[rows], self.eta[rows], _, theta_rows = neuromodulation_rows(p, self.dhat[rows], x.deliveries,
                                                                             baseline, self.t[rows])
        self.baseline[rows] = baseline + p.baseline_ema * (x.deliveries - baseline)
        self.formed[rows] = 0
        self.pruned[rows] = 0
        due = self.t[rows] % p.k == 0
        if due.any():
            theta_adj = np.zeros(self.replicas)
            theta_adj[rows] = theta_rows
            self._structural(x, theta_adj, rows[due])
        if every:
            self.age = np.where(self.A > 0, self.age + 1.0, 0.0)
        else:
            self.age[rows] = np.where(self.A[rows] > 0, self.age[rows] + 1.0, 0.0)

    def _step(self, x: PaperInputs) -> None:
        p = self.params
        own = self.owners
        one = self.replicas == 1
        self.t += 1

        # the task history every agent keeps from the ticks (input of J and of MI)
        self.history[:, :-1] = self.history[:, 1:]
        self.history[:, -1] = x.task
        if one:
            self.filled[0] = min(int(self.filled[0]) + 1, p.mi_window)
        else:
            np.minimum(self.filled + 1, p.mi_window, out=self.filled)

        # R4a: BCM threshold before the Hebbian step; extra decay on mature links above it
        self.theta_bcm *= p.bcm_tau
        self.theta_bcm += (1.0 - p.bcm_tau) * self.W
        mature = self.age > p.grace
        ratio = self.W / (self.theta_bcm + _EPS)
        extra = p.bcm_gain * _clip(ratio - 1.0, 0.0, 3.0) * (1.0 - p.gamma) * mature
        retention = _clip(p.gamma - extra, 0.5, 1.0)

        # Algorithm 1 runs R4b after R1, so R1 uses the α modulated by the previous step's η
        if one:
            alpha_eff = p.alpha * (1.0 + p.neuromod_gain * max(float(self.eta[0]), 0.0))
        else:
            alpha_eff = (p.alpha * (1.0 + p.neuromod_gain * np.maximum(self.eta, 0.0)))[:, None]

        # R1, Eq. 2: W ← γW + α J r A with J the Jaccard of recent task sets and r the agent's own step
        # reward (TA-RWARE's individual reward: +1 to the delivering AGV, +0.1 to the picker per load/unload,
        # -0.001 per step). Only J > 0.25 is credited, so the AGV's delivery strengthens its link to the
        # picker that shared the delivered task, not every co-active pair.
        jac = self.task_jaccard()
        credit = np.where(jac > p.credit_threshold, jac, 0.0)
        r = x.reward[own] if p.use_step_reward else np.full(len(own), p.cov)
        self.W *= retention
        self.W += alpha_eff * credit * r[:, None] * self.A
        # α_r: the picker that loaded a delivered shelf is credited for the delivery too (its own reward
        # for it is 0 in TA-RWARE's individual scheme)
        if p.reward_alpha > 0.0 and x.deliveries > 0:
            helped = (x.loader[None, :] == own[:, None]) & x.delivered[None, :]
            if helped.any():
                self.W += p.reward_alpha * helped * self.A
        _clip(self.W, 0.0, 1.0)
        self.W[self._self] = 0.0

        # R4b: η compares the delivery rate with a running baseline (fixed d_exp if baseline_ema = 0)
        theta_adj = self._neuromodulation(x.deliveries)

        self.formed[:] = 0
        self.pruned[:] = 0
        if one:
            if int(self.t[0]) % p.k == 0:
                self._structural(x, theta_adj, None)
        elif (due := self.t % p.k == 0).all():
            self._structural(x, theta_adj, None)
        elif due.any():  # rows whose robots missed views run their structural steps at other ticks
            self._structural(x, theta_adj, np.flatnonzero(due))

        self.age = np.where(self.A > 0, self.age + 1.0, 0.0)

    def _mi(self, rows: np.ndarray | None = None) -> np.ndarray:
        """(B, n) MI estimate of every row from its replica's history; with ``rows`` (a replica per row), of those
        rows only."""
        p = self.params
        if self.replicas == 1:
            f = int(self.filled[0])
            hist = self.history[0, -f:] if f >= 2 else self.history[0, -2:]
            return history_nmi(hist, self.owners) if p.mi_estimator == "nmi" else coassignment_rate(hist, self.owners)
        if rows is not None and p.mi_estimator != "nmi" and (kernels := compiled_kernels()) is not None:
            out = np.empty((len(rows), self.n))
            kernels.coassignment_rows(self.history, rows, self.owners, self.filled, out)
            return out
        own, filled, history = ((self.owners, self.filled, self.history) if rows is None else
                                (self.owners[rows], self.filled[rows], self.history[rows]))
        if p.mi_estimator == "nmi":  # its entropies depend on the window's length: each replica's on its own
            out = np.empty((len(own), self.n))
            for r, f in enumerate(filled.tolist()):
                hist = history[r, -f:] if f >= 2 else history[r, -2:]
                out[r] = history_nmi(hist, own[r : r + 1])[0]
            return out
        # counts over each replica's window (at least two ticks, as alone), its older ticks idle
        return coassignment_rates(self._window(np.maximum(filled, 2), p.mi_window, history), own)

    def _structural(self, x: PaperInputs, theta_adj, rows: np.ndarray | None) -> None:
        """Prune, form and homeostasis of every row, or of the rows ``rows`` (their replicas are at a k-th step);
        ``theta_adj`` is one threshold or one per row."""
        p = self.params
        if self.replicas > 1 and (kernels := compiled_kernels()) is not None:
            rows = np.arange(self.replicas) if rows is None else rows
            mi = self._mi(rows)
            if p.use_pred_hint and p.pred_boost > 0.0:
                mi = mi + p.pred_boost * x.hint[self.owners[rows]]
            kernels.paper_structural_rows(rows, mi, self.W, self.A, self.age, self.theta_bcm, self.h, self.owners,
                                          theta_adj[rows], p.theta_prune, float(p.grace), p.max_new(self.n), p.beta,
                                          p.rho_target, float(self.n - 1), p.h_min, p.h_max, self.formed,
                                          self.pruned)
            return
        if rows is not None:
            part = self._take(rows)
            part._structural(x, theta_adj[rows], None)
            self._put(rows, part)
            return
        own = self.owners
        mi = self._mi()
        if p.use_pred_hint and p.pred_boost > 0.0:
            mi = mi + p.pred_boost * x.hint[own]
        # Eq. 3-4 prune (age ≥ g) then form; a pair pruned now waits for the next structural step
        prune = (self.A > 0) & (self.W < p.theta_prune) & (self.age >= p.grace)
        self.pruned[:] = prune.sum(axis=1)
        for arr in (self.A, self.W, self.theta_bcm, self.age):
            arr[prune] = 0.0
        # H_gain,ij = h_i + h_j; an agent knows only its own h, so it uses 2 h_i
        score = mi * (1.0 + 2.0 * self.h[:, None])
        cand = (self.A == 0) & ~prune & (score >= (theta_adj if isinstance(theta_adj, float) else theta_adj[:, None]))
        cand[self._self] = False
        cap = p.max_new(self.n)
        if cap < self.n:
            # keep the best `cap` candidates of each row (stable: ties by index)
            masked = np.where(cand, score, -np.inf)
            order = np.argsort(-masked, axis=1, kind="stable")[:, :cap]
            keep = np.zeros_like(cand)
            np.put_along_axis(keep, order, True, axis=1)
            cand &= keep
        self.A[cand] = 1.0
        self.age[cand] = 0.0
        self.formed[:] = cand.sum(axis=1)
        # R2 every k steps, from h = 0
        deg = self.A.sum(axis=1)
        self.h += p.beta * (p.rho_target - deg / (self.n - 1))
        _clip(self.h, p.h_min, p.h_max)
