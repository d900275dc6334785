"""The ``reference`` preset against the published code's behaviour.

Reference numbers come from our run of the published code
(Cyber-physical-Systems-Lab/morph_v2@5f21ee4 on TA-RWARE@6109c33 with the rotation-aware A*). With the
reference's switches (sequential dispatch, one shared stream) our trajectories reproduce those runs.
"""

import numpy as np
import pytest

from morph_sim.lab.runner import REFERENCE_SEEDS, EpisodeSpec, run_episode

# the reference code's per-seed final deliveries (seeds 42, 7, 123, 999, 2024), mean ± population std, mean links
REFERENCE_82 = {
    ("tiny", "morph"): ([56, 57, 56, 52, 59], 56.0, 2.3, 27.1),
    ("small", "morph"): ([68, 71, 66, 65, 69], 67.8, 2.1, 38.6),
    ("medium", "morph"): ([75, 89, 85, 93, 89], 86.2, 6.1, 40.0),
    ("large", "morph"): ([101, 103, 105, 103, 101], 102.6, 1.5, 56.5),
    ("tiny", "full"): ([57, 48, 57, 61, 63], 57.2, 5.2, 28.0),
    ("small", "full"): ([67, 68, 67, 37, 65], 60.8, 11.9, 66.0),
    ("medium", "full"): ([69, 88, 90, 85, 89], 84.2, 7.8, 153.0),
    ("large", "full"): ([101, 99, 104, 98, 97], 99.8, 2.5, 276.0),
    ("tiny", "tsg"): ([54, 57, 49, 59, 54], 54.6, 3.4, 2.5),
    ("small", "tsg"): (None, 66.0, 2.1, 3.8),
    ("medium", "tsg"): ([87, 92, 90, 91, 87], 89.4, 2.1, 5.6),
    ("large", "tsg"): (None, 102.0, 2.1, 7.8),
    ("tiny", "proximity"): ([58, 49, 56, 58, 57], 55.6, 3.4, 22.5),
    ("small", "proximity"): ([68, 69, 72, 71, 72], 70.4, 1.6, 37.9),
    ("medium", "proximity"): ([96, 92, 96, 94, 100], 95.6, 2.7, 30.0),
    ("large", "proximity"): ([106, 112, 108, 108, 106], 108.0, 2.2, 60.2),
}
RADII = {"tiny": 10, "small": 10, "medium": 6, "large": 8}  # what the calibration chose


def _ref(scale, condition, seed, steps=800, **kw):
    return EpisodeSpec(scale=scale, condition=condition, seed=seed, steps=steps, preset="reference",
                       dispatch="sequential", shared_stream=True,
                       radius=RADII[scale] if condition == "proximity" else None, **kw)


#: episodes already run in this module, by spec: several tests read the same reference episode (seed 42 of MORPH at
#: Tiny and Medium, TSG at Tiny), and an episode is deterministic per spec, so each runs once. (spec -> the result
#: of run_episode, and of :func:`_trace` where a test traced it: its hook only reads the team.)
_RESULTS: dict[str, object] = {}
_TRACES: dict[str, tuple] = {}


def _run(spec):
    key = spec.model_dump_json()
    if key in _TRACES:
        return _TRACES[key][0]
    if key not in _RESULTS:
        _RESULTS[key] = run_episode(spec)
    return _RESULTS[key]


def _trace(spec):
    """Run with a hook recording, per update, the links formed and h."""
    key = spec.model_dump_json()
    if key not in _TRACES:
        _TRACES[key] = _trace_once(spec)
    return _TRACES[key]


def _trace_once(spec):
    formed, h = [], []

    def hook(obs, team):
        if obs.has_previous:
            s = team.state
            if s.t[0] % s.params.k == 0:
                formed.append(int(s.formed[0]))
            h.append(team.h().copy())

    result = run_episode(spec, trace_hook=hook)
    return result, formed, np.array(h)


def test_medium_seed42_mechanics():
    result, formed, h = _trace(_ref("medium", "morph", 42))
    s = result.summary
    assert s["deliveries"] == 75  # the reference's per-seed value, exactly
    assert s["median_lifetime"] == 21
    assert len(formed) == 266 and set(formed) == {3}  # 3 links at every structural step
    assert np.all(h.max(axis=0) == 1.0) and h[-1].min() > 0.99  # every h_i reaches 1 and stays there
    assert s["mean_p_respond"] == pytest.approx(0.271, abs=0.01)
    assert s["dispatch_decisions"] == 574
    assert s["w_asymmetry"] == 0.0
    assert s["link_events"] == 754


