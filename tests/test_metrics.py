"""Pure metric computations: hand-computed answers for every metric, plus a few properties."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from services.metrics import measures as m


def sym(n, pairs):
    A = np.zeros((n, n), dtype=int)
    for i, j in pairs:
        A[i, j] = A[j, i] = 1
    return A


# ----------------------------------------------------------------------------------------------------- link counts


def test_link_counts_directed_and_undirected():
    A = np.zeros((4, 4), dtype=int)
    A[0, 1] = 1  # one-way link
    A[2, 3] = A[3, 2] = 1  # mutual link
    A[1, 1] = 1  # diagonal never counts
    assert m.undirected_link_count(A) == 2
    assert m.directed_link_count(A) == 3
    assert m.undirected_link_count(np.zeros((3, 3))) == 0
    K5 = np.ones((5, 5)) - np.eye(5)
    assert m.undirected_link_count(K5) == 10
    assert m.directed_link_count(K5) == 20


def test_link_count_rejects_non_square():
    with pytest.raises(ValueError, match="A"):
        m.undirected_link_count(np.zeros((2, 3)))


# ------------------------------------------------------------------------------------------------------ link events


def test_link_tracker_scripted_sequence():
    n = 3
    seq = [
        sym(n, []),  # t0
        sym(n, [(0, 1)]),  # t1: (0,1) forms
        sym(n, [(0, 1), (1, 2)]),  # t2: (1,2) forms
        sym(n, [(1, 2)]),  # t3: (0,1) pruned, lifetime 3-1 = 2
        sym(n, [(1, 2), (0, 1)]),  # t4: (0,1) re-forms
        sym(n, []),  # t5: both pruned: (1,2) lifetime 3, (0,1) lifetime 1
        sym(n, [(0, 2)]),  # t6: (0,2) forms, still open at the end
        sym(n, [(0, 2)]),  # t7
    ]
    tr = m.LinkTracker(n)
    formed, pruned = [], []
    for _t, A in enumerate(seq):
        f, p = tr.update(A)
        formed.append(f)
        pruned.append(p)
    assert formed[1] == [(0, 1)] and formed[2] == [(1, 2)] and formed[4] == [(0, 1)] and formed[6] == [(0, 2)]
    assert pruned[3] == [(0, 1)] and sorted(pruned[5]) == [(0, 1), (1, 2)]
    assert tr.formations == 4 and tr.prunings == 3
    assert tr.n_ticks == 8 and tr.end == 8
    ev = tr.events()
    assert [(e.i, e.j, e.formed, e.pruned) for e in ev] == [
        (0, 1, 1, 3),
        (0, 1, 4, 5),
        (1, 2, 2, 5),
        (0, 2, 6, None),
    ]
    life, cens = tr.lifetimes()
    assert life.tolist() == [2, 1, 3, 2]  # the open one censored at T - birth = 8 - 6
    assert cens.tolist() == [False, False, False, True]
    assert tr.median_lifetime() == 2.0
    assert tr.core_periphery() == (0, 4)  # threshold T//2 = 4
    assert tr.core_periphery(threshold=2) == (3, 1)


def test_link_tracker_one_way_link_counts_as_undirected_link_and_directed_mode_splits():
    A = np.zeros((2, 2), dtype=int)
    A[1, 0] = 1
    tr = m.LinkTracker(2)
    assert tr.update(A, tick=10) == ([(0, 1)], [])
    trd = m.LinkTracker(2, directed=True)
    assert trd.update(A, tick=10) == ([(1, 0)], [])
    B = np.ones((2, 2)) - np.eye(2)
    assert trd.update(B, tick=11) == ([(0, 1)], [])
    assert tr.update(B, tick=11) == ([], [])  # still the same undirected link
    assert tr.n_ticks == 2 and tr.lifetimes()[0].tolist() == [2]


def test_link_tracker_ticks_must_increase_and_shape_is_checked():
    tr = m.LinkTracker(3)
    tr.update(np.zeros((3, 3)), tick=5)
    with pytest.raises(ValueError, match="tick"):
        tr.update(np.zeros((3, 3)), tick=5)
    with pytest.raises(ValueError, match="A"):
        tr.update(np.zeros((4, 4)), tick=6)


def test_link_tracker_empty_median_is_nan():
    tr = m.LinkTracker(3)
    tr.update(np.zeros((3, 3)))
    assert math.isnan(tr.median_lifetime())
    assert tr.core_periphery() == (0, 0)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.lists(st.booleans(), min_size=6, max_size=6), min_size=1, max_size=12))
def test_link_tracker_open_events_equal_current_links(rows):
    # Each tick's upper-triangle of a 4-agent system (6 pairs) as a list of booleans.
    tr = m.LinkTracker(4)
    iu = np.triu_indices(4, k=1)
    for bits in rows:
        A = np.zeros((4, 4), dtype=int)
        A[iu] = bits
        tr.update(A + A.T)
    _, cens = tr.lifetimes()
    assert tr.formations - tr.prunings == int(cens.sum()) == m.undirected_link_count(A + A.T)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.lists(st.booleans(), min_size=6, max_size=6), st.integers(1, 4)), min_size=1,
                max_size=10))
def test_link_tracker_on_repeated_matrices_equals_it_fed_each_afresh(runs):
    """A matrix fed again unchanged (most ticks of a converged run) takes a shortcut; the events, lifetimes and
    counts equal those of a tracker that reads every matrix afresh (each repeat as another dtype, which the shortcut
    does not take)."""
    iu = np.triu_indices(4, k=1)
    repeated, afresh = m.LinkTracker(4), m.LinkTracker(4)
    for bits, times in runs:
        A = np.zeros((4, 4), dtype=int)
        A[iu] = bits
        A = A + A.T
        for k in range(times):
            repeated.update(A)
            afresh.update(A.astype(np.int64 if k % 2 == 0 else np.int32))
    assert repeated.n_ticks == afresh.n_ticks and repeated.end == afresh.end
    assert (repeated.formations, repeated.prunings) == (afresh.formations, afresh.prunings)
    for a, b in zip(repeated.lifetimes(), afresh.lifetimes()):
        assert np.array_equal(a, b)
    assert repeated.core_periphery() == afresh.core_periphery()


# ---------------------------------------------------------------------------------------------------- W by block


def test_mean_w_by_block_excludes_diagonal_and_splits_directions():
    # agents: 0 AGV, 1 AGV, 2 picker, 3 picker
    W = np.array(
        [
            [9.0, 0.2, 0.5, 0.1],
            [0.4, 9.0, 0.3, 0.3],
            [0.7, 0.1, 9.0, 0.6],
            [0.1, 0.1, 0.2, 9.0],
        ]
    )
    b = m.mean_w_by_block(W, [True, True, False, False])
    assert b.agv_agv == pytest.approx((0.2 + 0.4) / 2)
    assert b.picker_picker == pytest.approx((0.6 + 0.2) / 2)
    assert b.agv_to_picker == pytest.approx((0.5 + 0.1 + 0.3 + 0.3) / 4)
    assert b.picker_to_agv == pytest.approx((0.7 + 0.1 + 0.1 + 0.1) / 4)
    assert b.agv_picker == pytest.approx((0.5 + 0.1 + 0.3 + 0.3 + 0.7 + 0.1 + 0.1 + 0.1) / 8)


def test_mean_w_by_block_single_agv_block_is_nan():
    b = m.mean_w_by_block(np.ones((3, 3)), [True, False, False])
    assert math.isnan(b.agv_agv)
    assert b.picker_picker == 1.0
    with pytest.raises(ValueError, match="is_agv"):
        m.mean_w_by_block(np.ones((3, 3)), [True, False])


# ------------------------------------------------------------------------------------------- algebraic connectivity


@pytest.mark.parametrize("n", [2, 3, 5, 8])
def test_path_graph_lambda2(n):
    A = sym(n, [(i, i + 1) for i in range(n - 1)])
    assert m.algebraic_connectivity(A) == pytest.approx(2 * (1 - math.cos(math.pi / n)))


@pytest.mark.parametrize("n", [2, 4, 8, 18])
def test_complete_graph_lambda2_both_definitions(n):
    K = np.ones((n, n), dtype=int) - np.eye(n, dtype=int)
    assert m.algebraic_connectivity(K) == pytest.approx(n)
    # Normalised Laplacian of K_n has eigenvalues 0 and n/(n-1): K_8 gives 8/7 (the reference's Tiny at t=100).
    assert m.reference_normalized_fiedler(K) == pytest.approx(n / (n - 1))


def test_weighted_lambda2_uses_mean_of_both_directions_on_links_only():
    A = sym(2, [(0, 1)])
    W = np.array([[0.0, 0.2], [0.6, 0.0]])
    assert m.algebraic_connectivity(A, W) == pytest.approx(2 * 0.4)  # L = [[w,-w],[-w,w]] → {0, 2w}
    # Weights off the links are ignored.
    A3 = sym(3, [(0, 1), (1, 2)])
    W3 = np.full((3, 3), 0.5)
    assert m.algebraic_connectivity(A3, W3) == pytest.approx(0.5 * 1.0)  # path P3 eigenvalues 0,1,3 scaled


def test_isolated_agent_textbook_zero_but_reference_one():
    A = sym(3, [(0, 1)])
    assert m.algebraic_connectivity(A) == 0.0
    # Edge block gives 0 and 2; the isolated agent contributes 1 (not 0) in the reference's normalised Laplacian.
    assert m.reference_normalized_fiedler(A) == pytest.approx(1.0)
    assert m.reference_normalized_fiedler(np.zeros((4, 4))) == 0.0
    assert m.algebraic_connectivity(np.zeros((1, 1))) == 0.0


def test_reference_fiedler_symmetrises_one_way_links():
    A = np.zeros((3, 3))
    A[0, 1] = A[1, 2] = 1
    assert m.reference_normalized_fiedler(A) == pytest.approx(1.0)  # P3 normalised: 0, 1, 2
    assert m.algebraic_connectivity(A) == pytest.approx(1.0)


@st.composite
def random_graph(draw):
    n = draw(st.integers(2, 8))
    bits = draw(st.lists(st.booleans(), min_size=n * (n - 1) // 2, max_size=n * (n - 1) // 2))
    A = np.zeros((n, n), dtype=int)
    A[np.triu_indices(n, k=1)] = bits
    return A + A.T


@settings(max_examples=80, deadline=None)
@given(random_graph())
def test_lambda2_nonnegative_and_positive_iff_connected(A):
    lam = m.algebraic_connectivity(A)
    assert lam >= 0.0
    assert (lam > 1e-9) == m.is_connected(A)
    ref = m.reference_normalized_fiedler(A)
    assert -1e-9 <= ref <= 2.0 + 1e-9


# -------------------------------------------------------------------------------------------------------- Spearman


def test_mean_manhattan_distance():
    pos = np.array(
        [
            [[0, 0], [3, 4], [1, 1]],
            [[0, 0], [1, 0], [1, 1]],
        ]
    )
    D = m.mean_manhattan_distance(pos)
    assert D[0, 1] == pytest.approx((7 + 1) / 2)
    assert D[1, 0] == D[0, 1]
    assert D[0, 2] == pytest.approx(2.0)
    assert D[1, 2] == pytest.approx((5 + 1) / 2)
    assert np.all(np.diag(D) == 0)
    with pytest.raises(ValueError, match="positions"):
        m.mean_manhattan_distance(np.zeros((3, 2)))


def _agv_picker_case():
    # agents 0, 1 AGVs; 2, 3 pickers. AGV→picker pairs (0,2), (0,3), (1,2), (1,3) at distances 1, 2, 3, 4.
    D = np.zeros((4, 4))
    for (i, j), d in zip([(0, 2), (0, 3), (1, 2), (1, 3)], [1, 2, 3, 4]):
        D[i, j] = D[j, i] = d
    W = np.zeros((4, 4))
    for (i, j), w in zip([(0, 2), (0, 3), (1, 2), (1, 3)], [0.4, 0.3, 0.2, 0.1]):
        W[i, j] = w
        W[j, i] = 0.5 - w  # reverse direction rises with distance
    return W, D, [True, True, False, False]


def test_spearman_agv_to_picker_perfect_negative_and_permutation_p():
    W, D, is_agv = _agv_picker_case()
    r = m.spearman_agv_picker(W, D, is_agv, n_permutations=20000, rng=1)
    assert r.n_pairs == 4
    assert r.rho == pytest.approx(-1.0)
    # 4 pairs: 2 of the 24 orderings give |ρ| = 1, so the two-sided permutation p is 1/12.
    assert r.p_permutation == pytest.approx(1 / 12, abs=0.01)
    again = m.spearman_agv_picker(W, D, is_agv, n_permutations=20000, rng=1)
    assert again.p_permutation == r.p_permutation  # seeded
    rev = m.spearman_agv_picker(W, D, is_agv, n_permutations=0, direction="picker_to_agv")
    assert rev.rho == pytest.approx(1.0) and rev.p_permutation is None
    both = m.spearman_agv_picker(W, D, is_agv, n_permutations=0, direction="both")
    assert both.n_pairs == 8
    with pytest.raises(ValueError, match="direction"):
        m.spearman_agv_picker(W, D, is_agv, direction="sideways")


def test_spearman_known_value_with_ties():
    # x = 1..5, y = [5, 6, 7, 8, 7]: ranks of y = [1, 2, 3.5, 5, 3.5]; ρ = 8 / sqrt(10 · 9.5).
    n = 6  # agent 0 is the only AGV, 1..5 are pickers → 5 AGV→picker pairs
    W = np.zeros((n, n))
    D = np.zeros((n, n))
    for k, (d, w) in enumerate(zip([1, 2, 3, 4, 5], [5, 6, 7, 8, 7]), start=1):
        D[0, k] = D[k, 0] = d
        W[0, k] = w
    r = m.spearman_agv_picker(W, D, [True] + [False] * 5, n_permutations=0)
    assert r.rho == pytest.approx(8 / math.sqrt(95))


def test_spearman_constant_w_is_nan():
    W, D, is_agv = _agv_picker_case()
    r = m.spearman_agv_picker(np.zeros_like(W), D, is_agv, n_permutations=100)
    assert math.isnan(r.rho) and math.isnan(r.p_permutation)


def test_spearman_reference_pairs_uses_upper_triangle_of_all_pairs():
    # 3 agents: pairs (0,1), (0,2), (1,2) at distance 1, 2, 3; upper W 0.3, 0.1, 0.2 → ranks 3,1,2:
    # ρ = 1 − 6·Σd²/(n(n²−1)) = 1 − 6·6/24 = −0.5.
    D = np.array([[0, 1, 2], [1, 0, 3], [2, 3, 0]], dtype=float)
    W = np.array([[0, 0.3, 0.1], [9, 0, 0.2], [9, 9, 0]])  # lower triangle must be ignored
    r = m.spearman_reference_pairs(W, D)
    assert r.n_pairs == 3
    assert r.rho == pytest.approx(-0.5)


def test_spearman_reference_pairs_count_at_medium():
    rng = np.random.default_rng(3)
    W = rng.random((18, 18))
    D = rng.random((18, 18))
    D = D + D.T
    r = m.spearman_reference_pairs(W, D, n_permutations=200, rng=0)
    assert r.n_pairs == 153  # 18·17/2 unordered pairs, every role combination
    assert 0 < r.p_permutation <= 1


# ------------------------------------------------------------------------------------------- rates and recovery


def test_rolling_sum_and_rate():
    d = [1, 0, 2, 0, 0, 3]
    assert m.rolling_sum(d, 3).tolist() == [1, 1, 3, 2, 2, 3]
    assert m.rolling_rate(d, 2).tolist() == [0.5, 0.5, 1.0, 1.0, 0.0, 1.5]
    with pytest.raises(ValueError, match="window"):
        m.rolling_sum(d, 0)


def test_phase_deliveries():
    d = np.arange(10)
    assert m.phase_deliveries(d, [0, 4, 7]).tolist() == [0 + 1 + 2 + 3, 4 + 5 + 6, 7 + 8 + 9]
    with pytest.raises(ValueError, match="boundaries"):
        m.phase_deliveries(d, [1, 4])


def _alternating(n):
    return np.array([1.0 if t % 2 == 0 else 0.0 for t in range(n)])


def test_recovery_time_known_answer():
    # Phases of 40 steps, window 10. Phases 0 and 1 deliver every other step (rate 0.5).
    # Phase 2: nothing for 20 steps, then one delivery per step. Baseline(2) = phase 0 = 0.5, level 0.45.
    # At t=80 the window 71..80 holds 4 deliveries (0.4 < 0.45); at t = 100 + m it holds m + 1 ⇒ first ≥ 4.5 at m = 4.
    d = np.concatenate([_alternating(80), np.zeros(20), np.ones(20), _alternating(40)])
    rec = m.shift_recoveries(d, [0, 40, 80, 120], window=10)
    assert [r.phase for r in rec] == [2, 3]
    r2 = rec[0]
    assert r2.baseline_phase == 0 and r2.baseline == 0.5 and r2.threshold == pytest.approx(0.45)
    assert (r2.time, r2.censored) == (24, False)
    # Phase 3 starts right after a full-rate stretch: never below threshold, so recovery 0.
    r3 = rec[1]
    assert r3.baseline_phase == 1 and (r3.time, r3.censored) == (0, False)


def test_recovery_time_censored_at_phase_length():
    d = np.concatenate([_alternating(80), np.zeros(80)])
    rec = m.shift_recoveries(d, [0, 40, 80, 120], window=10)
    assert [(r.phase, r.time, r.censored) for r in rec] == [(2, 40, True), (3, 40, True)]


def test_recovery_six_phases_default_window_reports_r3_to_r6():
    d = np.zeros(2400)
    d[::8] = 1  # steady 0.125 deliveries/step everywhere...
    d[1150:1300] = 0  # ...except an outage from 50 steps before phase 4 (0-based 3) to 100 steps into it
    rec = m.shift_recoveries(d, [0, 400, 800, 1200, 1600, 2000])
    assert [r.phase for r in rec] == [2, 3, 4, 5]
    by = {r.phase: r for r in rec}
    assert by[2].time == 0 and by[4].time == 0 and by[5].time == 0
    # After the outage deliveries resume at 1304, 1312, …; the 50-step window needs 0.9·0.125·50 = 5.625 → 6 of
    # them: the 6th is at 1344 (window 1295..1344), i.e. 144 steps after the boundary.
    assert (by[3].time, by[3].censored) == (144, False)
    assert by[3].baseline == pytest.approx(0.125)


def test_recovery_time_helper():
    rate = np.array([0.0, 0.1, 0.5, 0.2, 0.9])
    assert m.recovery_time(rate, 1, 5, 0.5) == (1, False)
    assert m.recovery_time(rate, 0, 2, 0.5) == (2, True)
    with pytest.raises(ValueError, match="start/stop"):
        m.recovery_time(rate, 3, 2, 0.5)


# ------------------------------------------------------------------------------------------------------ statistics


def test_mean_std_population_as_reference():
    s = m.mean_std([56, 57, 56, 52, 59])
    assert s.mean == 56.0 and s.n == 5
    assert s.std == pytest.approx(math.sqrt((0 + 1 + 0 + 16 + 9) / 5))
    assert str(s) == "56.0 ± 2.3"
    assert m.mean_std([1, 3], ddof=1).std == pytest.approx(math.sqrt(2))
    with pytest.raises(ValueError, match="values"):
        m.mean_std([])


def test_nan_mean_and_std_leave_nans_out_and_are_nan_without_a_warning_when_all_are():
    import warnings

    values = [1.0, float("nan"), 3.0, 8.0]
    assert m.nan_mean(values) == pytest.approx(4.0) and m.nan_std(values) == pytest.approx(np.std([1.0, 3.0, 8.0]))
    assert m.nan_mean(iter(values)) == pytest.approx(4.0)  # any iterable, as the summaries pass generators
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's nanmean and nanstd warn here ("Mean of empty slice")
        assert math.isnan(m.nan_mean([float("nan")] * 3)) and math.isnan(m.nan_std([float("nan")] * 3))
        assert math.isnan(m.nan_mean([])) and math.isnan(m.nan_std([]))


def test_welch_p_hand_computed():
    # a = [1,2,3], b = [4,5,6]: t = −3/sqrt(2/3), Welch df = 4 ⇒ p = 2·(1 − F_t4(3.674)) ≈ 0.02131.
    assert m.welch_p([1, 2, 3], [4, 5, 6]) == pytest.approx(0.021311, abs=2e-6)
    assert math.isnan(m.welch_p([1, 1], [1, 1]))
    assert math.isnan(m.welch_p([1], [2, 3]))


def test_reference_fiedler_has_scipys_bits():
    # the record calls LAPACK's syevr itself, without scipy's eigvalsh around it: same driver, range and workspace, so
    # the same bits as the reference's scipy call, on link graphs of every density and on weighted matrices alike
    from scipy import linalg

    rng = np.random.default_rng(11)
    for n in (2, 3, 7, 18, 24, 40):
        for density in (0.05, 0.2, 0.6, 1.0):
            A = (rng.random((n, n)) < density).astype(float)
            A = np.maximum(A, A.T)
            d = A.sum(axis=1)
            dis = 1.0 / np.sqrt(np.maximum(d, 1e-9))
            lap = np.eye(n) - dis[:, None] * A * dis[None, :]
            weighted = rng.random((n, n))
            for sym in (lap, weighted + weighted.T):
                want = linalg.eigvalsh(sym, subset_by_index=[0, 1])
                assert m._lowest_two(sym).tobytes() == want.tobytes()
            if d.sum():
                assert m.reference_normalized_fiedler(A) == float(linalg.eigvalsh(lap, subset_by_index=[0, 1])[1])
    bad = np.eye(3)
    bad[0, 1] = bad[1, 0] = np.nan
    with np.errstate(invalid="ignore"):  # not finite: 0, as with scipy's check
        assert m.reference_normalized_fiedler(np.where(np.isnan(bad), np.inf, 1.0)) == 0.0
