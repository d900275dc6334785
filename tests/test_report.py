"""``morph-sim report`` and the run record's robustness."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time

import numpy as np
import pytest
from PIL import Image

from morph_sim.local import run_local
from services.monitor.recorder import Recorder, read_metrics
from services.monitor.report import load, numbers, write_report
from services.runconfig import RunConfig

from _procs import FEW_ROBOTS, run_processes


def test_the_report_renders_every_figure_and_the_gif(tmp_path):
    # 80 ticks: the fault window, W snapshots at 0, 40 and the end, and a GIF frame per tick (under its 200-frame cap)
    config = RunConfig(run_id="rep", scale="tiny", steps=80, policy="morph", output_dir=tmp_path, snapshot_every=40)
    asyncio.run(run_local(config))
    with open(config.record_dir / "events.jsonl", "a") as f:  # a fault window to shade
        f.write('{"kind": "fault.set", "t": 30, "details": {"fault_id": "f1"}}\n')
        f.write('{"kind": "fault.healed", "t": 60, "details": {"fault_id": "f1"}}\n')
    md = write_report([config.record_dir], tmp_path / "report")
    text = md.read_text()
    for name in ("deliveries", "delivery_rate", "links", "w_heatmaps_0", "link_lifetimes"):
        assert f"({name}.png)" in text
        with Image.open(tmp_path / "report" / f"{name}.png") as im:
            assert im.size[0] > 300 and len(np.unique(np.asarray(im.convert("L")))) > 20  # a drawn figure, not blank
    assert "f1 [30, 60)" in text
    with Image.open(tmp_path / "report" / "warehouse_0.gif") as gif:
        assert gif.n_frames == config.steps
    rec = load(config.record_dir)
    assert numbers(rec)["deliveries"] == int(read_metrics(config.record_dir)[-1]["deliveries_total"])
    assert len(rec.positions()) == config.steps + 1 and len(rec.links()) == config.steps
    with pytest.raises(ValueError, match="run_dir"):
        load(tmp_path)


def test_a_restarted_recorder_trims_a_cut_line_and_resumes(tmp_path):
    config = RunConfig(run_id="cut", output_dir=tmp_path)
    rec = Recorder(config)
    rec.row({"t": 0, "deliveries": 1, "deliveries_total": 1})
    rec.row({"t": 1, "deliveries": 0, "deliveries_total": 1})
    rec.close()
    with open(config.record_dir / "metrics.csv", "a") as f:
        f.write("2,2.0,1")  # the monitor was killed mid-line
    again = Recorder(config)
    assert again.resume_from == (1, 1)
    again.close()
    assert [r["t"] for r in read_metrics(config.record_dir)] == ["0", "1"]


def _ticks_on_disk(path):
    return {int(ln.split(",", 1)[0]) for ln in path.read_text().splitlines() if ln[:1].isdigit()}


@pytest.mark.parametrize("flush_chars", [1 << 20, 5_000, 300])
def test_a_killed_recorder_never_leaves_a_row_on_disk_without_its_positions_and_links(tmp_path, monkeypatch,
                                                                                       flush_chars):
    # The monitor makes row t two ticks after it took the positions of tick t. Whatever moment a kill comes, what
    # is on disk then must be a record a restarted monitor can continue without a hole before its declared gap.
    import services.monitor.recorder as recorder_module

    monkeypatch.setattr(recorder_module, "FLUSH_CHARS", flush_chars)
    config = RunConfig(run_id="kill", scale="tiny", output_dir=tmp_path)
    rec = Recorder(config)
    n = config.n_agvs + config.n_pickers
    A = np.eye(n, dtype=bool) | np.eye(n, k=1, dtype=bool)
    zeros = [0] * n
    for t in range(400):
        rec.positions(t, zeros, zeros, zeros, zeros)
        if t >= 2:
            rec.row({"t": t - 2, "deliveries": 0, "deliveries_total": 0, "w_mean": 0.123456789}, links=A)
            rows = {int(r["t"]) for r in read_metrics(config.record_dir)}
            assert rows <= _ticks_on_disk(config.record_dir / "positions.csv"), t
            assert rows <= _ticks_on_disk(config.record_dir / "links.csv"), t
    # the last flush the kill left behind is where a restarted monitor goes on from
    on_disk = max({int(r["t"]) for r in read_metrics(config.record_dir)}, default=-1)
    again = Recorder(config)
    assert (again.resume_from or (-1, 0))[0] == on_disk
    again.close()
    assert (on_disk > 0) == (flush_chars < 1 << 20)  # the size rule flushed on its own, before a second was up


# the monitor is killed after KILL_AT rows on disk, which lag the run by up to a second: the run is paused at tick
# ~100-470, then a gap, then the rest recorded
STEPS = 700
KILL_AT = 50


def test_a_monitor_killed_and_restarted_mid_run_leaves_a_record_equal_apart_from_the_gap(tmp_path, live_run):
    # three robots: what the record keeps across the monitor's restart does not depend on the fleet
    up = live_run("killed", "--steps", str(STEPS), "--seed", "5", "--policy", "morph", *FEW_ROBOTS,
                  output_dir=tmp_path / "live")
    up.wait_for_endpoint()
    procs: dict = {}
    deadline = time.monotonic() + 30
    while len(procs) < 2 and time.monotonic() < deadline:  # the sim and the monitor, before the rows are waited for
        procs = dict(run_processes(up.pid, "sim", "monitor"))
        time.sleep(0.02)
    assert set(procs) == {"sim", "monitor"}, procs
    up.wait_for_rows(KILL_AT)
    # looked up again now that the run has rows: at its start a process may show a role's command line for a moment
    # and be gone (the monitor seen first was once no longer there to be killed); a listing takes milliseconds
    procs = dict(run_processes(up.pid, "sim", "monitor"))
    # The run is paused while its monitor is killed, so that it is killed mid-run: this small lockstep run makes
    # ~450 ticks/s and may run up to MONITOR_WINDOW ticks ahead of the rows on disk, so by the time a test had read
    # KILL_AT rows and looked for the monitor the sim was seen to have finished (and closed its endpoint on the
    # monitor's successor).
    os.kill(procs["sim"].pid, signal.SIGSTOP)
    try:
        os.kill(procs["monitor"].pid, signal.SIGKILL)  # no chance to flush or close; the supervisor restarts it
    finally:
        os.kill(procs["sim"].pid, signal.SIGCONT)
    # the record is incomplete (the gap): up says so and fails
    assert up.wait(120) == 1, up.stdout() + up.stderr()
    last_line = (up.stdout() + up.stderr()).strip().splitlines()[-1]
    assert "record is incomplete" in last_line and "declared lost: monitor restarted" in last_line, last_line
    killed = load(tmp_path / "live" / "killed")
    assert len(killed.gaps) == 1, killed.events
    first, last = killed.gaps[0]
    config = RunConfig(run_id="calm", scale="tiny", agvs=2, pickers=1, steps=STEPS, seed=5, policy="morph",
                       output_dir=tmp_path)
    asyncio.run(run_local(config))
    calm = read_metrics(config.record_dir)
    rows = read_metrics(killed.dir)
    ts = [int(r["t"]) for r in rows]
    assert ts == [t for t in range(STEPS) if not first <= t <= last]  # every row once, only the gap missing
    assert KILL_AT <= first and last < STEPS - 1, (first, last)  # rows before the gap, and after it again
    assert rows == [calm[t] for t in ts]  # every column, the cumulative ones included
    # every table outside the gap, byte for byte (positions: one line per tick, the final tick included)
    for name, ticks in (("links.csv", ts), ("positions.csv", ts + [STEPS])):
        ours = [ln for ln in (killed.dir / name).read_text().splitlines() if ln[:1].isdigit()]
        theirs = {int(ln.split(",", 1)[0]): ln for ln in (config.record_dir / name).read_text().splitlines()
                  if ln[:1].isdigit()}
        assert ours == [theirs[t] for t in ticks if t in theirs and not first <= t <= last], name
    summary = json.loads((killed.dir / "summary.json").read_text())
    assert summary["steps"] == len(rows) and summary["deliveries_total"] == int(rows[-1]["deliveries_total"])
    assert summary["deliveries_total"] == int(calm[-1]["deliveries_total"])
    assert summary["mean_links"] == pytest.approx(sum(int(r["links"]) for r in rows) / len(rows))
    lost = sum(int(calm[t]["deliveries"]) for t in range(first, last + 1))
    print(f"gap rows {first}..{last} ({last - first + 1} ticks, {lost} deliveries)")


# palette entries that are not glyphs of their own: floors and lines around the glyphs, the header, words
_NOT_GLYPHS = {"background", "rack_floor", "grid", "header", "text", "outline", "heading", "goal_mark", "target"}


def _colours(pixels: np.ndarray) -> set[str]:
    from services.world.render import COLORS

    name = {(r << 16) | (g << 8) | b: key for key, (r, g, b) in COLORS.items()}
    rgb = pixels.reshape(-1, 3).astype(np.int64)
    return {name[c] for c in np.unique((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).tolist() if c in name}


def test_the_report_names_each_runs_network_and_hand_overs_and_the_gif_legend_names_every_glyph(tmp_path, capsys):
    """A Wi-Fi run and an ideal-network run side by side: the table tells them apart, with the hand-overs the run
    itself reported; every glyph the GIF draws (access points and dead zones included) is in its legend."""
    import re

    from morph_sim.cli import main
    from services.world.layout import layout_for, named_sizes
    from services.world.render import image_size

    said = {}
    for name, flags in (("wifi", ["--network", "wifi-legacy-roaming"]), ("ideal", [])):
        assert main(["run", "--quiet", "--scale", "tiny", "--steps", "20", "--policy", "full", "--run-id", name,
                     "--output-dir", str(tmp_path), *flags]) == 0
        said[name] = capsys.readouterr().out
    handovers = int(re.search(r"^network wifi-legacy-roaming: (\d+) hand-overs", said["wifi"], re.M).group(1))
    assert handovers > 0
    assert main(["report", str(tmp_path / "wifi"), str(tmp_path / "ideal"), "--out", str(tmp_path / "report")]) == 0
    lines = (tmp_path / "report" / "report.md").read_text().splitlines()
    head = next(line for line in lines if line.startswith("| run |"))
    cols = [c.strip() for c in head.strip("|").split("|")]
    table = {cells[0]: dict(zip(cols, cells)) for line in lines if line.startswith(("| wifi |", "| ideal |"))
             for cells in [[c.strip() for c in line.strip("|").split("|")]]}
    assert (table["wifi"]["network"], table["wifi"]["hand-overs"]) == ("wifi-legacy-roaming", str(handovers))
    assert (table["ideal"]["network"], table["ideal"]["hand-overs"]) == ("ideal (none)", "–")

    lay = layout_for(named_sizes()["tiny"][0])
    for k, network_glyphs in ((0, {"access_point", "dead_zone"}), (1, set())):
        drawn, named = set(), set()
        with Image.open(tmp_path / "report" / f"warehouse_{k}.gif") as gif:
            cell = (gif.size[0] - 1) // lay.W - 1
            map_height = image_size(lay.H, lay.W, cell, True, ())[1]  # the frame above its legend band
            for i in range(gif.n_frames):
                gif.seek(i)
                rgb = np.asarray(gif.convert("RGB"))
                drawn |= _colours(rgb[:map_height])
                named |= _colours(rgb[map_height:])
        assert drawn & {"access_point", "dead_zone"} == network_glyphs
        assert drawn - _NOT_GLYPHS <= named, f"drawn but not in the legend: {drawn - _NOT_GLYPHS - named}"
