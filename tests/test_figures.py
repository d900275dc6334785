"""Figures a person can decode without asking: every figure is checked as it is saved — nothing (title, legend,
colourbar) cut off by the figure's edge, no legend over the axes' data area — and every colour or marker that carries
meaning has a legend entry: one per fault window, a crash line per crash that happened, a labelled colourbar, and a
legend band under the warehouse frames. The report GIF is large enough to read (>= 600 px wide)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from PIL import Image

from morph_sim.local import run_local
from services.monitor.report import Record, load, write_report
from services.runconfig import RunConfig
from services.world.render import (
    COLORS,
    RECORD_LEGEND,
    WAREHOUSE_LEGEND,
    Frame,
    image_size,
    render_frame,
)


@pytest.fixture
def checked_figures(monkeypatch):
    """Every Figure.savefig first checks the layout; the figures seen are returned for more checks."""
    import matplotlib  # here, not at collection: every pytest worker imports this module, one runs it

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    seen: list[Figure] = []
    original = Figure.savefig

    def savefig(fig, *args, **kwargs):
        renderer = fig.canvas.get_renderer()
        fig.canvas.draw()
        tight = kwargs.get("bbox_inches") == "tight"  # the saved image grows to hold whatever lies outside
        page = fig.bbox
        texts = [t for t in [fig._suptitle] if t is not None and t.get_text()]
        legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
        for artist in texts + legends:
            box = artist.get_window_extent(renderer)
            if not tight:
                assert box.x0 >= page.x0 - 1 and box.x1 <= page.x1 + 1 and box.y0 >= page.y0 - 1 \
                    and box.y1 <= page.y1 + 1, f"{artist} cut off by the figure's edge: {box} vs {page}"
        for legend in legends:
            box = legend.get_window_extent(renderer)
            for ax in fig.axes:
                if ax.get_label() == "<colorbar>":
                    continue
                assert not box.overlaps(ax.bbox), f"a legend lies over the data of {ax.get_title()!r}"
        seen.append(fig)
        return original(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    return seen


def _record(events: list[dict], steps: int = 300) -> Record:
    rows = [{"t": str(t), "deliveries": "0", "links": "1"} for t in range(steps)]
    return Record(dir=None, manifest={}, rows=rows, events=events, summary=None, n_agvs=5, n_agents=8, name="r")


def test_crash_lines_are_the_crashes_that_happened_and_resets_close_only_their_window():
    rec = _record([
        {"kind": "fault.set", "t": 10, "details": {"fault_id": "a"}},
        {"kind": "fault.set", "t": 20, "details": {"fault_id": "b"}},
        {"kind": "fault.crash_planned", "t": 0, "details": {"fault_id": "k"}},  # a plan, not a crash
        {"kind": "fault.reset", "t": 30, "details": {"fault_id": "k"}},  # a crash plan cancelled: no window closes
        {"kind": "fault.reset", "t": 40, "details": {"fault_id": "a"}},
        {"kind": "agent.crash", "t": 50, "details": {"agent": 1, "tick": 50}},
        {"kind": "agent.restart", "t": 52, "details": {"agent": 1}},  # the same crash: no second line
    ])
    assert rec.crashes() == [(50.0, "1")]
    assert rec.fault_windows() == [(10.0, 40.0, "a"), (20.0, 300.0, "b")]


def test_report_figures_legend_every_window_and_crash_and_label_the_colourbar(tmp_path, checked_figures):
    config = RunConfig(run_id="figs", scale="tiny", steps=120, policy="morph", output_dir=tmp_path,
                       snapshot_every=40)
    asyncio.run(run_local(config))
    with open(config.record_dir / "events.jsonl", "a") as f:  # two overlapping fault windows and one crash
        for line in ({"kind": "fault.set", "t": 20, "details": {"fault_id": "loss"}},
                     {"kind": "fault.set", "t": 40, "details": {"fault_id": "lat"}},
                     {"kind": "fault.healed", "t": 60, "details": {"fault_id": "loss"}},
                     {"kind": "fault.healed", "t": 90, "details": {"fault_id": "lat"}},
                     {"kind": "agent.crash", "t": 70, "details": {"agent": 3, "tick": 70}}):
            f.write(json.dumps(line) + "\n")
    write_report([config.record_dir], tmp_path / "report")
    rate = next(fig for fig in checked_figures if fig.axes and fig.axes[0].get_title() == "Delivery rate")
    ax = rate.axes[0]
    handles, labels = ax.get_legend_handles_labels()
    assert "fault loss [20, 60)" in labels and "fault lat [40, 90)" in labels and "agent crash" in labels
    windows = [h for h, label in zip(handles, labels) if label.startswith("fault ")]
    assert len({tuple(h.get_facecolor()[:3]) for h in windows}) == 2  # overlapping windows in distinct colours
    heat = next(fig for fig in checked_figures if fig._suptitle is not None and "W snapshots" in fig._suptitle.get_text())
    bars = [a for a in heat.axes if a.get_label() == "<colorbar>"]
    assert len(bars) == 1 and bars[0].get_ylabel().startswith("W")

    from services.world.layout import layout_for, named_sizes

    lay = layout_for(named_sizes()["tiny"][0])
    with Image.open(tmp_path / "report" / "warehouse_0.gif") as gif:
        width, height = gif.size
    cell = (width - 1) // lay.W - 1
    assert width >= 600
    assert (width, height) == image_size(lay.H, lay.W, cell, True, RECORD_LEGEND)  # the frames carry the legend
    assert load(config.record_dir).crashes() == [(70.0, "3")]


def _frame() -> Frame:
    H, W = 6, 5
    highway = np.ones((H, W), bool)
    highway[1:4, 1:3] = False
    shelves = ~highway
    requested = np.zeros_like(shelves)
    requested[1, 1] = True
    return Frame(height=H, width=W, highway=highway, goals=np.array([[1, 5], [2, 5]]), shelves=shelves,
                 requested=requested, agent_x=np.array([0, 4, 3]), agent_y=np.array([0, 2, 4]),
                 agent_dir=np.array([0, 1, 2]), is_agv=np.array([True, True, False]),
                 carrying=np.array([False, True, False]), step=3, caption="legend test",
                 links=((0, 2, "stable"), (1, 2, "pruned")))


@pytest.mark.parametrize("legend", [WAREHOUSE_LEGEND, RECORD_LEGEND])
def test_warehouse_frames_carry_a_legend_of_their_glyphs_and_colours(legend):
    plain = np.asarray(render_frame(_frame(), cell_px=20))
    with_legend = np.asarray(render_frame(_frame(), cell_px=20, legend=legend))
    assert with_legend.shape[1] == plain.shape[1] and with_legend.shape[0] > plain.shape[0]
    assert (with_legend.shape[1], with_legend.shape[0]) == image_size(6, 5, 20, True, legend)
    assert np.array_equal(with_legend[: plain.shape[0]], plain)  # the map itself is unchanged
    band = with_legend[plain.shape[0]:].reshape(-1, 3)
    colours = {tuple(c) for c in band.tolist()}
    for key in legend:  # every entry's colour is drawn in the band (with its words beside it)
        colour = COLORS["goal" if key == "goal" else key]
        assert tuple(colour) in colours, key


def test_warehouse_cli_png_has_the_legend(tmp_path):
    from morph_sim.cli import main as cli_main

    png = tmp_path / "w.png"
    assert cli_main(["warehouse", "--scale", "tiny", "--steps", "5", "--png", str(png), "--no-progress"]) == 0
    from services.world.layout import layout_for, named_sizes

    lay = layout_for(named_sizes()["tiny"][0])
    with Image.open(png) as im:
        assert im.size == image_size(lay.H, lay.W, 20, True, WAREHOUSE_LEGEND)


def test_suite_plots_with_one_scale_keep_title_and_legend_in_view(tmp_path, checked_figures):
    from morph_sim.lab.suite import SuiteConfig, run_suite

    cfg = SuiteConfig(kind="ablation", preset="paper", scales=("tiny",), seeds=(42,), steps=40,
                      conditions=("morph", "v1"), dispatch="concurrent", shared_stream=False, radii=None, jobs=1,
                      fiedler_every=10)
    run_suite(cfg, tmp_path, "one", show_progress=False)
    assert len(checked_figures) == 3  # cumulative deliveries, link usage, bars: each passed the layout check
    assert all(fig.legends for fig in checked_figures)


def test_shift_plots_keep_legends_off_the_curves(tmp_path, checked_figures):
    from morph_sim.lab.shift import ShiftConfig, run_shift

    run_shift(ShiftConfig(scale="tiny", seeds=(1,), phase_steps=60, conditions=("proximity", "tsg"), jobs=1),
              tmp_path, "sh", show_progress=False)
    assert len(checked_figures) == 2
