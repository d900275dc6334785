"""The in-process lab: dispatch modes, common random numbers, paper-preset liveness, suites and records."""

import csv
import json
from importlib import resources

import numpy as np
import pytest

from morph_sim.cli import main as cli_main
from morph_sim.lab.runner import EpisodeSpec, run_episode
from morph_sim.lab.suite import SuiteConfig, markdown_table, run_suite, summarise

PAPER_ABLATIONS = ("v1", "no_threshold", "no_reward", "no_neuromod")


def _outcome(result):
    """What an episode produced: when each delivery happened and when each picker was sent."""
    return np.concatenate([result.ticks["deliveries"], result.ticks["commits"]])


def _behaviour(result):
    """The outcome plus the agents' dispatch behaviour: the gate probabilities they applied."""
    return np.concatenate([_outcome(result), result.ticks["gate_p_sum"]])


def test_dispatch_modes_and_divergence_count():
    kw = dict(scale="medium", condition="full", seed=42, steps=300)
    conc = run_episode(EpisodeSpec(dispatch="concurrent", **kw)).summary
    seq = run_episode(EpisodeSpec(dispatch="sequential", **kw)).summary
    assert conc["divergent_dispatch_ticks"] > 0  # two AGVs asking the same picker happens
    assert seq["divergent_dispatch_ticks"] > 0
    assert conc["deliveries"] > 0 and seq["deliveries"] > 0


def test_per_agent_streams_give_common_random_numbers():
    """Gate draws no longer touch the warehouse's stream: Full (no draws) is the same in both stream modes,
    and the request queue's evolution only depends on deliveries."""
    kw = dict(scale="tiny", condition="full", seed=7, steps=400, dispatch="sequential")
    a = run_episode(EpisodeSpec(shared_stream=False, **kw))
    b = run_episode(EpisodeSpec(shared_stream=True, **kw))
    np.testing.assert_array_equal(a.ticks["deliveries"], b.ticks["deliveries"])
    kw["condition"] = "morph"
    own = run_episode(EpisodeSpec(shared_stream=False, **kw))
    shared = run_episode(EpisodeSpec(shared_stream=True, **kw))
    assert not np.array_equal(own.ticks["commits"], shared.ticks["commits"])


def test_same_seed_same_trajectory():
    spec = EpisodeSpec(scale="small", condition="morph", seed=123, steps=250, preset="paper")
    a, b = run_episode(spec), run_episode(spec)
    np.testing.assert_array_equal(_outcome(a), _outcome(b))
    np.testing.assert_array_equal(a.final_weights, b.final_weights)


# Which ablations change the realised outcome (deliveries and pickers sent) of some reference seed within
# 400 steps at each scale; neuromodulation changes the gate probabilities everywhere but the realised
# dispatches only at some scales (docs/morph.md, "liveness").
OUTCOME_LIVE = {
    "tiny": PAPER_ABLATIONS,
    "small": ("v1", "no_threshold", "no_reward"),
    "medium": ("v1", "no_threshold", "no_reward"),
    "large": ("no_threshold", "no_reward", "no_neuromod"),
}


# Tiny in the default suite (every ablation changes an outcome there), the other scales with -m slow.
@pytest.mark.parametrize("scale", ["tiny", *(pytest.param(s, marks=pytest.mark.slow) for s in ("small", "medium",
                                                                                             "large"))])
def test_paper_preset_every_ablation_changes_some_seed(scale):
    """No dead rule: each ablation changes what the agents do (gate probabilities, dispatches, deliveries) for at
    least one of the reference seeds in 400 steps, and most change the realised outcome."""
    base: dict[int, object] = {}
    for ablation in PAPER_ABLATIONS:
        behaviour = outcome = False
        for seed in (42, 7, 123, 999, 2024):
            if seed not in base:
                base[seed] = run_episode(EpisodeSpec(scale=scale, condition="morph", seed=seed, steps=400,
                                                     preset="paper", fiedler_every=400))
            res = run_episode(EpisodeSpec(scale=scale, condition=ablation, seed=seed, steps=400, preset="paper",
                                          fiedler_every=400))
            behaviour |= not np.array_equal(_behaviour(res), _behaviour(base[seed]))
            outcome |= not np.array_equal(_outcome(res), _outcome(base[seed]))
            if outcome:
                break
        assert behaviour, f"{ablation} changed nothing at {scale}"
        if ablation in OUTCOME_LIVE[scale]:
            assert outcome, f"{ablation} changed no outcome at {scale}"


@pytest.mark.parametrize("scale", [pytest.param("small", marks=pytest.mark.slow), "medium"])  # Small: 3 seeds, -m slow
def test_paper_preset_no_neuromod_changes_an_outcome_in_800_steps(scale):
    """At Small and Medium −neuromod changes no realised outcome of the reference seeds in 400 steps; over 800 steps
    it does for some seed (measured: Medium seed 7, Small seeds 1 and 6 of 1…8, none of the reference five at Small),
    so with the test above the rule changes an outcome at every scale."""
    for seed in (7, 42, 1, 6):
        kw = dict(scale=scale, seed=seed, steps=800, preset="paper", fiedler_every=800)
        full = run_episode(EpisodeSpec(condition="morph", **kw))
        ablated = run_episode(EpisodeSpec(condition="no_neuromod", **kw))
        if not np.array_equal(_outcome(full), _outcome(ablated)):
            return
    pytest.fail(f"no_neuromod changed no outcome at {scale} in 800 steps")


