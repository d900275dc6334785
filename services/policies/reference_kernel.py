"""MORPH's updates of many replicas in compiled loops (numba), for the in-process lab's fleet brain.

:meth:`.plasticity.ReferenceState.step` on B replicas of (n, n) arrays is some sixty numpy calls a tick, each on a few
thousand numbers, so what it costs is the calls, not the arithmetic. :func:`step_rows` does the same arithmetic element
by element in one compiled function; the paper preset's task sets, co-assignment rates and structural step have
theirs. Every value is computed by the same IEEE operations, in the same order, from the same
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


@njit(cache=True)
def paper_step_rows(rows, W, A, age, theta, jaccard, alpha, reward, owners, loader, delivered, credit_delivery,
                    reward_alpha, bcm_tau, keep_tau, bcm_gain, keep_gamma, gamma, grace, credit_threshold, eps):
    """The paper preset's element-wise update of the rows ``rows`` (``PaperState._step`` between the task history and
    the neuromodulation): the BCM threshold, the retention that decays mature links above it, the Hebbian term on the
    task-set Jaccard ``jaccard[k]`` above ``credit_threshold`` times the row's ``alpha[k]`` and ``reward[k]``, the
    loader's credit for a delivered shelf (only when ``credit_delivery``: a delivery this step and reward_alpha > 0),
    then W clipped to [0, 1] with the robot's own column at 0. ``jaccard``, ``alpha`` and ``reward`` are per row of
    ``rows``."""
    n = W.shape[1]
    if credit_delivery:  # numpy adds the loader's credit only when some stepped row has a shelf it loaded delivered
        credit_delivery = False
        for k in range(rows.shape[0]):
            own = owners[rows[k]]
            for j in range(n):
                if loader[j] == own and delivered[j]:
                    credit_delivery = True
    for k in range(rows.shape[0]):
        b = rows[k]
        own = owners[b]
        a_eff = alpha[k]
        r = reward[k]
        for j in range(n):
            w = W[b, j]
            a = A[b, j]
            th = theta[b, j] * bcm_tau + keep_tau * w
            theta[b, j] = th
            s = bcm_gain * _clip(w / (th + eps) - 1.0, 0.0, 3.0)
            s = s * keep_gamma
            s = s * (1.0 if age[b, j] > grace else 0.0)
            w = w * _clip(gamma - s, 0.5, 1.0)
            jac = jaccard[k, j]
            w = w + a_eff * (jac if jac > credit_threshold else 0.0) * r * a
            if credit_delivery:
                w = w + reward_alpha * (1.0 if (loader[j] == own and delivered[j]) else 0.0) * a
            w = _clip(w, 0.0, 1.0)
            if j == own:
                w = 0.0
            W[b, j] = w


@njit(cache=True)
def _task_set(labels, mark, stamp, own_mark, own_stamp):
    """(the distinct tasks among ``labels``, how many of them own holds): a task is a label > 0, counted once by
    marking it with ``stamp`` in ``mark``; own's tasks are those marked ``own_stamp`` in ``own_mark``."""
    size = 0
    shared = 0
    for label in labels:
        if label > 0 and mark[label] != stamp:
            mark[label] = stamp
            size += 1
            if own_mark[label] == own_stamp:
                shared += 1
    return size, shared


