"""``morph-sim experiment network`` in its reduced form (tiny, two seeds, a few steps): every flag reaches the grid,
the tables and a figure per scale are written, the progress bar runs, and a grid cut short resumes from its run
record to the same tables as one that ran straight through."""

from __future__ import annotations

import json
import subprocess

import pytest

from morph_sim.lab.network_study import CONDITIONS, SEEDS, grid_plan, network_tasks, run_study


def _cli(argv, capsys):
    """``morph-sim experiment network`` in this process (the CLI's parser and error handling): its exit status,
    stdout and stderr."""
    from morph_sim.cli import main

    capsys.readouterr()
    try:
        code = main(["experiment", "network", *argv])
    except SystemExit as exc:  # argparse's errors
        code = exc.code
    out = capsys.readouterr()
    return subprocess.CompletedProcess(argv, code, out.out, out.err)


# --jobs 1: twelve 40-tick episodes cost less than starting worker processes for them (the study's grid runs on the
# sweep's worker pool, tested in tests/test_sweep.py)
ARGV = ["--scales", "tiny", "--seeds", "301,302", "--steps", "40", "--profiles", "lan,wifi-legacy-roaming",
        "--conditions", "morph,full,tsg", "--jobs", "1"]


def test_a_policy_from_outside_runs_under_wifi_roaming_by_the_name_policy_takes(tmp_path, capsys) -> None:
    """"How does my allocator do under Wi-Fi roaming?" is one command: the outside policy runs every cell beside
    MORPH, under its name in the record and the tables."""
    outside = "services.policies.coordinators:ConstantPolicy"
    res = _cli(["--scales", "tiny", "--seeds", "301", "--steps", "40", "--profiles", "wifi-legacy-roaming",
                "--conditions", f"morph,{outside}", "--out", str(tmp_path), "--run-id", "o", "--jobs", "1"], capsys)
    assert res.returncode == 0, res.stderr
    eps = json.loads((tmp_path / "o" / "network.json").read_text())["episodes"]
    assert sorted(e["condition"] for e in eps) == sorted(["MORPH (reference)", outside])
    assert all(e["network_handovers"] > 0 for e in eps)
    assert f"| wifi-legacy-roaming | {outside} | " in res.stdout


def test_cli_runs_the_grid_asked_for_with_tables_figure_and_progress(tmp_path, capsys) -> None:
    res = _cli([*ARGV, "--out", str(tmp_path), "--run-id", "n"], capsys)
    assert res.returncode == 0, res.stderr
    record = tmp_path / "n"
    data = json.loads((record / "network.json").read_text())
    eps = data["episodes"]
    assert len(eps) == 12 and {e["seed"] for e in eps} == {301, 302} and {e["steps"] for e in eps} == {40}
    assert {e["profile"] for e in eps} == {"lan", "wifi-legacy-roaming"}
    assert {e["condition"] for e in eps} == {"MORPH (reference)", "Full-Graph", "TSG"}
    # the radio model ran: legacy roaming hands over and stops silent robots, the LAN does neither
    legacy = [e for e in eps if e["profile"] == "wifi-legacy-roaming"]
    assert all(e["network_handovers"] > 0 for e in legacy)
    assert all(e["network_handovers"] == 0 and e["view_age_mean"] == 0 for e in eps if e["profile"] == "lan")
    assert all(e["view_age_mean"] > 0 for e in legacy)
    assert (record / "network_tiny.png").stat().st_size > 10_000
    # the claims table compares MORPH with all-to-all per profile; the per-scale table has every policy
    assert "### The paper's claims: MORPH against all-to-all (Full-Graph)" in res.stdout
    assert "| MORPH (reference) | wifi-legacy-roaming | " in res.stdout
    assert "| wifi-legacy-roaming | TSG | " in res.stdout and "### tiny (T = 40)" in res.stdout
    assert res.stdout.strip().splitlines()[-1].startswith("network experiment: 12 episodes run, 0 already")
    assert "12/12" in res.stderr and "2 profiles × 3 policies × 2 seeds = 12 episodes" in res.stderr
    assert (record / "network.md").read_text().strip() == res.stdout.split("network experiment:")[0].strip()