def test_reset_at_boundary_clears_the_state(tmp_path):
    text = resources.files("services.policies").joinpath("presets", "morph_paper.toml").read_text()
    preset = tmp_path / "paper_reset150.toml"
    preset.write_text(text.replace("reset_every = 400", "reset_every = 150"))
    seen = {}

    def hook(obs, team):
        if obs.t in (149, 150, 151):
            seen[obs.t] = team.team_weights().sum()

    spec = EpisodeSpec(scale="tiny", condition="reset_at_boundary", seed=42, steps=300, preset=str(preset))
    reset = run_episode(spec, trace_hook=hook)
    full = run_episode(EpisodeSpec(scale="tiny", condition="morph", seed=42, steps=300, preset=str(preset)))
    assert seen[149] > 0 and seen[150] == 0.0
    assert not np.array_equal(_outcome(reset), _outcome(full))


def test_suite_writes_records_tables_and_plots(tmp_path):
    # jobs=1: the record does not depend on where the episodes ran (the test below), and 12 short episodes cost less
    # than starting worker processes for them
    outside = "services.policies.coordinators:ConstantPolicy"  # a policy from outside, by the name --policy takes
    cfg = SuiteConfig(kind="scale", scales=("tiny",), seeds=(42, 7), steps=120,
                      conditions=("none", "proximity", "tsg", "morph", "full", outside), jobs=1)
    res = run_suite(cfg, tmp_path, "t1", show_progress=False, argv=["test"])
    run = tmp_path / "t1"
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["seeds"] == [42, 7] and manifest["command_line"] == ["test"]
    assert "git_revision" in manifest and manifest["proximity_radii"]["tiny"] in (2, 3, 4, 5, 6, 8, 10)
    ep = run / "episodes" / "tiny_morph_s42"
    rows = list(csv.DictReader(open(ep / "ticks.csv")))
    assert len(rows) == 120 and "links" in rows[0]
    assert json.loads((ep / "summary.json").read_text())["deliveries"] == int(float(rows[-1]["deliveries_total"]))
    table = list(csv.DictReader(open(run / "summary.csv")))
    assert {r["condition"] for r in table} == set(cfg.conditions)
    full = next(r for r in table if r["condition"] == "full")
    assert float(full["pct_full"]) == pytest.approx(100.0)
    md = (run / "summary.md").read_text()
    assert "MORPH" in md and "Full-Graph" in md and "Wall time" in md and f"| {outside} |" in md
    assert float(next(r for r in table if r["condition"] == outside)["mean"]) > 0  # deliveries
    for png in ("cumulative_deliveries.png", "link_usage.png", "deliveries_bars.png"):
        assert (run / "plots" / png).stat().st_size > 5000
    # tables are recomputable from the episode summaries alone
    again = summarise(cfg, [json.loads(p.read_text()) for p in (run / "episodes").glob("*/summary.json")])
    assert markdown_table(cfg, again) .splitlines()[:7] == markdown_table(cfg, summarise(cfg, res.episodes)).splitlines()[:7]


def test_the_suite_gives_the_same_episodes_in_worker_processes_and_in_this_process():
    cfg = SuiteConfig(kind="scale", scales=("tiny",), seeds=(42, 7), steps=60, conditions=("proximity", "morph"),
                      jobs=2)
    pooled = run_suite(cfg, None, show_progress=False)
    serial = run_suite(cfg.model_copy(update={"jobs": 1}), None, show_progress=False)

    def strip(episodes):
        return [{k: v for k, v in e.items() if k != "wall_s"} for e in episodes]

    assert pooled.radii == serial.radii
    assert repr(strip(pooled.episodes)) == repr(strip(serial.episodes))  # repr: NaN compares equal to itself


def test_cli_experiment_small_run_and_errors(tmp_path, capsys):
    code = cli_main(["experiment", "ablation", "--scales", "tiny", "--seeds", "42", "--steps", "60",
                     "--conditions", "morph,v1", "--jobs", "1", "--no-progress", "--out", str(tmp_path),
                     "--run-id", "cli"])
    out = capsys.readouterr().out
    assert code == 0 and "study wall time" in out and (tmp_path / "cli" / "summary.md").exists()
    assert cli_main(["experiment", "scale", "--conditions", "morph,teleport", "--out", str(tmp_path)]) == 2
    assert "conditions" in capsys.readouterr().err
    assert cli_main(["experiment", "scale", "--seeds", "a,b", "--out", str(tmp_path)]) == 2
    assert "seeds" in capsys.readouterr().err
    assert cli_main(["experiment", "scale", "--preset", "nope", "--out", str(tmp_path)]) == 2
