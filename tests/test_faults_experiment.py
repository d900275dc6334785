"""The degradation study in its reduced CI form: the sweep runs through the lab's one episode loop, is deterministic
per seed, loss and latency cost what the protocol says (late, not lost), and the table, plot and JSON are written."""

from __future__ import annotations

import json

import pytest

from morph_sim.lab.faults_experiment import fault_spec, run_experiment, run_fault_episode


def test_no_fault_point_loses_nothing_and_is_deterministic() -> None:
    a = run_fault_episode("MORPH (reference)", "bernoulli", 0, seed=3, steps=120)
    b = run_fault_episode("MORPH (reference)", "bernoulli", 0, seed=3, steps=120)
    assert a.lost_attempts == 0 and a.attempts > 0 and a.outcomes["late_applied"] == 0
    assert (a.deliveries, a.mean_links, a.dispatch_delay) == (b.deliveries, b.mean_links, b.dispatch_delay)


def test_loss_expires_requests_and_is_reproducible() -> None:
    ep = run_fault_episode("Full-Graph", "bernoulli", 30, seed=1, steps=300)
    # an AGV whose request, the reply or the commitment is lost waits for its timeout: a share of its requests expire
    assert 0.1 < ep.lost_attempts / ep.attempts < 0.8
    again = run_fault_episode("Full-Graph", "bernoulli", 30, seed=1, steps=300)
    assert (again.attempts, again.lost_attempts, again.deliveries) == (ep.attempts, ep.lost_attempts, ep.deliveries)


def test_latency_of_a_tick_delivers_late_instead_of_nothing() -> None:
    """Late, not lost: a latency beyond half a tick delays the commitments, it does not drop them."""
    clean = run_fault_episode("TSG", "bernoulli", 0, seed=1, steps=150)
    ep = run_fault_episode("TSG", "latency", 1.0, seed=1, steps=150)
    assert ep.outcomes["late_applied"] > 0 and ep.deliveries > 0.5 * clean.deliveries
    assert ep.dispatch_delay > clean.dispatch_delay


def test_fleet_broadcast_faults_reach_learning() -> None:
    clean = run_fault_episode("MORPH (reference)", "bernoulli", 0, seed=2, steps=150)
    lossy = run_fault_episode("MORPH (reference)", "bernoulli", 40, seed=2, steps=150, target="fleet")
    assert lossy.outcomes["requests"] != clean.outcomes["requests"] or lossy.mean_links != clean.mean_links


def test_fault_spec_rejects_unknown_kinds() -> None:
    assert fault_spec("bernoulli", 0, 1) is None
    assert fault_spec("bursty", 20, 1).loss.burst_length == 4
    with pytest.raises(ValueError, match="kind"):
        fault_spec("jam", 10, 1)


def test_reduced_experiment_writes_json_and_plot(tmp_path) -> None:
    out = run_experiment(tmp_path, quick=True)
    rows = json.loads((tmp_path / "faults.json").read_text())["rows"]
    assert (tmp_path / "faults_tiny.png").stat().st_size > 10_000 and rows == out["rows"]
    assert "| tiny | dispatch | Full-Graph |" in (tmp_path / "faults.md").read_text()
    by = {(r["condition"], r["kind"], r["level"]): r for r in rows}
    clean, lossy = by[("Full-Graph", "bernoulli", 0.0)], by[("Full-Graph", "bernoulli", 30.0)]
    assert clean["lost_share"] == 0 and lossy["lost_share"] > 0.1
    assert lossy["dispatch_delay"] > clean["dispatch_delay"]


@pytest.mark.parametrize(("condition", "lab_condition", "preset"), [
    ("MORPH (reference)", "morph", "reference"), ("MORPH (paper)", "morph", "paper"), ("TSG", "tsg", "reference")])
def test_zero_fault_point_is_the_lab_episode(condition: str, lab_condition: str, preset: str) -> None:
    """Without faults the experiment's protocol is the lab's protocol, tick for tick."""
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    ours = run_fault_episode(condition, "bernoulli", 0, seed=42, steps=200)
    lab = run_episode(EpisodeSpec(scale="tiny", condition=lab_condition, preset=preset, seed=42, steps=200,
                                  fiedler_every=1000))
    assert ours.deliveries == lab.summary["deliveries"]
    assert ours.attempts == lab.summary["dispatched"] == lab.summary["protocol_requests"]


@pytest.mark.slow
def test_full_experiment_within_ten_minutes(tmp_path) -> None:
    out = run_experiment(tmp_path, jobs=2, steps=400)
    assert out["wall_s"] < 1800
    assert {r["seeds"] for r in out["rows"] if r["level"] > 0} == {10}
