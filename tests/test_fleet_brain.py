"""One brain for a fleet whose robots hold views of their own equals a brain per robot, tick for tick.

Under a network profile or faults on the fleet broadcast each robot learns from the view it holds (late, or a lost one
never). The lab steps such a fleet in one brain (``CoordinationPolicy.fleet_brains``: every robot's state in one
array) where the policy has one; these tests hold it to the brain-per-robot path on every shipped policy, the
reference preset's ablations, the paper preset, fleet faults (views lost and late, so the robots' update counts and
structural steps fall out of step) and every network profile. The full product of policies × profiles runs with
``-m slow``.
"""

from __future__ import annotations

import numpy as np
import pytest

from morph_sim.lab.network import fleet_faults
from morph_sim.lab.runner import EpisodeSpec, run_episode
from schemas.faults import FaultSpec, Latency, Loss
from services.faults.network import profile_names
from services.policies.presets import ABLATIONS

POLICIES = ("morph", "tsg", "proximity", "full", "full-broadcast", "constant", "none")
PROFILES = tuple(profile_names())
# views lost (a fifth of them) and late (up to about two ticks): robots fall out of step with each other
FLEET_FAULTS = tuple(fleet_faults(FaultSpec(id="views", seed=7, loss=Loss(percent=20),
                                            latency=Latency(delay=0.8, jitter=0.8, distribution="uniform"))))


def _both(**fields):
    """(fleet brain, brain per robot) results of one episode."""
    fleet = run_episode(EpisodeSpec(fleet_brain=True, **fields))
    robots = run_episode(EpisodeSpec(fleet_brain=False, **fields))
    return fleet, robots


