"""The Python API from a user's side: the worked example in docs/ runs as written and its tables have the documented
columns; records of every kind load; without pandas the API answers with numpy columns and says how to get
DataFrames; a distributed run started from Python equals its record."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

import morph_sim as ms
from morph_sim import api

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "docs" / "notebook-example.md"


def _documented_columns() -> dict[str, list[str]]:
    out = {}
    for m in re.finditer(r"^\| `(\w+)` \| ([a-z_0-9, ]+) \|$", EXAMPLE.read_text(), re.M):
        out[m.group(1)] = [c.strip() for c in m.group(2).split(",")]
    return out


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", EXAMPLE.read_text(), re.S)


def test_the_worked_example_runs_and_its_tables_have_the_documented_columns(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    blocks = _blocks()
    assert len(blocks) >= 4
    for code in blocks:
        exec(compile(code, str(EXAMPLE), "exec"), ns)
    documented = _documented_columns()
    assert set(documented) == {"metrics", "events", "links", "positions"}
    assert documented == {k: list(v) for k, v in api.RUN_TABLES.items()}
    for policy, rec in ns["records"].items():
        for name, cols in documented.items():
            assert list(rec.table(name).columns) == cols, (policy, name)
        m = rec.metrics
        assert list(m["t"]) == list(range(150))
        # the table's last values are the record's totals
        assert m["deliveries_total"].iloc[-1] == rec.totals["deliveries_total"]
        assert m["deliveries"].sum() == rec.totals["deliveries_total"]
        assert m["links"].iloc[-1] == rec.totals["final_links"]
        assert list(rec.events["kind"])[0] == "run.started" and list(rec.events["kind"])[-1] == "run.finished"
        assert len(rec.positions) == 8 * len(set(rec.positions["t"]))
        assert (rec.links["i"] < rec.links["j"]).all()
        assert rec.manifest.run_config.policy == policy
    # links table and metrics agree tick by tick
    rec = ns["records"]["morph"]
    per_tick = rec.links.groupby("t").size().reindex(rec.metrics["t"], fill_value=0)
    assert list(per_tick) == list(rec.metrics["links"].astype(int))
    assert (tmp_path / "deliveries.png").stat().st_size > 5000
    sw = ns["sw"]
    assert list(sw.episodes.columns) == ["policy", "faults.loss.percent", "seed", "deliveries", "mean_links",
                                         "requests", "commits", "lab_gate_decisions", "lab_mean_p_respond",
                                         "median_lifetime", "eta_mean"]
    assert len(sw.episodes) == 3 * 2 * 3
    # common random numbers: every condition ran the same seeds
    assert all(sorted(g) == [1, 2, 3] for _, g in sw.episodes.groupby(["policy", "faults.loss.percent"])["seed"])
    assert ns["ep"].summary["deliveries"] == ns["ep"].ticks["deliveries_total"].iloc[-1]


def test_a_study_record_loads_as_episodes_ticks_and_summary(tmp_path):
    from morph_sim.cli import main

    assert main(["experiment", "scale", "--scales", "tiny", "--seeds", "1,2", "--steps", "30", "--conditions",
                 "morph,full", "--out", str(tmp_path), "--run-id", "st", "--no-progress", "--jobs", "1"]) == 0
    rec = ms.load(tmp_path / "st")
    assert rec.kind == "scale" and rec.tables == ("episodes", "ticks", "summary")
    eps = rec.episodes
    assert sorted(zip(eps["condition"], eps["seed"])) == [("full", 1), ("full", 2), ("morph", 1), ("morph", 2)]
    assert len(rec.ticks) == 4 * 30 and {"episode", "t", "deliveries", "deliveries_total", "links"} <= set(rec.ticks.columns)
    last = rec.ticks.groupby("episode")["deliveries_total"].last()
    assert sorted(last.astype(int)) == sorted(eps["deliveries"])
    assert set(rec.summary["condition"]) == {"morph", "full"}
    with pytest.raises(KeyError, match="metrics"):
        rec.table("metrics")


def test_without_pandas_tables_are_numpy_columns_and_the_message_says_how_to_get_dataframes(tmp_path, monkeypatch):
    rec = ms.run(policy="tsg", steps=30, seed=4, run_id="np", output_dir=tmp_path)
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas -> ImportError
    monkeypatch.setattr(api, "_warned", False)
    assert not api.has_pandas()
    fresh = ms.load(rec.path)
    with pytest.warns(UserWarning, match=r"pip install 'morph-sim\[data\]'"):
        metrics = fresh.metrics
    assert isinstance(metrics, dict) and list(metrics) == list(api.RUN_TABLES["metrics"])
    assert metrics["t"].dtype == np.int64 and metrics["t"].tolist() == list(range(30))
    assert metrics["deliveries_total"][-1] == fresh.totals["deliveries_total"]
    assert list(fresh.links) == ["t", "i", "j"]
    with pytest.raises(ImportError, match=r"pip install 'morph-sim\[data\]'"):
        fresh.frame("metrics")


def test_bad_configuration_names_the_field(tmp_path):
    with pytest.raises(ValueError, match=r"^policy:"):
        ms.run(policy="bogus", output_dir=tmp_path)
    with pytest.raises(ValueError, match=r"^steps:"):
        ms.episode(steps=0)
    with pytest.raises(ValueError, match=r"^mode: the lab engine does not model it"):
        ms.episode(mode="paced")
    with pytest.raises(FileNotFoundError, match="not a record"):
        ms.load(tmp_path)


def test_a_distributed_run_from_python_equals_its_in_process_twin(tmp_path):
    """ms.up starts real processes (sim, an agent per robot, monitor over Zenoh); a zero-fault run equals ms.run's.
    Three robots (tests/_procs.py FEW_ROBOTS): the API's path to the processes is the same for any fleet, and the
    default fleet's distributed run is held to the lab in tests/test_equivalence.py."""
    few = {"agvs": 2, "pickers": 1}
    dist = ms.up(steps=25, seed=5, run_id="py-up", output_dir=tmp_path, **few)
    local = ms.run(steps=25, seed=5, run_id="py-run", output_dir=tmp_path, **few)
    assert dist.manifest.run_config.seed == 5 and len(dist.metrics) == 25
    cols = ["t", "deliveries", "deliveries_total", "links", "lambda2"]
    assert dist.metrics[cols].equals(local.metrics[cols])
    assert dist.totals["deliveries_total"] == dist.metrics["deliveries_total"].iloc[-1]


