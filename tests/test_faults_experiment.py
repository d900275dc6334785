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
    out = run_experiment(tmp_path / "q", quick=True, seeds=(1, 2))
    rows = json.loads((tmp_path / "q" / "faults.json").read_text())["rows"]
    assert (tmp_path / "q" / "faults_tiny.png").stat().st_size > 10_000 and rows == out["rows"]
    md = (tmp_path / "q" / "faults.md").read_text()
    assert "### tiny: faults on the dispatch messages" in md and "| Full-Graph | " in md
    import re

    m, thr = re.match(r"(\d+) comparisons .* Bonferroni threshold for a family-wise 5 %: p < ([0-9.e-]+)", md).groups()
    # 2 policies × 3 fault points; a p is undefined only where both samples have no variance
    assert 1 <= int(m) <= 6 and float(thr) == pytest.approx(0.05 / int(m), rel=0.01)
    by = {(r["condition"], r["kind"], r["level"]): r for r in rows}
    clean, lossy = by[("Full-Graph", "bernoulli", 0.0)], by[("Full-Graph", "bernoulli", 30.0)]
    assert clean["lost_share"] == 0 and lossy["lost_share"] > 0.1 and clean["seeds"] == lossy["seeds"] == 2
    assert lossy["dispatch_delay"] > clean["dispatch_delay"]
    assert lossy["bytes_per_delivery"] > lossy["messages_per_delivery"] > 0
    assert lossy["p_vs_clean"] is None or 0 <= lossy["p_vs_clean"] <= 1


def _cli(argv, capsys):
    """``morph-sim experiment faults`` in this process (the same parser and error handling as the CLI's; the
    interrupt below needs a process of its own): its exit status, stdout and stderr."""
    import subprocess

    from morph_sim.cli import main

    capsys.readouterr()
    try:
        code = main(["experiment", "faults", *argv])
    except SystemExit as exc:  # argparse's errors
        code = exc.code
    out = capsys.readouterr()
    return subprocess.CompletedProcess(argv, code, out.out, out.err)


def test_cli_honours_scales_seeds_steps_targets_and_levels(tmp_path, capsys) -> None:
    """Every flag reaches the grid: the record holds exactly the episodes asked for, at the scales and length asked
    for; the table (a section per scale), the figures (one per scale) and the last line say what ran."""
    # --jobs 1: 32 40-tick episodes cost less than starting worker processes for them (the study's grid runs on the
    # sweep's worker pool, tested in tests/test_sweep.py)
    res = _cli(["--scales", "tiny,small", "--seeds", "3,4", "--steps", "40", "--jobs", "1", "--conditions",
                "tsg,morph", "--targets", "fleet", "--loss-levels", "0,20", "--latency-levels", "2", "--out",
                str(tmp_path), "--run-id", "f"], capsys)
    assert res.returncode == 0, res.stderr
    record = tmp_path / "f"
    eps = json.loads((record / "faults.json").read_text())["episodes"]
    # fault-free + Bernoulli 20 + GE 20 + latency 2 (fleet broadcast), two policies, two seeds, two scales
    assert len(eps) == 32 and {e["scale"] for e in eps} == {"tiny", "small"} and {e["seed"] for e in eps} == {3, 4}
    assert {e["target"] for e in eps} == {"none", "fleet"} and {e["condition"] for e in eps} == {"TSG",
                                                                                               "MORPH (reference)"}
    assert {(e["kind"], e["level"]) for e in eps} == {("none", 0), ("bernoulli", 20), ("bursty", 20), ("latency", 2)}
    assert all(e["view_age_mean"] > 0 for e in eps if e["target"] == "fleet")
    for scale in ("tiny", "small"):
        assert (record / f"faults_{scale}.png").stat().st_size > 10_000
        assert (f"### {scale}: faults on the fleet broadcast (each agent learns and gates from its own view) "
                "(2 seeds)") in res.stdout
    assert not (record / "faults_medium.png").exists()
    assert res.stdout.strip().splitlines()[-1].startswith("faults experiment: 32 episodes run, 0 already in the record")
    assert "32 episodes" in res.stderr and "T = 40" in res.stderr


