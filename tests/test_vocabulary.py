"""One vocabulary: the lab's tick table and a ``morph-sim run`` record of the same episode use the metric catalogue's
names, and every column they share holds the same values, tick for tick; the lab's own columns are catalogue
entries marked lab-only. The per-episode tables (sweep, studies) draw their columns from the catalogue too, and the
studies' conditions from the one condition table."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from morph_sim.lab.runner import EpisodeSpec, run_episode
from morph_sim.local import run_local
from services.metrics import catalogue
from services.monitor.recorder import read_metrics
from services.runconfig import RunConfig

STEPS, SEED = 200, 1
#: the columns a fault-free lab episode and its run must both have (the check below cannot pass vacuously)
EXPECTED_SHARED = {"t", "deliveries", "deliveries_total", "requests", "commits", "links", "lambda2", "eta",
                   "view_age_mean", "view_age_max", *catalogue.outcome_values({})}


def _lab_table(policy: str) -> dict[str, np.ndarray]:
    # λ₂ on every tick, as the monitor computes it on every row
    res = run_episode(EpisodeSpec(scale="tiny", condition=policy, seed=SEED, steps=STEPS, fiedler_every=1))
    return {"t": np.arange(STEPS, dtype=float), **res.ticks}


def _run_table(policy: str, tmp_path) -> dict[str, np.ndarray]:
    cfg = RunConfig(run_id=f"voc-{policy}", scale="tiny", policy=policy, seed=SEED, steps=STEPS,
                    output_dir=tmp_path)
    result = asyncio.run(run_local(cfg, record=True))
    assert list(read_metrics(cfg.record_dir)[0]) == list(catalogue.COLUMNS)
    rows = result.monitor.rows  # the values metrics.csv was written from, before its rounding to 12 digits
    assert len(rows) == STEPS
    return {c: np.array([np.nan if r[c] is None else float(r[c]) for r in rows]) for c in catalogue.COLUMNS}


# Full-Graph with -m slow: its twin by default is MORPH's, the same checks on the same columns; every column that
# varies in Full-Graph's episode varies in MORPH's, which also moves the links, λ₂, η and the learning's columns that
# stay constant under Full-Graph.
@pytest.mark.parametrize("policy", [pytest.param("full", marks=pytest.mark.slow), "morph"])
def test_the_lab_tick_table_and_a_run_record_share_names_and_values(policy, tmp_path):
    lab, run = _lab_table(policy), _run_table(policy, tmp_path)
    assert list(run) == list(catalogue.COLUMNS)
    # every lab column is a catalogue name: a row metric (same meaning) or a lab-only entry
    unknown = [c for c in lab if c not in catalogue.COLUMNS and c not in catalogue.LAB_TICKS]
    assert not unknown, unknown
    shared = [c for c in lab if c in run]
    assert EXPECTED_SHARED <= set(shared), EXPECTED_SHARED - set(shared)
    for c in shared:
        np.testing.assert_array_equal(lab[c], run[c], err_msg=c)
    # the episode did something: deliveries, requests, commitments and links to compare
    for c in ("deliveries", "requests", "commits", "links"):
        assert np.nansum(run[c]) > 0, c
    np.testing.assert_array_equal(np.cumsum(lab["deliveries"]), lab["deliveries_total"])


def test_lab_only_columns_have_names_no_row_metric_uses():
    assert not set(catalogue.LAB_TICKS) & set(catalogue.NAMES)
    assert not set(catalogue.LAB_TICKS) & set(catalogue.EPISODE_BY_NAME)
    assert all(m.source == "lab" for m in catalogue.LAB_TICK_METRICS)


def test_study_metrics_come_from_the_catalogue():
    from morph_sim.lab import faults_experiment, network_study, sweep

    for metrics in (sweep.METRICS, faults_experiment.METRICS, network_study.METRICS):
        assert set(metrics) <= set(catalogue.EPISODE_BY_NAME)
    assert set(catalogue.COST_METRICS) <= set(faults_experiment.METRICS) & set(network_study.METRICS)
    with pytest.raises(KeyError, match="committed"):
        catalogue.episode_metrics("committed")


def test_the_sweep_engines_fill_shared_columns_with_the_same_meaning(tmp_path):
    """The same condition and seed on both engines: every column both fill holds the same value (``lab_*`` are the
    lab's alone and empty on the services engine)."""
    from morph_sim.lab.sweep import METRICS, EpisodeTask, SweepPlan, run_task

    out = {}
    for engine in ("lab", "services"):
        plan = SweepPlan.build(seeds=[SEED], base={"scale": "tiny", "steps": 120}, engine=engine)
        task = EpisodeTask(f"{engine}-task", plan.model_dump(mode="json"), {}, SEED, str(tmp_path / engine))
        out[engine] = run_task(task)["metrics"]
    lab, services = out["lab"], out["services"]
    for m in METRICS:
        if m.startswith("lab_"):
            assert services[m] is None and lab[m] is not None, m
        else:
            assert lab[m] == pytest.approx(services[m], rel=1e-12), m
    assert lab["requests"] > 0 and lab["commits"] > 0 and lab["median_lifetime"] is not None


def test_every_study_draws_its_conditions_from_the_one_table():
    from morph_sim.lab import audit, faults_experiment, network_study, shift
    from services.policies.conditions import ABLATION_STUDY, CONDITIONS, key_of

    table = {c.label: c for c in CONDITIONS.values()}
    for study in (faults_experiment.CONDITIONS, network_study.CONDITIONS):
        assert all(study[label] is table[label] for label in study)
    assert all(shift.SHIFT_CONDITIONS[k] is CONDITIONS[k] for k in shift.SHIFT_CONDITIONS)
    assert set(audit.PAPER_CONDITIONS) | set(ABLATION_STUDY) <= set(CONDITIONS)
    # the command lines' keys and labels as docs/results.md shows them
    assert faults_experiment.CONDITION_KEYS == {"morph": "MORPH (reference)", "morph-paper": "MORPH (paper)",
                                                "full": "Full-Graph", "tsg": "TSG", "proximity": "Proximity"}
    assert network_study.CONDITION_KEYS["full-broadcast"] == "Full-Graph (broadcast)"
    assert key_of("morph", "full") == "morph" and key_of("morph", "v1") == "v1"
    with pytest.raises(ValueError, match="ablation"):
        key_of("morph", "no_such_ablation")