async def test_run_works_from_inside_a_running_event_loop_as_in_a_notebook(tmp_path):
    """Jupyter runs cells inside an event loop; asyncio.run would refuse there, so the API runs in a helper thread."""
    rec = ms.run(policy="full", steps=15, seed=2, run_id="in-loop", output_dir=tmp_path)
    assert len(rec.metrics) == 15 and rec.totals["steps"] == 15


def _files(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def test_a_run_id_with_a_record_is_refused_and_the_record_left_as_it_was(tmp_path):
    """A notebook cell run twice: the second call names the run id and writes nothing; ms.up refuses it before any
    process starts."""
    import time

    first = ms.run(policy="full", steps=20, seed=1, run_id="rr", output_dir=tmp_path)
    before = _files(first.path)
    assert len(first.positions) == 8 * 21  # t = 0..20
    for again in (ms.run, ms.up):
        started = time.monotonic()
        with pytest.raises(ValueError, match=r"^run_id: .*rr exists .*overwrite=True"):
            again(policy="full", steps=20, seed=1, run_id="rr", output_dir=tmp_path)
        assert time.monotonic() - started < 2
        assert _files(first.path) == before


def test_overwrite_removes_the_old_record_wholly_before_the_run(tmp_path):
    ms.run(policy="full", steps=20, seed=1, run_id="ow", output_dir=tmp_path)
    stale = tmp_path / "ow" / "snapshots" / "stale.npz"
    stale.write_bytes(b"left by the first run")
    rec = ms.run(policy="tsg", steps=15, seed=2, run_id="ow", output_dir=tmp_path, overwrite=True)
    twin = ms.run(policy="tsg", steps=15, seed=2, run_id="twin", output_dir=tmp_path)
    assert not stale.exists()
    assert rec.manifest.run_config.policy == "tsg" and len(rec.metrics) == 15
    for name in ("metrics.csv", "positions.csv", "links.csv"):
        assert (rec.path / name).read_text() == (twin.path / name).read_text(), name
    # a directory that is not a run record is never removed
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "thesis.tex").write_text("mine")
    with pytest.raises(ValueError, match=r"^run_id: .*notes is not a run record \(it holds thesis.tex\)"):
        ms.run(policy="tsg", steps=5, run_id="notes", output_dir=tmp_path, overwrite=True)
    assert (tmp_path / "notes" / "thesis.tex").read_text() == "mine"