def test_a_policy_from_outside_enters_the_fault_study_by_the_name_policy_takes(tmp_path, capsys) -> None:
    """`--conditions morph,package.module:Class`: the outside policy runs every cell beside MORPH, under its own
    name, in the record, the table and the figure; an unknown name is one line."""
    outside = "services.policies.coordinators:ConstantPolicy"
    res = _cli(["--scales", "tiny", "--seeds", "1", "--steps", "40", "--conditions", f"morph,{outside}",
                "--targets", "dispatch", "--loss-levels", "0,20", "--latency-levels", "1", "--out", str(tmp_path),
                "--run-id", "o", "--jobs", "1"], capsys)  # 8 short episodes: no pool
    assert res.returncode == 0, res.stderr
    eps = json.loads((tmp_path / "o" / "faults.json").read_text())["episodes"]
    assert {e["condition"] for e in eps} == {"MORPH (reference)", outside}
    assert all(e["deliveries"] > 0 for e in eps if e["condition"] == outside)
    assert f"| {outside} |" in res.stdout and (tmp_path / "o" / "faults_tiny.png").exists()
    bad = _cli(["--quick", "--conditions", "morph,nope.mod:Thing", "--out", str(tmp_path)], capsys)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith(
        "morph-sim experiment: error: conditions: unknown 'nope.mod:Thing'"), bad.stderr


def test_cli_progress_and_resume_after_interrupt_give_the_same_tables(tmp_path, capsys) -> None:
    """Interrupted by Ctrl-C mid-grid: exit 130 and a line saying how to resume; resumed with the same --run-id it
    runs only the missing episodes, and its tables equal those of a grid that ran straight through. (The interrupted
    grid is a process of its own, as a user's terminal starts it; the others run the CLI in this process.)"""
    import os
    import signal
    import subprocess
    import sys
    import time

    from _procs import kill_tree, terminal_signals

    # 30 ticks an episode: the resume needs a grid of episodes to cut (16 of them), not long ones
    argv = ["--quick", "--seeds", "1,2", "--steps", "30", "--jobs", "1", "--out", str(tmp_path)]
    straight = _cli([*argv, "--run-id", "a"], capsys)
    assert straight.returncode == 0 and "faults" in straight.stderr and "16/16" in straight.stderr  # progress
    proc = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "experiment", "faults", *argv, "--run-id", "b"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=terminal_signals)
    try:
        log = tmp_path / "b" / "episodes.jsonl"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not log.exists() or log.read_text().count("\n") < 3):
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        kill_tree(proc)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1].startswith("experiment faults: interrupted with ")
    assert "--run-id b resumes it" in err
    done = log.read_text().count("\n")
    assert 3 <= done < 16
    resumed = _cli([*argv, "--run-id", "b"], capsys)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{16 - done} episodes run, {done} already in the record" in resumed.stdout
    assert (tmp_path / "b" / "faults.md").read_text() == (tmp_path / "a" / "faults.md").read_text()
    assert resumed.stdout.split("faults experiment:")[0] == straight.stdout.split("faults experiment:")[0]
    other = _cli(["--quick", "--seeds", "1", "--out", str(tmp_path), "--run-id", "b"], capsys)  # another grid
    assert other.returncode == 2 and other.stderr.strip().endswith("holds a different faults; give another --run-id "
                                                                   "or --out")


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
def test_full_tiny_grid_within_an_hour(tmp_path) -> None:
    out = run_experiment(tmp_path / "full", jobs=2, steps=400, scales=("tiny",))
    assert out["wall_s"] < 3600
    assert {r["seeds"] for r in out["rows"] if r["level"] > 0} == {10}
