"""`morph-sim sweep` from the user's side: real CLI processes interrupted (the uninterrupted and resumed sweeps they are
compared with run the CLI in this process), on local processes and on a Dask cluster (dask.distributed's LocalCluster in this process, loopback only), the services engine, bad input."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from morph_sim.lab.sweep import SweepPlan, run_sweep

from _procs import alive, descendants, kill_all, kill_tree, terminal_signals

# The acceptance sweep: 3 policies × 3 loss levels × 2 scales × 5 seeds = 90 episodes. The default suite runs it with
# short episodes and two seeds; the slow versions run it whole at the studies' length.
GRID = ["--grid", "policy=morph,full,tsg", "--grid", "faults.loss=0,10,30", "--grid", "scale=tiny,small"]
ACCEPTANCE = [*GRID, "--seeds", "1-5"]
REDUCED = [*GRID, "--seeds", "1-2"]
SHORT = ["--set", "steps=40"]
LONG = ["--set", "steps=400"]


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "morph_sim.cli", "sweep", *args], capture_output=True, text=True,
                          timeout=timeout)


def _in_process(*args: str) -> subprocess.CompletedProcess:
    """``morph-sim sweep`` in this process, as :func:`_cli` runs it in its own: for the runs that are only a
    reference or a resume (the interrupted runs are processes of their own, as a user's terminal starts them)."""
    import contextlib
    import io

    from morph_sim.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["sweep", *args])
    return subprocess.CompletedProcess(["sweep", *args], code, out.getvalue(), err.getvalue())


