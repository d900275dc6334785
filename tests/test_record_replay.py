"""Bus record and offline replay: the replayed monitor recomputes the live run's metrics exactly."""

from __future__ import annotations

import asyncio
import subprocess
import sys

import msgpack
import pytest

from morph_sim.local import run_local
from schemas.tick import tick_number
from services.bus.local import LocalNetwork
from services.monitor.recorder import read_metrics
from services.monitor.replay import BusRecorder, read_record, replay
from services.runconfig import RunConfig

from _procs import FEW_ROBOTS


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


def test_up_bus_record_replays_to_the_record(tmp_path, recorded_run):
    """``up --bus-record`` records the run from its first tick (the monitor writes it, and the sim starts no tick
    before the monitor is there): ``morph-sim replay`` of it recomputes the live run's record, byte for byte."""
    up = recorded_run.up
    assert recorded_run.code == 0, up.stderr()[-3000:]
    rep = subprocess.run([sys.executable, "-m", "morph_sim.cli", "replay", str(recorded_run.recording),
                          "--output-dir", str(tmp_path / "replayed")], capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr[-2000:]
    replayed, live = read_metrics(tmp_path / "replayed" / up.run_id), read_metrics(up.record)
    assert len(replayed) == len(live) == recorded_run.steps
    # the monitor holds a row until every agent's ack and link report is in, so every column must agree
    cols = ("t", "sim_time", "deliveries", "deliveries_total", "requests", "commits", "acks", "links", "lambda2", "eta")
    assert [[r[c] for c in cols] for r in replayed] == [[r[c] for c in cols] for r in live]
    for name in ("metrics.csv", "links.csv", "positions.csv"):  # byte for byte
        assert (tmp_path / "replayed" / up.run_id / name).read_bytes() == (up.record / name).read_bytes(), name


def test_record_joins_a_live_run_and_writes_only_what_the_run_sent(tmp_path, live_run):
    """``morph-sim record`` joins a running run over its endpoint (the operator's credentials found in the run
    directory, the configuration asked of the monitor): every message it writes was sent in the run (the run's own
    recording, ``up --bus-record``, holds it), none twice, ticks in order."""
    whole = tmp_path / "whole.mbr"
    up = live_run("joined", "--steps", "100000", "--mode", "paced", "--period", "0.05", *FEW_ROBOTS,
                  "--bus-record", str(whole))
    rows = up.record / "metrics.csv"
    up.wait_until(lambda: rows.exists() and rows.read_text().count("\n") > 5, 60, "the run's first rows")
    rec = subprocess.run([sys.executable, "-m", "morph_sim.cli", "record", "--run-id", up.run_id, "--endpoint",
                          up.endpoint, "--out", str(tmp_path / "joined.mbr"), "--timeout", "3", "--output-dir",
                          str(up.output_dir)], capture_output=True, text=True, timeout=120)
    assert up.stop() is not None  # the run's end closes its recording
    assert rec.returncode == 0, rec.stderr[-2000:]
    assert rec.stderr.startswith(f"recording run {up.run_id} (tiny, 100000 steps)"), rec.stderr
    assert rec.stdout.strip().splitlines()[-1].startswith("recorded ")
    header, joined = read_record(tmp_path / "joined.mbr")
    assert header["run_id"] == up.run_id and header["config"]["steps"] == 100000
    joined = list(joined)
    sent = {(s.key, s.sender, s.seq) for s in read_record(whole)[1]}
    # (the client also takes the monitor's own publications, its metric streams and events, which the monitor's
    # recording leaves out: a replay makes them again)
    frames = [(s.key, s.sender, s.seq) for s in joined if s.sender != "monitor"]
    assert frames and set(frames) <= sent and len(set(frames)) == len(frames)
    ticks = [tick_number(s.payload) for s in joined if s.key.endswith("/sim/tick")]
    assert len(ticks) >= 10 and ticks == sorted(ticks)  # three seconds of a paced run, in order
