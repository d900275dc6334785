"""``morph-sim experiment``: every flag is honoured by the study it is given to, or refused with one line naming it
(exit 2, before any work) — never silently ignored."""

from __future__ import annotations

import json

import pytest

from morph_sim.cli import main as cli_main


def _manifest_scale(record) -> str:
    return json.loads((record / "manifest.json").read_text())["config"]["scale"]


def test_shift_and_emergent_run_at_the_scale_given(tmp_path, capsys):
    rc = cli_main(["experiment", "shift", "--scales", "tiny", "--seeds", "1", "--phase-steps", "60",
                   "--conditions", "proximity", "--jobs", "1", "--no-progress", "--out", str(tmp_path),
                   "--run-id", "sh"])
    assert rc == 0 and "tiny, 6 phases × 60 steps" in capsys.readouterr().out
    assert _manifest_scale(tmp_path / "sh") == "tiny"
    episode = next((tmp_path / "sh" / "episodes").iterdir())
    assert json.loads((episode / "summary.json").read_text())["scale"] == "tiny"

    rc = cli_main(["experiment", "emergent", "--scales", "tiny", "--seeds", "1", "--steps", "60", "--preset", "paper",
                   "--jobs", "1", "--no-progress", "--out", str(tmp_path), "--run-id", "em"])
    assert rc == 0
    assert _manifest_scale(tmp_path / "em") == "tiny"


@pytest.mark.parametrize("argv, message", [
    (["scale", "--quick"], "quick: experiment scale does not take --quick (only faults takes it)"),
    (["ablation", "--loss", "5"], "loss: experiment ablation does not take --loss (only shift and emergent take it)"),
    (["shift", "--steps", "100"], "steps: experiment shift does not take --steps (its length is 6 phases × "
                                  "--phase-steps)"),
    (["shift", "--scales", "tiny,small"], "scales: experiment shift runs at one scale, got 'tiny,small'"),
    (["shift", "--radius", "tiny=3"], "radius: experiment shift takes one integer radius, got 'tiny=3'"),
    (["emergent", "--conditions", "morph"], "conditions: experiment emergent does not take --conditions"),
    (["emergent", "--scales", "huge"], "scales: unknown scale 'huge'"),
    (["faults", "--loss", "10"], "loss: experiment faults does not take --loss"),
    (["faults", "--scales", "huge"], "scales: unknown scale 'huge'"),
])
def test_a_flag_the_study_cannot_honour_is_refused_in_one_line(tmp_path, capsys, argv, message):
    rc = cli_main(["experiment", *argv, "--out", str(tmp_path / "never")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith(f"morph-sim experiment: error: {message}"), err
    assert not (tmp_path / "never").exists()  # refused before any work
