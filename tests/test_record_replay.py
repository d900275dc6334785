"""Bus record and offline replay: the replayed monitor recomputes the live run's metrics exactly."""

from __future__ import annotations

import asyncio
import subprocess
import sys

import msgpack
import pytest

from services.bus.local import LocalNetwork
from services.monitor.recorder import read_metrics
from services.monitor.replay import BusRecorder, read_record, replay
from services.runconfig import RunConfig
from services.supervisor.local import run_local


@pytest.mark.parametrize("policy", ["morph", "proximity"])
async def test_replayed_metrics_equal_the_live_runs(tmp_path, policy):
    config = RunConfig(run_id=f"rec-{policy}", scale="tiny", steps=120, policy=policy, output_dir=tmp_path / "live")
    net = LocalNetwork()
    rec = BusRecorder(net.session("recorder"), config, tmp_path / "bus.mbr")
    recording = asyncio.create_task(rec.run(timeout=60))
    await asyncio.sleep(0)
    live = await run_local(config, network=net)
    frames = await recording
    header, samples = read_record(tmp_path / "bus.mbr")
    assert header["run_id"] == config.run_id and frames == sum(1 for _ in samples) > 1000
    result = await replay(tmp_path / "bus.mbr", tmp_path / "replayed")
    assert result.deliveries_total == live.monitor.deliveries_total
    assert read_metrics(tmp_path / "replayed" / config.run_id) == read_metrics(config.record_dir)
    assert len(read_metrics(config.record_dir)) == config.steps
    with pytest.raises(ValueError, match="output_dir"):  # never appends to an existing record
        await replay(tmp_path / "bus.mbr", tmp_path / "replayed")


def test_a_truncated_record_replays_up_to_its_last_whole_frame(tmp_path):
    path = tmp_path / "cut.mbr"
    config = RunConfig(run_id="cut")
    data = msgpack.packb({"format": "morph-sim-bus-record", "version": 1, "run_id": "cut",
                          "config": config.model_dump(mode="json")})
    frame = msgpack.packb([0.0, "morph/cut/ctl/stop", b"\x80", "x", 1, 0.0], use_bin_type=True)
    path.write_bytes(data + frame + frame[:-3])
    _, samples = read_record(path)
    assert len(list(samples)) == 1
    (tmp_path / "bad.mbr").write_bytes(msgpack.packb({"format": "other"}))
    with pytest.raises(ValueError, match="not a morph-sim bus record"):
        read_record(tmp_path / "bad.mbr")


def test_record_and_replay_commands_against_a_live_up_run(tmp_path, recorded_run):
    """``morph-sim record`` followed the shared run from its start (tests/conftest.py); ``morph-sim replay`` of what
    it wrote recomputes the live run's record."""
    up, rec = recorded_run.up, recorded_run.record
    assert rec.returncode == 0, rec.stderr[-2000:]
    assert rec.stderr.startswith(f"recording run {up.run_id} (tiny, {recorded_run.steps} steps)"), rec.stderr
    assert recorded_run.code == 0, up.stderr()[-3000:]
    rep = subprocess.run([sys.executable, "-m", "morph_sim.cli", "replay", str(recorded_run.recording),
                          "--output-dir", str(tmp_path / "replayed")], capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr[-2000:]
    replayed, live = read_metrics(tmp_path / "replayed" / up.run_id), read_metrics(up.record)
    assert len(replayed) == len(live) == recorded_run.steps
    # Over Zenoh the recorder and the monitor are two subscribers; the monitor holds a row until every agent's ack
    # and link report is in (a grace of a few ticks), so every column, links included, must agree.
    cols = ("t", "sim_time", "deliveries", "deliveries_total", "requests", "commits", "acks", "links", "lambda2", "eta")
    assert [[r[c] for c in cols] for r in replayed] == [[r[c] for c in cols] for r in live]
    for name in ("metrics.csv", "links.csv", "positions.csv"):  # byte for byte
        assert (tmp_path / "replayed" / up.run_id / name).read_bytes() == (up.record / name).read_bytes(), name