def _main(*args: str, capsys) -> tuple[int, str, str]:
    """The CLI in this process (same parser, same error handling) for checks that need no process of their own."""
    from morph_sim.cli import main

    code = main(["sweep", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.exists() else 0


def _interrupt_at_half(args: list[str], log: Path, sig: int, total: int) -> subprocess.CompletedProcess:
    proc = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "sweep", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=terminal_signals)
    try:
        deadline = time.monotonic() + 240
        while _lines(log) < total // 2:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the sweep did not reach half"
            time.sleep(0.01)
        workers = descendants(proc.pid)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
        if sig == signal.SIGINT:  # the workers ignore SIGINT: the sweep stops them, none is left running
            deadline = time.monotonic() + 10
            while alive(workers) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not alive(workers), f"workers of the interrupted sweep still run: {alive(workers)}"
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    finally:
        kill_tree(proc)


def _check_interrupted_then_resumed(tmp_path: Path, grid: list[str], total: int, sig: int, jobs: str,
                                    whole: tuple[Path, subprocess.CompletedProcess] | None = None
                                    ) -> subprocess.CompletedProcess:
    """``whole``: the uninterrupted sweep of the same command line (its directory and its process), if one ran."""
    common = [*grid, "--out", str(tmp_path), "--no-progress", "--jobs", jobs]
    if whole is None:
        whole = (tmp_path / "whole", _in_process(*common, "--run-id", "whole"))
    whole_dir, done_whole = whole
    assert done_whole.returncode == 0, done_whole.stderr
    assert f"{total} episodes run, 0 already in the record" in done_whole.stdout.splitlines()[-1]

    log = tmp_path / "cut" / "episodes.jsonl"
    cut = _interrupt_at_half([*common, "--run-id", "cut"], log, sig, total)
    done = _lines(log)
    assert 0 < done < total, f"interrupted with {done} of {total}"
    if sig == signal.SIGINT:
        assert cut.returncode == 130
        assert cut.stderr.strip().splitlines()[-1] == (
            f"sweep cut: interrupted with {done} of {total} episodes in the record; the same command with "
            "--run-id cut resumes it")
    assert not (tmp_path / "cut" / "results.csv").exists()

    resumed = _in_process(*common, "--run-id", "cut")
    assert resumed.returncode == 0, resumed.stderr
    assert resumed.stdout.splitlines()[-1].startswith(f"sweep cut: {total - done} episodes run, {done} already in "
                                                      "the record")
    for name in ("results.csv", "comparison.csv", "comparison.md"):
        assert (tmp_path / "cut" / name).read_text() == (whole_dir / name).read_text(), name
    assert _lines(log) == total  # nothing ran twice
    rows = list(csv.DictReader(open(whole_dir / "results.csv")))
    assert len(rows) == total
    return done_whole


@pytest.fixture(scope="module")
def reduced_sweep(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """The reduced acceptance sweep (short episodes, two seeds) from the CLI in this process, its episodes run here
    too (``--jobs 1``), to its end once: the uninterrupted sweep that the interrupted one (on two worker processes)
    and the Dask one must equal. (Its directory, its outcome.)"""
    out = tmp_path_factory.mktemp("sweep")
    done = _in_process(*REDUCED, *SHORT, "--out", str(out), "--run-id", "whole", "--no-progress", "--jobs", "1")
    return out / "whole", done


def test_interrupted_at_half_and_resumed_equals_an_uninterrupted_sweep(tmp_path, reduced_sweep):
    whole = _check_interrupted_then_resumed(tmp_path, [*REDUCED, *SHORT], 36, signal.SIGINT, "2", reduced_sweep)
    _check_tidy(reduced_sweep[0], whole.stdout)


def test_an_interrupted_pool_has_ended_its_manager_thread_and_workers_when_the_command_goes_on():
    # what the interpreter's exit finds of an interrupted pool: no thread left to close its wake-up pipe while the exit
    # wakes it (Python 3.11 does so without a lock: "Bad file descriptor" once ended an interrupted sweep's output)
    from morph_sim.lab.executors import episode_pool

    seen = {}
    with pytest.raises(KeyboardInterrupt):
        with episode_pool(2) as pool:
            assert pool.submit(abs, -1).result(timeout=30) == 1
            pool.submit(time.sleep, 30)
            seen["manager"] = pool._executor_manager_thread
            seen["workers"] = list(pool._processes.values())
            raise KeyboardInterrupt
    assert not seen["manager"].is_alive()
    assert not any(worker.is_alive() for worker in seen["workers"])


def test_a_killed_sweep_resumes_too(tmp_path):
    """SIGKILL may cut a line of the record in half: the resumed sweep drops it and runs that episode again."""
    grid = ["--grid", "policy=morph,tsg", "--seeds", "1-5", "--set", "steps=40"]
    _check_interrupted_then_resumed(tmp_path, grid, 10, signal.SIGKILL, "1")


@pytest.mark.slow
def test_acceptance_sweep_interrupted_and_resumed_at_full_length(tmp_path):
    _check_interrupted_then_resumed(tmp_path, [*ACCEPTANCE, *LONG], 90, signal.SIGINT, "2")


def _check_tidy(run_dir: Path, stdout: str) -> None:
    rows = list(csv.DictReader(open(run_dir / "results.csv")))
    assert list(rows[0]) == ["policy", "faults.loss.percent", "scale", "seed", "deliveries", "mean_links",
                             "requests", "commits", "lab_gate_decisions", "lab_mean_p_respond", "median_lifetime",
                             "eta_mean"]
    by: dict = {}
    for r in rows:
        by.setdefault((r["policy"], r["faults.loss.percent"], r["scale"]), []).append(int(r["seed"]))
    # common random numbers: every condition ran the same seeds, in order
    assert len(by) == 18 and all(s == [1, 2] for s in by.values())
    import pandas as pd

    pq = pd.read_parquet(run_dir / "results.parquet")
    assert len(pq) == 36 and list(pq.columns) == list(rows[0])
    assert pq["deliveries"].tolist() == [int(r["deliveries"]) for r in rows]
    # the comparison table: one row per condition, Welch p against MORPH with the other axes equal
    comp = list(csv.DictReader(open(run_dir / "comparison.csv")))
    assert len(comp) == 18
    assert {r["baseline"] for r in comp if r["policy"] != "morph"} == {"policy=morph"}
    assert all(r["p_vs_baseline"] == "" for r in comp if r["policy"] == "morph")
    assert "| policy | faults.loss.percent | scale | n | deliveries | links | baseline | Welch p |" in stdout


def _local_cluster():
    from distributed import LocalCluster

    return LocalCluster(processes=False, n_workers=1, threads_per_worker=2, protocol="tcp", host="127.0.0.1",
                        dashboard_address=None)


def test_dask_local_cluster_equals_local_processes_episode_for_episode(tmp_path, reduced_sweep):
    """The CLI in its own process sends the acceptance grid (short episodes, two seeds) to a LocalCluster's
    scheduler; the slow test below runs all five seeds at length."""
    local_dir, local = reduced_sweep
    assert local.returncode == 0, local.stderr
    with _local_cluster() as cluster:
        res = _cli(*REDUCED, *SHORT, "--out", str(tmp_path), "--run-id", "dask", "--no-progress",
                   "--executor", "dask", "--scheduler", cluster.scheduler_address)
    assert res.returncode == 0, res.stderr
    assert "(lab engine, dask executor)" in res.stderr
    for name in ("results.csv", "comparison.csv"):
        assert (tmp_path / "dask" / name).read_text() == (local_dir / name).read_text()
    a = [json.loads(x) for x in (local_dir / "episodes.jsonl").read_text().splitlines()]
    b = {r["key"]: r["metrics"] for r in map(json.loads, (tmp_path / "dask" / "episodes.jsonl").read_text().splitlines())}
    assert len(a) == 36 and all(b[r["key"]] == r["metrics"] for r in a)


@pytest.mark.slow
def test_dask_acceptance_sweep_at_full_length(tmp_path):
    plan = SweepPlan.build(grid={"policy": ["morph", "full", "tsg"], "faults.loss": [0, 10, 30],
                                 "scale": ["tiny", "small"]}, seeds="1-5", base={"steps": 400})
    local = run_sweep(plan, tmp_path, "local", progress=False)
    with _local_cluster() as cluster:
        dask = run_sweep(plan, tmp_path, "dask", executor="dask", scheduler=cluster, progress=False)
    assert dask.rows == local.rows and len(local.rows) == 90


def test_a_dask_sweep_interrupted_resumes_locally_to_the_same_table(tmp_path):
    """The record does not care where an episode ran: half on the cluster, the rest on local processes."""
    plan = SweepPlan.build(grid={"policy": ["morph", "tsg"], "scale": ["tiny", "small"]}, seeds="1-3",
                           base={"steps": 40})
    seen = []

    def stop_at_half(done, total):
        seen.append(done)
        if done >= total // 2:
            raise KeyboardInterrupt

    with _local_cluster() as cluster:
        with pytest.raises(KeyboardInterrupt):
            run_sweep(plan, tmp_path, "mixed", executor="dask", scheduler=cluster, progress=stop_at_half)
    resumed = run_sweep(plan, tmp_path, "mixed", progress=False, jobs=1)
    assert resumed.skipped == 6 and resumed.ran == 6
    whole = run_sweep(plan, tmp_path, "whole", progress=False, jobs=1)
    assert resumed.rows == whole.rows


def test_services_engine_episodes_equal_morph_sim_run(tmp_path):
    """The services engine runs the real services over the in-process bus: each episode has a run record, and the
    zero-fault episode equals `morph-sim run` with the same config; loss is applied from tick 0 by a schedule. (Both
    commands in this process, the sweep's four episodes too, --jobs 1: where an episode runs does not change its
    record, and worker processes would cost more than these short episodes; the lab engine's sweeps above run on
    the pool.)"""
    res = _in_process("--engine", "services", "--grid", "policy=morph,tsg", "--grid", "faults.loss=0,30", "--seeds", "3",
                      "--set", "steps=40", "--set", "mode=lockstep", "--out", str(tmp_path), "--run-id", "svc",
                      "--no-progress", "--jobs", "1")
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader(open(tmp_path / "svc" / "results.csv")))
    assert len(rows) == 4
    records = sorted((tmp_path / "svc" / "episodes").glob("ep-*/summary.json"))
    assert len(records) == 4
    from morph_sim.cli import main

    assert main(["run", "--quiet", "--policy", "morph", "--seed", "3", "--steps", "40", "--output-dir",
                 str(tmp_path), "--run-id", "twin"]) == 0
    total = json.loads((tmp_path / "twin" / "summary.json").read_text())
    clean = next(r for r in rows if r["policy"] == "morph" and r["faults.loss.percent"] == "0")
    assert int(clean["deliveries"]) == total["deliveries_total"]
    assert float(clean["mean_links"]) == total["mean_links"]
    lossy = [p for p in (tmp_path / "svc" / "episodes").glob("*.faults.toml")]
    assert len(lossy) == 2 and "percent = 30" in lossy[0].read_text()
    events = [json.loads(x) for p in (tmp_path / "svc" / "episodes").glob("ep-*/events.jsonl")
              for x in p.read_text().splitlines()]
    assert sum(e["kind"] == "fault.set" for e in events) >= 2


def test_a_sweep_file_equals_the_same_grid_on_the_command_line(tmp_path, capsys):
    f = tmp_path / "sweep.toml"
    f.write_text('seeds = "1-3"\n[grid]\npolicy = ["morph", "tsg"]\n"faults.loss" = [0, 20]\n'
                 '[base]\nsteps = 40\n[run]\njobs = 1\n')
    a = _main(str(f), "--out", str(tmp_path), "--run-id", "file", "--no-progress", capsys=capsys)
    b = _main("--grid", "policy=morph,tsg", "--grid", "faults.loss=0,20", "--seeds", "1-3", "--set", "steps=40",
              "--out", str(tmp_path), "--run-id", "flags", "--no-progress", "--jobs", "1", capsys=capsys)
    assert a[0] == 0 and b[0] == 0, a[2] + b[2]
    assert (tmp_path / "file" / "results.csv").read_text() == (tmp_path / "flags" / "results.csv").read_text()


@pytest.mark.parametrize("args, message", [
    (["--grid", "policy=morph,bogus"], "policy: unknown 'bogus' (known: full, full-broadcast, constant, tsg, "
                                       "proximity, none, morph; or package.module:Class)"),
    (["--grid", "scale=tiny,huge"], "scale: unknown size 'huge'"),
    (["--grid", "faults.loss=0,abc"], "faults.loss.percent: Input should be a valid number"),
    (["--grid", "faults.loss=0,150"], "faults.loss.percent: Input should be less than or equal to 100"),
    (["--grid", "warp=1,2"], "warp: not a RunConfig field or a faults.* parameter"),
    (["--grid", "policy"], "grid: 'policy' is not like field=v1,v2,…"),
    (["--grid", "mode=lockstep,paced"], "mode: the lab engine does not model it"),
    (["--grid", "faults.latency.delay=0,1"], "faults.latency.delay: the lab engine models message loss only"),
    (["--grid", "steps=10,0"], "steps: Input should be greater than or equal to 1"),
    (["--grid", "policy=tsg", "--seeds", "5-1"], "seeds: '5-1' is not a seed or a range like 1-20"),
    (["--grid", "policy=tsg", "--seeds", "x"], "seeds: 'x' is not a seed or a range like 1-20"),
    (["--grid", "seed=1,2"], "seed: sweep seeds with --seeds"),
    (["--grid", "policy=tsg,tsg"], "policy: a value is given twice"),
    (["--grid", "ablation=v1"], ""),  # valid: an ablation of MORPH (the default policy)
    (["--grid", "policy=tsg", "--executor", "dask"], "scheduler: --executor dask needs --scheduler"),
    (["--grid", "policy=tsg", "--jobs", "0"], "jobs: must be at least 1"),
    (["--grid", "policy=tsg", "--baseline", "policy=full"], "baseline: policy='full' is not one of the grid's"),
])
def test_bad_grid_values_fail_with_one_line_naming_the_field(tmp_path, args, message, capsys):
    fixed = [] if any(a.startswith("steps=") for a in args) else ["--set", "steps=5"]
    code, out, err = _main(*args, *fixed, "--out", str(tmp_path), "--run-id", "bad", "--no-progress", "--jobs", "1",
                           capsys=capsys) if "--jobs" not in args else _main(
        *args, *fixed, "--out", str(tmp_path), "--run-id", "bad", "--no-progress", capsys=capsys)
    if not message:
        assert code == 0, err
        return
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"morph-sim sweep: error: {message}"), lines
    assert not (tmp_path / "bad" / "episodes.jsonl").exists()


