"""The paper-preset audit (morph_sim/lab/audit.py, docs/morph.md §4a), reduced: variants are the paper preset with
the stated overrides, and α_r — which only writes picker rows — changes no seed's behaviour."""

from __future__ import annotations

import json

from morph_sim.lab.audit import VARIANTS, run_audit, variant_toml
from services.policies.presets import load_preset


def test_variant_presets_are_the_paper_preset_with_their_overrides(tmp_path):
    paper = load_preset("paper")
    for name, (_, _, overrides) in VARIANTS.items():
        path = tmp_path / f"{name}.toml"
        path.write_text(variant_toml(name))
        preset = load_preset(str(path))
        assert preset.rules == "paper" and set(preset.ablations) == set(paper.ablations)
        assert preset.params.model_dump() == {**paper.params.model_dump(), **overrides}
    # the paper's v1 keeps δ_pred and α_r; the reference code's drops them
    assert paper.resolve("v1_paper").pred_boost > 0 and paper.resolve("v1_paper").reward_alpha > 0
    assert paper.resolve("v1").pred_boost == 0 and paper.resolve("v1").reward_alpha == 0
    assert paper.resolve("v1_paper").bcm_gain == paper.resolve("v1_paper").neuromod_gain == 0


def test_reduced_audit_alpha_r_changes_no_seed(tmp_path):
    res = run_audit(tmp_path / "audit", scales=("tiny",), seeds=(1, 2), steps=150,
                    variants=("paper", "no_alpha_r"), jobs=1, show_progress=False)
    rows = {(r["variant"], r["condition"]): r for r in res.rows}
    assert rows[("no_alpha_r", "morph")]["tiny"]["same_as_paper"]
    assert rows[("no_alpha_r", "morph")]["tiny"]["gate"] == rows[("paper", "morph")]["tiny"]["gate"]
    assert rows[("paper", "full")]["tiny"]["gate"] == 1.0 and rows[("paper", "tsg")]["tiny"]["gate"] == 0.25
    saved = json.loads((tmp_path / "audit" / "audit.json").read_text())
    assert saved["steps"] == 150 and "converged" in {c["target"] for c in saved["calibration"].values()}
    assert "| no_alpha_r | b | morph |" in (tmp_path / "audit" / "audit.md").read_text()
