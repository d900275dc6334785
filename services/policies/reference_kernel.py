"""The reference rule set's update of many replicas in one compiled loop (numba), for the in-process lab's fleet brain.

:meth:`.plasticity.ReferenceState.step` on B replicas of (n, n) arrays is some sixty numpy calls a tick, each on a few
thousand numbers, so what it costs is the calls, not the arithmetic. This module does the same arithmetic element by
element in one compiled function: every value is computed by the same IEEE operations, in the same order, from the same
operands as the numpy code (numba compiles without fast-math, so no operation is fused or reordered), and so has the
same bits. The tests step both on the same states and episodes and compare every array bit for bit.

It is only used where numba is installed and the state holds more than one replica (the lab): an agent process (one
replica) stays on numpy and never imports numba, which would cost it tens of MiB.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _clip(x: float, lo: float, hi: float) -> float:
    # np.minimum(np.maximum(x, lo), hi) of a number that is not NaN (every input here is finite)
    if not x >= lo:
        x = lo
    if not x <= hi:
        x = hi
    return x


@njit(cache=True)
def step_rows(rows, W, A, age, theta, j_prev, h, jaccard, alpha, credit_gain, bcm_tau, keep_tau, bcm_gain,
              keep_gamma, gamma, flat_decay, grace, cov, credit_threshold, beta, homeostasis_target, n_minus_1,
              eps, due, mi, theta_adj, max_new, theta_prune, formed, pruned):
    """One reference step of the replicas ``rows``: BCM threshold, decay, Hebbian term, delivery credit, clip,
    homeostasis, then for those ``due`` the structural step (prune, greedy formation on ``mi`` against
    ``theta_adj``), and ageing. ``alpha`` and ``theta_adj`` are per row of ``rows``; ``credit_gain`` is
    reward_alpha · deliveries, or 0 when no credit is paid (no delivery, or reward_alpha 0); ``bcm_gain`` 0 decays by
    ``flat_decay``."""
    n = W.shape[1]
    score = np.empty((n, n))
    for k in range(rows.shape[0]):
        b = rows[k]
        a_eff = alpha[k]
        formed[b] = 0
        pruned[b] = 0
        for i in range(n):
            deg = 0.0
            for j in range(n):
                w = W[b, i, j]
                a = A[b, i, j]
                if w == 0.0 and a == 0.0 and theta[b, i, j] == 0.0:
                    # a pair never linked (or long unlinked): every term below is +0.0 and leaves W and θ at +0.0
                    # (every operand is non-negative, so no -0.0 appears); only the co-assignment is kept
                    j_prev[b, i, j] = jaccard[i, j]
                    continue
                # BCM threshold tracks W before this step's decay
                th = theta[b, i, j] * bcm_tau + w * keep_tau
                if i == j:
                    th = 0.0
                theta[b, i, j] = th
                # decay, with extra decay on mature links above their threshold
                if bcm_gain > 0.0:
                    s = _clip(w / (th + eps) - 1.0, 0.0, 3.0)
                    s = bcm_gain * s
                    s = s * keep_gamma
                    s = s * (1.0 if age[b, i, j] > grace else 0.0)
                    w = w * _clip(gamma - s, 0.5, 1.0)
                else:
                    w = w * flat_decay
                # Hebbian term, then the delivery burst's credit to the pairs co-assigned on the previous step
                w = w + a_eff * jaccard[i, j] * cov * a
                if credit_gain != 0.0:
                    jp = j_prev[b, i, j]
                    w = w + credit_gain * (jp if jp > credit_threshold else 0.0) * a
                j_prev[b, i, j] = jaccard[i, j]
                w = _clip(w, 0.0, 1.0)
                if i == j:
                    w = 0.0
                W[b, i, j] = w
                deg += a
            # homeostasis, from the degrees before the structural step
            h[b, i] = _clip(h[b, i] + beta * (homeostasis_target - deg) / n_minus_1, 0.0, 1.0)
        if due[k]:
            pruned_cells = 0
            for i in range(n):
                for j in range(n):
                    if A[b, i, j] > 0.0 and W[b, i, j] < theta_prune and age[b, i, j] > grace:
                        A[b, i, j] = 0.0
                        W[b, i, j] = 0.0
                        theta[b, i, j] = 0.0
                        age[b, i, j] = 0.0
                        pruned_cells += 1
            pruned[b] = pruned_cells // 2
            for i in range(n):
                for j in range(n):
                    if A[b, i, j] != 0.0 or i == j:
                        score[i, j] = -1.0
                    else:
                        score[i, j] = mi[i, j] * (1.0 + (h[b, i] + h[b, j]))
            threshold = theta_adj[k]
            count = 0
            for _ in range(max_new):
                # the first largest score (np.argmax), with the rows and columns of agents already linked this step
                # at -1
                best, bi, bj = -np.inf, -1, -1
                for i in range(n):
                    for j in range(n):
                        v = score[i, j]
                        if v > best:
                            best, bi, bj = v, i, j
                if not best >= threshold:
                    break
                A[b, bi, bj] = 1.0
                A[b, bj, bi] = 1.0
                age[b, bi, bj] = 0.0
                age[b, bj, bi] = 0.0
                for x in (bi, bj):
                    for y in range(n):
                        score[x, y] = -1.0
                        score[y, x] = -1.0
                count += 1
            formed[b] = count
        # age + 1 on links, 0 elsewhere
        for i in range(n):
            for j in range(n):
                age[b, i, j] = age[b, i, j] + 1.0 if A[b, i, j] > 0.0 else 0.0