def test_a_bad_value_from_a_real_process_is_one_line_and_exit_2(tmp_path):
    res = _cli("--grid", "policy=morph,bogus", "--out", str(tmp_path))
    assert res.returncode == 2 and res.stdout == ""
    assert res.stderr.strip().splitlines() == [
        "morph-sim sweep: error: policy: unknown 'bogus' (known: full, full-broadcast, constant, tsg, proximity, "
        "none, morph; or package.module:Class)"]


def test_a_record_of_another_sweep_is_not_resumed(tmp_path, capsys):
    assert _main("--grid", "policy=tsg", "--set", "steps=5", "--out", str(tmp_path), "--run-id", "x",
                 "--no-progress", capsys=capsys)[0] == 0
    code, _, err = _main("--grid", "policy=full", "--set", "steps=5", "--out", str(tmp_path), "--run-id", "x",
                         "--no-progress", capsys=capsys)
    assert code == 2
    assert err.strip().splitlines()[-1] == (f"morph-sim sweep: error: sweep: {tmp_path / 'x'} holds a different sweep "
                                            "(not the same grid; only more seeds extend it); give another --run-id or "
                                            "--out")


def test_dask_executor_without_the_extra_says_how_to_install(tmp_path, monkeypatch):
    from morph_sim.lab import executors

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"pip install 'morph-sim\[cluster\]'"):
        executors.make_executor("dask", scheduler="tcp://127.0.0.1:8786")


