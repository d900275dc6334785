"""Coordination policies behind one interface; per-agent brains own their state and their gate stream."""

import numpy as np
import pytest

from morph_sim.lab.runner import EpisodeSpec, run_episode
from services.policies.coordinators import (
    ConstantPolicy,
    FullPolicy,
    MorphPolicy,
    NonePolicy,
    ProximityPolicy,
    TSGPolicy,
    calibrate_radius,
)
from services.policies.interface import Fleet, agent_rng
from services.policies.loading import make_policy
from services.policies.presets import load_preset
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig


def _observations(scale="tiny", seed=42, ticks=60):
    """Real observations from the controller with every request answered (Full)."""
    cta = CTAController(Warehouse(WarehouseConfig.named(scale, max_steps=10_000)))
    cta.reset(seed)
    out = []
    for _ in range(ticks):
        obs = cta.begin_tick()
        out.append(obs)
        free = obs.free_picker.copy()
        commits = []
        for a in obs.requesters():
            p = obs.nearest_free_picker(int(a), free)
            if p >= 0:
                commits.append((p, int(a)))
                free[p] = False
        cta.commit(commits)
        cta.finish_tick()
    return out


def test_make_policy_names_and_errors():
    assert isinstance(make_policy("full"), FullPolicy)
    assert make_policy("constant", p=0.4).p == 0.4
    assert make_policy("proximity", radius=6).radius == 6
    assert make_policy("morph", preset="paper", ablation="v1").describe()["ablation"] == "v1"
    with pytest.raises(ValueError, match="policy"):
        make_policy("broadcast")
    with pytest.raises(ValueError, match="p:"):
        ConstantPolicy(p=1.5)
    with pytest.raises(ValueError, match="radius"):
        ProximityPolicy(radius=-1)
    with pytest.raises(ValueError, match="ablation"):
        MorphPolicy(preset="reference", ablation="no_hebb")
    with pytest.raises(ValueError, match="preset"):
        MorphPolicy(preset="nonexistent")
    with pytest.raises(ValueError, match="owners"):
        FullPolicy().brains(Fleet(2, 1), [0, 5], 1)


def test_gate_probabilities_of_memoryless_policies():
    fleet = Fleet(5, 3)
    obs = next(o for o in _observations() if len(o.requesters()))
    agv = int(obs.requesters()[0])
    picker = obs.nearest_free_picker(agv)
    full = FullPolicy().brains(fleet, range(8), 1)
    none = NonePolicy().brains(fleet, range(8), 1)
    const = ConstantPolicy(p=0.3).brains(fleet, range(8), 1)
    tsg = TSGPolicy().brains(fleet, range(8), 1)
    prox = ProximityPolicy(radius=1000).brains(fleet, range(8), 1)
    for b in (tsg, prox):
        b.learn(obs)
    assert (full.draws, none.draws, const.draws) == (False, False, True)
    assert full.probability(agv, picker, obs) == 1.0
    assert none.probability(agv, picker, obs) == 0.0
    assert const.probability(agv, picker, obs) == 0.3
    # TSG's entry for a free candidate is always 0: a free picker has no target to share
    assert tsg.probability(agv, picker, obs) == 0.25
    assert prox.probability(agv, picker, obs) == 1.0
    assert full.team_links().sum() == 8 * 7
    np.testing.assert_array_equal(tsg.team_links(), tsg.team_links().T)


def test_agent_streams_are_seeded_and_independent():
    a = agent_rng(42, 3).random(5)
    assert np.array_equal(a, agent_rng(42, 3).random(5))
    assert not np.array_equal(a, agent_rng(42, 4).random(5))
    assert not np.array_equal(a, agent_rng(7, 3).random(5))
    b = ConstantPolicy().brains(Fleet(5, 3), [3], 42)
    assert b.draw(3) == a[0]
    with pytest.raises(ValueError, match="agent"):
        b.draw(2)


@pytest.mark.parametrize("preset", ["reference", "paper"])
def test_one_agent_brain_equals_its_row_in_the_team(preset):
    """An agent holding only its own state learns exactly what the team bank computes for it."""
    spec = EpisodeSpec(scale="tiny", condition="morph", seed=7, steps=150, preset=preset)
    solos = {}
    policy = spec.policy()
    fleet = Fleet(5, 3, "tiny")
    for agent in (0, 6):
        solos[agent] = policy.brains(fleet, [agent], spec.seed)
    checked = []

    def hook(obs, team):
        for agent, solo in solos.items():
            solo.learn(obs)
            np.testing.assert_array_equal(solo.weight_rows()[0], team.weight_rows()[agent])
            np.testing.assert_array_equal(solo.link_rows()[0], team.link_rows()[agent])
        checked.append(obs.t)

    run_episode(spec, trace_hook=hook)
    assert len(checked) == 151


def test_reference_replicas_agree_and_stay_symmetric():
    """Separate replicas (one per agent) stay identical, symmetric, and equal to the shared-storage bank."""
    fleet = Fleet(8, 4, "small")
    separate = MorphPolicy(preset="reference", share_replicas=False).brains(fleet, range(12), 42)
    assert separate.state.W.shape == (12, 12, 12)
    checked = []

    def hook(obs, team):
        separate.learn(obs)
        if obs.t % 50 == 0:
            W, A = separate.state.W, separate.state.A
            assert np.all(W == W[0]) and np.all(A == A[0])
            assert np.array_equal(W[0], W[0].T)
            np.testing.assert_array_equal(separate.team_weights(), team.team_weights())
            np.testing.assert_array_equal(separate.team_links(), team.team_links())
            checked.append(A[0].sum())

    run_episode(EpisodeSpec(scale="small", condition="morph", seed=42, steps=200), trace_hook=hook)
    assert len(checked) == 5 and checked[-1] > 0  # ticks 0, 50, 100, 150, 200 (the final one)


def test_paper_rows_are_directed():
    asym = []

    def hook(obs, team):
        W = team.team_weights()
        asym.append(np.abs(W - W.T).max())

    run_episode(EpisodeSpec(scale="tiny", condition="morph", seed=42, steps=300, preset="paper"), trace_hook=hook)
    assert max(asym) > 0


def test_calibrate_radius_picks_closest_first():
    links = {2: 5.0, 3: 9.0, 4: 12.0, 5: 14.0, 6: 20.0, 8: 26.0, 10: 30.0}
    assert calibrate_radius(13.0, links.__getitem__) == 4  # 12 and 14 tie: the first wins
    assert calibrate_radius(100.0, links.__getitem__) == 10


def test_presets_validate_and_name_bad_fields(tmp_path):
    ref = load_preset("reference")
    assert [ref.params.max_new(n) for n in (8, 12, 18, 24)] == [3, 3, 3, 4]
    assert ref.params.d_exp("medium") == 0.12 and ref.params.d_exp("unknown") == 0.07
    assert ref.resolve("v1").bcm_gain == 0 and not ref.resolve("v1").use_pred_hint
    bad = tmp_path / "bad.toml"
    bad.write_text((
        'name = "x"\nrules = "reference"\n[params]\n' + "\n".join(
            f"{k} = {v!r}".replace("'", '"') for k, v in ref.params.model_dump().items()
            if not isinstance(v, dict)
        ) + "\nexpected_delivery_rate = { tiny = 0.07 }\n"
    ).replace("gamma = 0.98", "gamma = 1.5").replace("True", "true").replace("False", "false"))
    with pytest.raises(ValueError, match="gamma"):
        load_preset(str(bad))