def _assert_same(fleet, robots) -> None:
    assert fleet.ticks.keys() == robots.ticks.keys()
    for name in fleet.ticks:
        np.testing.assert_array_equal(np.asarray(fleet.ticks[name]), np.asarray(robots.ticks[name]), err_msg=name)
    ignore = {"brains", "wall_s", "cpu_s"}
    a = {k: v for k, v in fleet.summary.items() if k not in ignore}
    b = {k: v for k, v in robots.summary.items() if k not in ignore}
    assert repr(a) == repr(b)
    for name in ("final_weights", "final_links"):
        a, b = getattr(fleet, name), getattr(robots, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_array_equal(a, b, err_msg=name)


def _policy_fields(policy: str) -> dict:
    if policy == "proximity":
        return {"condition": "proximity", "radius": 4}
    if policy in ("full", "full-broadcast", "constant"):
        return {"condition": policy, "policy_name": policy}
    return {"condition": policy}


@pytest.mark.parametrize("policy", POLICIES)
def test_every_shipped_policy_learns_the_same_in_one_fleet_brain_under_fleet_faults(policy):
    fleet, robots = _both(scale="tiny", seed=4, steps=100, faults=FLEET_FAULTS, **_policy_fields(policy))
    assert fleet.summary["brains"] == "fleet" and robots.summary["brains"] == "per-robot"
    _assert_same(fleet, robots)
    if policy not in ("none",):
        assert fleet.summary["deliveries"] > 0


@pytest.mark.parametrize("ablation", ABLATIONS)
def test_each_reference_ablation_learns_the_same_in_one_fleet_brain(ablation):
    fleet, robots = _both(scale="tiny", seed=2, steps=100, faults=FLEET_FAULTS, condition=ablation)
    assert fleet.summary["brains"] == "fleet"
    _assert_same(fleet, robots)


@pytest.mark.parametrize("profile", PROFILES)
def test_morph_learns_the_same_in_one_fleet_brain_under_each_network_profile(profile):
    fleet, robots = _both(scale="tiny", seed=3, steps=100, network=profile, condition="morph")
    _assert_same(fleet, robots)


def test_the_robots_fall_out_of_step_so_the_test_above_means_something():
    """Under the fleet faults the robots' replicas have taken different numbers of updates by the end: the fleet
    brain has stepped robots with different update counts, d̂ and structural phases in one array."""
    seen = {}

    def hook(obs, brains):
        seen["t"] = brains.state.t.copy()
        seen["dhat"] = brains.state.dhat.copy()

    run_episode(EpisodeSpec(scale="tiny", condition="morph", seed=4, steps=100, faults=FLEET_FAULTS), trace_hook=hook)
    assert len(set(seen["t"].tolist())) > 1 and len(set(seen["dhat"].tolist())) > 1
    assert len({t % 3 for t in seen["t"].tolist()}) > 1  # structural steps at different ticks


@pytest.mark.parametrize("views", ("faults",) + PROFILES)
def test_the_paper_preset_learns_the_same_in_one_fleet_brain(views):
    """The paper preset's fleet brain keeps a task history (with t, d̂, baseline, η) per robot beside its row; under
    the fleet faults and each network profile it steps robots whose histories, fill and structural phases differ."""
    where = {"faults": FLEET_FAULTS} if views == "faults" else {"network": views}
    seen = {"filled": 1, "formed": 0}

    def hook(obs, brains):
        seen["filled"] = max(seen["filled"], len(set(brains.state.filled.tolist())))  # windows filled unequally
        seen["t"] = set(brains.state.t.tolist())
        seen["formed"] += int(brains.state.formed.sum())

    fields = {"scale": "tiny", "condition": "morph", "preset": "paper", "seed": 4, "steps": 100, **where}
    fleet = run_episode(EpisodeSpec(fleet_brain=True, **fields), trace_hook=hook)
    robots = run_episode(EpisodeSpec(fleet_brain=False, **fields))
    assert fleet.summary["brains"] == "fleet" and robots.summary["brains"] == "per-robot"
    _assert_same(fleet, robots)
    assert seen["formed"] > 0 and fleet.summary["deliveries"] > 0
    if views != "lan":  # on the LAN every view arrives within its tick: the robots stay in step
        assert len(seen["t"]) > 1 and len({t % 3 for t in seen["t"]}) > 1 and seen["filled"] > 1


def test_a_team_run_says_it_ran_one_team_brain():
    assert run_episode(EpisodeSpec(scale="tiny", condition="morph", seed=1, steps=20)).summary["brains"] == "team"


@pytest.mark.slow
@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("policy", POLICIES)
def test_every_policy_under_every_profile_at_medium(policy, profile):
    fleet, robots = _both(scale="medium", seed=11, steps=300, network=profile, **_policy_fields(policy))
    _assert_same(fleet, robots)


def test_bench_brains_prints_both_ways_and_the_ratio_to_proximity(capsys):
    from morph_sim.cli import main

    # short episodes: what is checked is the table (both ways, the ratio to the seconds shown, the same episode
    # both ways), not how long an episode takes
    code = main(["bench", "brains", "--scale", "tiny", "--steps", "20", "--seeds", "1,2", "--profiles", "congested",
                 "--policies", "morph,morph_paper,proximity"])
    out = capsys.readouterr().out.splitlines()
    assert code == 0, out
    rows = [line.split() for line in out if line.startswith("congested")]
    assert [r[1] for r in rows] == ["morph", "morph_paper", "proximity"]
    for r in rows:
        fleet_s, robot_s, speedup = float(r[2]), float(r[3]), float(r[4].rstrip("×"))
        # the table rounds seconds to 1 ms and the speed-up to 0.01
        assert fleet_s > 0 and robot_s > 0
        assert (robot_s - 5e-4) / (fleet_s + 5e-4) - 0.005 <= speedup <= (robot_s + 5e-4) / (fleet_s - 5e-4) + 0.005
        assert r[-1] == "yes"  # the same episode both ways
    assert rows[2][5] == "1.00×"  # Proximity against itself
    # numba is a test dependency: the table is the compiled update's
    assert any(line.startswith("MORPH's fleet brain: compiled update (numba ") for line in out), out


def test_bench_brains_refuses_bad_seeds_in_one_line(capsys):
    from morph_sim.cli import main

    assert main(["bench", "brains", "--seeds", "1,x"]) == 2
    assert capsys.readouterr().err.strip() == (
        "morph-sim bench brains: error: seeds: 'x' is not a seed or a range like 1-20")
    assert main(["bench", "brains", "--seeds", "1-100000000"]) == 2  # refused before the range is spelled out
    assert "seeds" in capsys.readouterr().err
    assert main(["bench", "brains", "--steps", "0"]) == 2
    assert capsys.readouterr().err.strip() == (
        "morph-sim bench brains: error: policies, profiles, seeds: at least one each, and steps >= 1")