@njit(cache=True)
def task_jaccard_rows(history, filled, task_window, owners, out, most_labels):
    """The paper preset's task-set Jaccard of every row b, from a history of its own (``PaperState.task_jaccard`` of
    many replicas): T_i = the distinct non-zero labels agent i held in the last max(min(filled[b], task_window), 1)
    ticks of history[b]; out[b, j] = |T_own ∩ T_j| / |T_own ∪ T_j| (0 for an empty union and for j = own). Counts are
    integers, so the division has numpy's operands and bits. Returns False, leaving ``out`` unfinished, when a label
    is negative or above ``most_labels`` (the caller then counts with numpy)."""
    replicas, ticks, n = history.shape
    top = 0
    for b in range(replicas):
        for t in range(ticks - min(max(task_window, 1), ticks), ticks):  # the ticks any window reads
            for j in range(n):
                label = history[b, t, j]
                if label < 0 or label > most_labels:
                    return False
                if label > top:
                    top = label
    own_mark = np.zeros(top + 1, dtype=np.int64)
    seen = np.zeros(top + 1, dtype=np.int64)
    stamp = 0
    for b in range(replicas):
        own = owners[b]
        length = min(filled[b], task_window)
        length = min(max(length, 1), ticks)
        start = ticks - length
        stamp += 1
        own_stamp = stamp
        own_size, _ = _task_set(history[b, start:, own], own_mark, own_stamp, own_mark, own_stamp)
        for j in range(n):
            if j == own:
                out[b, j] = 0.0
                continue
            stamp += 1
            size, inter = _task_set(history[b, start:, j], seen, stamp, own_mark, own_stamp)
            union = own_size + size - inter
            out[b, j] = float(inter) / float(union) if union > 0 else 0.0
    return True


@njit(cache=True)
def paper_structural_rows(rows, mi, W, A, age, theta, h, owners, theta_adj, theta_prune, grace, cap, beta,
                          rho_target, n_minus_1, h_min, h_max, formed, pruned):
    """The paper preset's structural step of the rows ``rows`` (``PaperState._structural``), ``mi`` holding their
    MI (hint included) row by row: prune links of age ≥ grace below θ_prune; form links to the ``cap`` best
    candidates (score = MI · (1 + 2 h) ≥ θ_adj, not linked, not pruned now, not itself; ties to the lower index, as a
    stable sort gives them); homeostasis from the new degree."""
    n = W.shape[1]
    chosen = np.empty(n, dtype=np.bool_)
    score = np.empty(n)
    for k in range(rows.shape[0]):
        b = rows[k]
        own = owners[b]
        cut = 0
        for j in range(n):
            candidate = True
            if A[b, j] > 0.0 and W[b, j] < theta_prune and age[b, j] >= grace:
                A[b, j] = 0.0
                W[b, j] = 0.0
                theta[b, j] = 0.0
                age[b, j] = 0.0
                cut += 1
                candidate = False
            s = mi[k, j] * (1.0 + 2.0 * h[b])
            chosen[j] = False
            if candidate and A[b, j] == 0.0 and j != own and s >= theta_adj[k]:
                score[j] = s
            else:
                score[j] = -np.inf
        pruned[b] = cut
        count = 0
        for _ in range(cap):
            best, pick = -np.inf, -1
            for j in range(n):
                if not chosen[j] and score[j] > best:
                    best, pick = score[j], j
            if pick < 0:
                break
            chosen[pick] = True
            A[b, pick] = 1.0
            age[b, pick] = 0.0
            count += 1
        formed[b] = count
        deg = 0.0
        for j in range(n):
            deg += A[b, j]
        h[b] = _clip(h[b] + beta * (rho_target - deg / n_minus_1), h_min, h_max)


@njit(cache=True)
def coassignment_rows(history, rows, owners, filled, out):
    """The paper preset's co-assignment rate of the rows ``rows``, each from its own history (``coassignment_rates``
    of their windows): over the last max(filled[b], 2) ticks, out[k, j] = the ticks on which agent j held the task own
    held (a task: label > 0) ÷ the ticks own held one (at least 1), 0 for j = own. Counts are integers, so the
    division has numpy's operands and bits."""
    ticks, n = history.shape[1], history.shape[2]
    for k in range(rows.shape[0]):
        b = rows[k]
        own = owners[b]
        start = max(ticks - max(filled[b], 2), 0)
        busy = 0
        for t in range(start, ticks):
            if history[b, t, own] > 0:
                busy += 1
        denominator = float(max(busy, 1))
        for j in range(n):
            if j == own:
                out[k, j] = 0.0
                continue
            same = 0
            for t in range(start, ticks):
                label = history[b, t, own]
                if label > 0 and history[b, t, j] == label:
                    same += 1
            out[k, j] = float(same) / denominator