def test_an_unreachable_scheduler_is_one_error_line(tmp_path):
    from morph_sim.lab.executors import DaskExecutor
    from services.bus.zenoh_bus import free_port

    with pytest.raises(ValueError, match=r"^scheduler: cannot reach tcp://127.0.0.1:\d+"):
        DaskExecutor(f"tcp://127.0.0.1:{free_port()}", timeout=1)


def test_the_scale_study_on_dask_equals_it_on_local_processes(tmp_path, capsys):
    """The existing studies take the same executor: the scale study (with the Proximity calibration that gates some
    episodes) on a LocalCluster gives the same episodes as run locally. Both from the CLI in this process (a CLI
    process of its own sending work to the cluster is the sweep's test above), the local study with --jobs 1: that
    a study's local worker processes give the episodes run in this process is tests/test_lab.py's
    test_the_suite_gives_the_same_episodes_in_worker_processes_and_in_this_process."""
    from morph_sim.cli import main

    study = ["experiment", "scale", "--scales", "tiny", "--seeds", "1,2", "--steps", "25", "--conditions",
             "morph,proximity", "--out", str(tmp_path), "--no-progress"]
    assert main([*study, "--run-id", "local", "--jobs", "1"]) == 0, capsys.readouterr().err
    with _local_cluster() as cluster:
        code = main([*study, "--run-id", "dask", "--executor", "dask", "--scheduler", cluster.scheduler_address])
    assert code == 0, capsys.readouterr().err

    def episodes(run: str) -> dict:
        out = {}
        for p in sorted((tmp_path / run / "episodes").glob("*/summary.json")):
            summary = json.loads(p.read_text())
            summary.pop("wall_s")
            out[p.parent.name] = (summary, (p.parent / "ticks.csv").read_text())
        return out

    a, b = episodes("local"), episodes("dask")
    assert len(a) == 4 and a == b
    assert (tmp_path / "dask" / "summary.csv").read_text() == (tmp_path / "local" / "summary.csv").read_text()
    capsys.readouterr()
    assert main(["experiment", "shift", "--executor", "dask", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert capsys.readouterr().err.strip() == (
        "morph-sim experiment: error: executor: the dask executor runs the scale and ablation studies (and sweeps), "
        "not shift")


def test_progress_counts_every_episode_and_the_bar_ends_full(tmp_path, capsys):
    plan = SweepPlan.build(grid={"policy": ["tsg", "full"]}, seeds="1-3", base={"steps": 10})
    seen = []
    run_sweep(plan, tmp_path, "cb", progress=lambda done, total: seen.append((done, total)), jobs=1)
    assert seen == [(k, 6) for k in range(1, 7)]
    code, out, err = _main("--grid", "policy=tsg,full", "--seeds", "1-3", "--set", "steps=10", "--out", str(tmp_path),
                           "--run-id", "bar", "--jobs", "1", capsys=capsys)
    assert code == 0 and "6/6" in err and "sweep: 2 conditions × 3 seeds = 6 episodes" in err


def test_lab_engine_sweeps_network_profiles_as_the_lab_episode():
    """network is a lab field: each episode is run_episode with the profile (the services' radio model)."""
    from morph_sim.lab.runner import run_episode

    plan = SweepPlan.build(grid={"network": ["lan", "wifi-legacy-roaming"]}, seeds="3", base={"steps": 60,
                                                                                              "policy": "full"})
    specs = [plan.episode_spec(c, s) for c, s in plan.episodes()]
    assert [s.network for s in specs] == ["lan", "wifi-legacy-roaming"]
    assert run_episode(specs[1]).summary["network_handovers"] > 0


def test_no_worker_outlives_a_sweep_killed_with_sigkill(tmp_path):
    """SIGKILL leaves the parent no chance to stop its pool: each worker dies with it (the kernel tells it)."""
    log = tmp_path / "k" / "episodes.jsonl"
    with open(tmp_path / "stderr", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "sweep", "--grid", "policy=morph,tsg",
                                 "--seeds", "1-30", "--set", "steps=300", "--out", str(tmp_path), "--run-id", "k",
                                 "--no-progress", "--jobs", "2"], stdout=subprocess.DEVNULL, stderr=err)
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while _lines(log) < 1 or len(workers) < 2:
            assert proc.poll() is None, (tmp_path / "stderr").read_text()
            assert time.monotonic() < deadline, "the sweep's workers did not start"
            workers |= descendants(proc.pid)
            time.sleep(0.02)
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10
        while alive(workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(workers), f"workers of the killed sweep still run: {alive(workers)}"
        assert _lines(log) < 60  # killed mid-way: the workers had episodes left to run
    finally:
        kill_tree(proc)
        kill_all(alive(workers))


WELCH_GRID = ["--grid", "policy=morph,full", "--set", "steps=120", "--no-progress", "--jobs", "1"]


def test_welch_p_is_withheld_below_three_seeds_and_more_seeds_extend_the_sweep(tmp_path, capsys):
    out = ("--out", str(tmp_path))
    code, stdout, err = _main(*WELCH_GRID, "--seeds", "1-2", *out, "--run-id", "w", capsys=capsys)
    assert code == 0, err
    comp = {r["policy"]: r for r in csv.DictReader(open(tmp_path / "w" / "comparison.csv"))}
    assert comp["full"]["p_vs_baseline"] == "" and comp["full"]["p_note"] == "n < 3"
    assert "| full | 2 |" in stdout and "| policy=morph | withheld (n < 3) |" in stdout
    assert "Welch p is withheld where a condition or its baseline has fewer than 3 seeds" in stdout

    # the same sweep with one more seed: the four episodes run are kept, the two new ones run
    code, stdout, err = _main(*WELCH_GRID, "--seeds", "1-3", *out, "--run-id", "w", capsys=capsys)
    assert code == 0, err
    assert stdout.splitlines()[-1].startswith("sweep w: 2 episodes run, 4 already in the record")
    assert _lines(tmp_path / "w" / "episodes.jsonl") == 6
    code, fresh, err = _main(*WELCH_GRID, "--seeds", "1-3", *out, "--run-id", "fresh", capsys=capsys)
    assert code == 0, err
    for name in ("results.csv", "comparison.csv", "comparison.md"):
        assert (tmp_path / "w" / name).read_text() == (tmp_path / "fresh" / name).read_text(), name
    comp = {r["policy"]: r for r in csv.DictReader(open(tmp_path / "w" / "comparison.csv"))}
    assert comp["full"]["p_note"] == "" and 0 <= float(comp["full"]["p_vs_baseline"]) <= 1
    assert "withheld (" not in stdout and "Welch p is withheld" not in stdout
    import morph_sim as ms

    assert ms.load(tmp_path / "w").manifest.sweep_plan.seeds == (1, 2, 3)

    # anything else changed is still another sweep: fewer seeds, another grid
    for args in (("--seeds", "1-2"), ("--seeds", "1-4", "--set", "scale=small")):
        code, _, err = _main(*WELCH_GRID, *args, *out, "--run-id", "w", capsys=capsys)
        assert code == 2 and f"sweep: {tmp_path / 'w'} holds a different sweep (not the same " in err, err
    assert _lines(tmp_path / "w" / "episodes.jsonl") == 6
