"""A zero-fault distributed run (``morph-sim up``: one OS process per agent over Zenoh) equals the
LocalBus run (``morph-sim run``) with the same seed — per-tick deliveries, links and W snapshots, tick for tick.

The default suite keeps one configuration per scale of the fast kind; the full matrix is marked slow.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from services.monitor.recorder import read_metrics, read_snapshots
from services.runconfig import RunConfig
from services.supervisor.local import run_local

POLICIES = [("full", "reference"), ("tsg", "reference"), ("proximity", "reference"), ("morph", "reference"),
            ("morph", "paper")]


def check_equal(live_run, tmp_path: Path, scale: str, policy: str, preset: str, steps: int = 200, seed: int = 42
                ) -> None:
    up = live_run("eq", "--policy", policy, "--preset", preset, "--steps", str(steps), "--seed", str(seed),
                  "--state-every", "10", "--snapshot-every", "50", scale=scale, listen=False, output_dir=tmp_path / "up")
    assert up.wait(timeout=300) == 0, up.stderr()[-3000:]
    config = RunConfig(run_id="eq", scale=scale, policy=policy, preset=preset, steps=steps, seed=seed,
                       state_every=10, snapshot_every=50, output_dir=tmp_path / "local")
    asyncio.run(run_local(config))
    up, local = tmp_path / "up" / "eq", tmp_path / "local" / "eq"
    up_rows, local_rows = read_metrics(up), read_metrics(local)
    assert len(up_rows) == len(local_rows) == steps
    for name in ("deliveries", "links", "lambda2", "requests", "commits", "acks", "eta"):
        assert [r[name] for r in up_rows] == [r[name] for r in local_rows], name
    assert (up / "metrics.csv").read_bytes() == (local / "metrics.csv").read_bytes()
    up_snaps, local_snaps = read_snapshots(up), read_snapshots(local)
    assert sorted(up_snaps) == sorted(local_snaps) == list(range(0, steps + 1, 50))
    for t in local_snaps:
        np.testing.assert_array_equal(up_snaps[t]["W"], local_snaps[t]["W"], err_msg=f"W at tick {t}")
        np.testing.assert_array_equal(up_snaps[t]["A"], local_snaps[t]["A"], err_msg=f"A at tick {t}")


def test_up_equals_local_tiny_morph(live_run, tmp_path):
    check_equal(live_run, tmp_path, "tiny", "morph", "reference")


@pytest.mark.slow
@pytest.mark.parametrize("scale", ["tiny", "small"])
@pytest.mark.parametrize("policy,preset", POLICIES)
def test_up_equals_local(live_run, tmp_path, scale, policy, preset):
    check_equal(live_run, tmp_path, scale, policy, preset)


@pytest.mark.slow
@pytest.mark.parametrize("policy,preset", [("morph", "reference"), ("morph", "paper")])
def test_up_equals_local_medium(live_run, tmp_path, policy, preset):
    check_equal(live_run, tmp_path, "medium", policy, preset, steps=400)
