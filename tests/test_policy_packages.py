"""A policy from outside, the way its author meets morph-sim: a package written by ``morph-sim policy new``, run by
import path or by its entry point in ``run`` and ``up`` (one process per robot); a policy that chooses for its
pickers gives the lab's record in ``run`` and ``up`` under a Wi-Fi profile; an agent started with another policy
than its run's refuses to join, naming both."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

from morph_sim.local import run_local
from services.bus.zenoh_bus import free_port
from services.runconfig import RunConfig

from _procs import kill_tree

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def _env(*paths: Path) -> dict[str, str]:
    extra = os.pathsep.join(str(p) for p in paths)
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (extra, str(ROOT)) if p)}


def _morph(args, env, cwd=None, timeout=240, python=sys.executable) -> subprocess.CompletedProcess:
    return subprocess.run([python, "-m", "morph_sim.cli", *args], env=env, cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def _main(args, capsys) -> subprocess.CompletedProcess:
    """The CLI in this process (the same parser and error handling) for the commands whose outcome is a file or a
    line, not processes of their own: its exit status, stdout and stderr."""
    from morph_sim.cli import main

    capsys.readouterr()
    code = main(args)
    out = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out.out, out.err)


def test_a_template_package_runs_in_run_and_up_without_touching_morph_sim(tmp_path, capsys, monkeypatch):
    """``policy new``, ``policy check`` and ``run`` in this process with the package on the path (as PYTHONPATH puts
    it there for a process); ``up`` in its own, whose agent processes import the package from PYTHONPATH."""
    pkg = tmp_path / "near-first"
    done = _main(["policy", "new", "near-first", "--out", str(pkg)], capsys)
    assert done.returncode == 0, done.stderr
    assert {p.relative_to(pkg).as_posix() for p in pkg.rglob("*") if p.is_file()} == {
        "pyproject.toml", "README.md", "near_first/__init__.py", "near_first/policy.py", "tests/test_policy.py"}
    env, name = _env(pkg), "near_first.policy:NearFirstPolicy"
    monkeypatch.syspath_prepend(str(pkg))
    check = _main(["policy", "check", name, "--no-distributed", "--steps", "60", "--decision-limit", "2"], capsys)
    assert check.returncode == 0 and check.stderr.strip() == f"policy {name}: 6 of 6 rules kept", check.stderr
    out = tmp_path / "runs"
    flags = ["--policy", name, "--policy-option", "reach=6", "--steps", "80", "--seed", "3", "--output-dir", str(out)]
    run = _main(["run", *flags, "--run-id", "r"], capsys)
    up = _morph(["up", *flags, "--run-id", "u", "--quiet", "--insecure"], env)
    assert run.returncode == 0 and up.returncode == 0, (run.stderr, up.stderr)
    assert up.stdout.strip().splitlines()[-1].startswith("run u: completed; 80 rows")
    assert (out / "r" / "metrics.csv").read_bytes() == (out / "u" / "metrics.csv").read_bytes()
    assert '"policy_options": {\n' in (out / "u" / "manifest.json").read_text()


def test_a_policy_that_chooses_for_its_pickers_gives_the_labs_record_under_wifi_roaming(tmp_path, monkeypatch):
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    monkeypatch.syspath_prepend(str(TESTS))
    # 100 ticks: hand-overs have made views stale (view_age_max 6) and the pickers' choices have parted from
    # Full-Graph's in a score of ticks by then; the records are compared whatever their length
    name, steps, seed, net = "_policies:ClosestRequest", 100, 4, "wifi-legacy-roaming"
    lab = run_episode(EpisodeSpec(scale="tiny", condition="closest", policy_name=name, seed=seed, steps=steps,
                                  network=net, fiedler_every=1))
    config = RunConfig(run_id="c", policy=name, steps=steps, seed=seed, network=net,
                       output_dir=tmp_path / "local")
    run = asyncio.run(run_local(config))
    up = _morph(["up", "--policy", name, "--steps", str(steps), "--seed", str(seed), "--network", net,
                 "--run-id", "c", "--output-dir", str(tmp_path / "up"), "--quiet", "--insecure"], _env(TESTS))
    assert up.returncode == 0, up.stderr[-2000:]
    assert (tmp_path / "up" / "c" / "metrics.csv").read_bytes() == (tmp_path / "local" / "c" / "metrics.csv").read_bytes()
    rows = run.monitor.rows

    def col(key):
        return np.array([np.nan if r[key] is None else float(r[key]) for r in rows])

    for key in ("deliveries_total", "requests", "commits", "view_age_mean", "view_age_max"):
        np.testing.assert_array_equal(col(key), lab.ticks[key], err_msg=key)
    # the profile acted (views went stale) and the pickers' choices took effect: Full-Graph asks as this policy does
    # and its pickers take the first request
    full = run_episode(EpisodeSpec(scale="tiny", condition="full", seed=seed, steps=steps, network=net))
    assert np.nanmax(col("view_age_max")) > 0 and lab.summary["deliveries"] > 0
    assert (lab.ticks["commits"] != full.ticks["commits"]).any()


AUCTION = ROOT / "examples" / "auction"


def test_the_auction_talks_and_gives_the_labs_record_in_run_and_up_under_wifi_roaming(tmp_path, monkeypatch):
    """The example allocator from outside (examples/auction: pickers bid over policy messages) under roaming:
    the lab, ``run`` and ``up`` give one record, messages included."""
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    monkeypatch.syspath_prepend(str(AUCTION))
    # 100 ticks: some two hundred messages and deliveries by then (the bids are counted below)
    name, steps, seed, net = "morph_auction.policy:AuctionPolicy", 100, 5, "wifi-legacy-roaming"
    lab = run_episode(EpisodeSpec(scale="tiny", condition="auction", policy_name=name, seed=seed, steps=steps,
                                  network=net, fiedler_every=1))
    run = asyncio.run(run_local(RunConfig(run_id="a", policy=name, steps=steps, seed=seed, network=net,
                                          output_dir=tmp_path / "local")))
    up = _morph(["up", "--policy", name, "--steps", str(steps), "--seed", str(seed), "--network", net,
                 "--run-id", "a", "--output-dir", str(tmp_path / "up"), "--quiet", "--insecure"], _env(AUCTION))
    assert up.returncode == 0, up.stderr[-2000:]
    assert (tmp_path / "up" / "a" / "metrics.csv").read_bytes() == (tmp_path / "local" / "a" / "metrics.csv").read_bytes()
    assert (tmp_path / "up" / "a" / "links.csv").read_bytes() == (tmp_path / "local" / "a" / "links.csv").read_bytes()
    rows = run.monitor.rows

    def col(key):
        return np.array([np.nan if r[key] is None else float(r[key]) for r in rows])

    for key in ("deliveries_total", "requests", "commits", "links", "view_age_mean", "view_age_max"):
        np.testing.assert_array_equal(col(key), lab.ticks[key], err_msg=key)
    # it talked: bids went over the radio (some lost or late under roaming), and the services counted them
    assert lab.summary["messages_sent"] > 3 * lab.summary["deliveries"] > 0
    assert run.monitor.messages.get("policy", 0) > 0


def test_an_agent_with_another_policy_refuses_to_join_naming_both(tmp_path):
    port = free_port()
    common = ["--run-id", "m", "--steps", "20", "--output-dir", str(tmp_path)]
    sim = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "sim", *common, "--policy", "proximity",
                            "--listen", f"tcp/127.0.0.1:{port}"], env=_env(), stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True)
    try:
        agent = _morph(["agent", *common, "--id", "0", "--endpoint", f"tcp/127.0.0.1:{port}", "--policy", "proximity",
                        "--radius", "3"], _env(), timeout=60)
        assert agent.returncode == 2
        assert agent.stderr.strip().splitlines()[-1] == (
            "morph-sim agent: error: policy: this agent runs 'proximity' (radius=3), the run's sim announces "
            "'proximity' (radius=4); start the agent with the run's --policy and --policy-option values")
    finally:
        kill_tree(sim)


@pytest.mark.slow
def test_a_template_package_installed_beside_morph_sim_passes_its_tests_and_runs(tmp_path):
    """The author's path end to end: ``policy new``, ``pip install -e`` into a fresh venv that sees morph-sim's own
    environment, the package's tests (the conformance kit, with a distributed run), ``policy check``, ``run`` and
    ``up`` by the entry point's name."""
    pkg, venv = tmp_path / "near-first", tmp_path / "venv"
    assert _morph(["policy", "new", "near-first", "--out", str(pkg)], _env()).returncode == 0
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = str(venv / "bin" / "python")
    site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    # beside morph-sim: the fresh venv sees the environment morph-sim is installed in (and its .pth files)
    Path(site, "beside_morph_sim.pth").write_text(f"import site; site.addsitedir({sysconfig.get_paths()['purelib']!r})\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    pip = subprocess.run([python, "-m", "pip", "install", "-q", "-e", str(pkg)], env=env, capture_output=True,
                         text=True, timeout=600)
    assert pip.returncode == 0, pip.stderr[-2000:]
    tests = subprocess.run([python, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", "tests"],
                           cwd=pkg, env=env, capture_output=True, text=True, timeout=600)
    assert tests.returncode == 0, tests.stdout[-3000:]
    assert _morph(["policy", "check", "near-first"], env, python=python).returncode == 0
    out = tmp_path / "runs"
    flags = ["--policy", "near-first", "--steps", "60", "--output-dir", str(out)]
    assert _morph(["run", *flags, "--run-id", "r"], env, python=python).returncode == 0
    assert _morph(["up", *flags, "--run-id", "u", "--quiet"], env, python=python).returncode == 0
    assert (out / "r" / "metrics.csv").read_bytes() == (out / "u" / "metrics.csv").read_bytes()