def test_tiny_seed42_mechanics():
    result, formed, h = _trace(_ref("tiny", "morph", 42))
    s = result.summary
    assert s["deliveries"] == 56
    assert np.all(h.min(axis=0) == 0.0) and h[-1].max() < 0.01  # h saturates at 0 at Tiny
    assert s["mean_p_respond"] == pytest.approx(0.326, abs=0.01)
    assert s["dispatch_decisions"] == 340
    assert np.bincount(formed, minlength=4).tolist() == [2, 47, 108, 109]  # (limited by free pairs)


# Tiny in the default suite, the other scales (fifteen more 800-step episodes) with -m slow; seed 42 at Medium is
# compared step by step by default (test_per_step_traces_equal_the_reference_code).
@pytest.mark.parametrize("scale,links", [("tiny", 27.1), pytest.param("small", 38.6, marks=pytest.mark.slow),
                                         pytest.param("medium", 40.0, marks=pytest.mark.slow),
                                         pytest.param("large", 56.5, marks=pytest.mark.slow)])
def test_morph_link_counts_and_deliveries_over_the_reference_seeds(scale, links):
    got = [_run(_ref(scale, "morph", seed)).summary for seed in REFERENCE_SEEDS]
    assert np.mean([g["mean_links"] for g in got]) == pytest.approx(links, abs=0.5)  # ≈ 27 / 38-39 / 40 / 56
    assert [g["deliveries"] for g in got] == REFERENCE_82[(scale, "morph")][0]


@pytest.mark.parametrize("scale", ["tiny", pytest.param("medium", marks=pytest.mark.slow)])  # Medium: -m slow
def test_tsg_equals_constant_quarter_gate(scale):
    for seed in (42, 7):
        for shared, dispatch in ((True, "sequential"), (False, "concurrent")):
            kw = dict(scale=scale, seed=seed, steps=800, dispatch=dispatch, shared_stream=shared)
            tsg = _run(EpisodeSpec(condition="tsg", **kw))
            const = run_episode(EpisodeSpec(condition="constant", **kw))
            np.testing.assert_array_equal(tsg.ticks["deliveries_total"], const.ticks["deliveries_total"])
            assert tsg.summary["dispatch_decisions"] == const.summary["dispatch_decisions"]
        if seed == 42 and scale == "tiny":
            assert tsg.summary["deliveries"] == 54 or not shared


@pytest.mark.parametrize("scale", ["tiny", "small", "medium", "large"])
def test_no_coordination_delivers_nothing(scale):
    for shared in (True, False):
        s = run_episode(EpisodeSpec(scale=scale, condition="none", seed=42, steps=400, shared_stream=shared))
        assert s.summary["deliveries"] == 0 and s.summary["mean_links"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("scale", ["tiny", "small", "medium", "large"])
@pytest.mark.parametrize("condition", ["morph", "full", "tsg", "proximity"])
def test_shared_stream_means_within_one_reference_std(scale, condition):
    values, mean, std, links = REFERENCE_82[(scale, condition)]
    got = [run_episode(_ref(scale, condition, seed)).summary for seed in REFERENCE_SEEDS]
    d = [g["deliveries"] for g in got]
    assert abs(np.mean(d) - mean) <= std
    if values is not None:
        assert d == values  # in fact bit-identical to the reference run
    assert np.mean([g["mean_links"] for g in got]) == pytest.approx(links, abs=1.0)


def test_per_step_traces_equal_the_reference_code():
    """Tick by tick, cumulative deliveries, link counts and mean W equal the published code's (seed 42)."""
    import json
    from pathlib import Path

    data = json.loads((Path(__file__).parent / "data" / "morph_reference_traces_seed42.json").read_text())
    assert len(data["episodes"]) == 4
    for key, trace in data["episodes"].items():
        scale, cond = key.split("_", 1)
        res = _run(_ref(scale, {"morph_v2": "morph", "tsg": "tsg"}[cond], 42))
        np.testing.assert_array_equal(res.ticks["deliveries_total"], trace["deliveries"])
        np.testing.assert_array_equal(res.ticks["links"], trace["links"])
        if cond == "morph_v2":
            np.testing.assert_allclose(res.ticks["mean_w_links"], trace["w_mean"], rtol=0, atol=1e-12)