def test_a_grid_cut_short_resumes_to_the_same_tables(tmp_path) -> None:
    plan = grid_plan(scales=("tiny",), profiles=("congested",), conditions=("morph", "full"), seeds=(301, 302),
                     steps=30)
    # the grid runs straight through once; its tables are then cut short and resumed
    cut = run_study(tmp_path / "b", plan, jobs=1)
    straight = {"markdown": cut["markdown"], "md": (tmp_path / "b" / "network.md").read_text()}
    log = tmp_path / "b" / "episodes.jsonl"
    lines = log.read_text().splitlines(keepends=True)
    log.write_text("".join(lines[:2]) + lines[2][:15])  # killed while writing the third line
    resumed = run_study(tmp_path / "b", plan, jobs=1)
    assert (resumed["ran"], resumed["skipped"]) == (2, 2) and cut["ran"] == 4
    assert resumed["markdown"] == straight["markdown"]
    assert (tmp_path / "b" / "network.md").read_text() == straight["md"]


def test_a_cell_is_cross_checked_through_the_services_under_a_rate_limited_profile(tmp_path, capsys) -> None:
    """--services-cell runs one cell again through morph-sim run's services (the air among them under `congested`)
    and says, seed by seed, that they give the lab's deliveries and view ages."""
    res = _cli(["--scales", "tiny", "--seeds", "1", "--steps", "60", "--profiles", "congested", "--conditions",
                "full-broadcast", "--jobs", "1", "--services-cell", "tiny:congested:full-broadcast", "--out",
                str(tmp_path), "--run-id", "x", "--no-progress"], capsys)
    assert res.returncode == 0, res.stderr
    assert "services cross-check of Full-Graph (broadcast) under congested at tiny: 1 seed, the lab's" in res.stderr
    check = json.loads((tmp_path / "x" / "services_check.json").read_text())
    (row,) = check["seeds"]
    assert check["equal"] and row["equal"] and row["lab_deliveries"] == row["services_deliveries"] > 0
    assert "## Services cross-check" in (tmp_path / "x" / "network.md").read_text()


def test_default_grid_is_the_study_the_issue_asks_for() -> None:
    plan = grid_plan()
    assert plan["scales"] == ["tiny", "small", "medium", "large"]
    assert plan["profiles"] == ["lan", "wifi-fast-roaming", "wifi-legacy-roaming", "congested", "lossy-mesh"]
    assert {"MORPH (reference)", "MORPH (paper)", "Full-Graph", "TSG", "Proximity"} <= set(plan["conditions"])
    assert len(SEEDS) >= 10 and not set(SEEDS) & {*range(1, 16), 42, 7, 123, 999, 2024}
    assert len(network_tasks(plan)) == 4 * 5 * len(plan["conditions"]) * len(SEEDS)
    assert set(plan["conditions"]) <= set(CONDITIONS)


@pytest.mark.parametrize("argv, message", [
    (["--profiles", "lan,5g"], "profiles: "),
    (["--conditions", "morph,all"], "conditions: unknown 'all'"),
    (["--scales", "huge"], "scales: unknown scale 'huge'"),
    (["--steps", "0"], "steps: must be >= 1"),
    (["--quick"], "quick: experiment network does not take --quick"),
    (["--services-cell", "tiny:congested"], "services_cell: expected SCALE:PROFILE:CONDITION"),
    (["--scales", "tiny", "--services-cell", "small:lan:morph"], "services_cell: 'small:lan:morph' is not a cell"),
])
def test_bad_values_are_refused_in_one_line(tmp_path, argv, message, capsys) -> None:
    res = _cli([*argv, "--out", str(tmp_path / "never")], capsys)
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert res.stderr.startswith(f"morph-sim experiment: error: {message}"), res.stderr
    assert not (tmp_path / "never").exists()
