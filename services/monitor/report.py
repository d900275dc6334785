"""Markdown report of one or more run records, with figures and an animation of the warehouse.

Reads only the record files (``manifest.json``, ``metrics.csv``, ``events.jsonl``, ``snapshots/``,
``positions.csv``, ``links.csv``, ``summary.json``), so a report can be made long after the run, for a record written
by a live monitor, a restarted one or ``morph-sim replay``. Figures: cumulative deliveries, delivery rate with fault
windows shaded, links over time, W heatmaps with the AGV/picker blocks, link-lifetime histogram; a GIF with the
coordination links drawn (stable green, new, pruned red dashed — the renderer's colours).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.metrics import measures as M
from services.monitor.recorder import read_snapshots

log = logging.getLogger("morph_sim.report")

RATE_WINDOW = 50


@dataclass
class Record:
    """One run record, loaded."""

    dir: Path
    manifest: dict
    rows: list[dict]
    events: list[dict]
    summary: dict | None
    n_agvs: int
    n_agents: int
    name: str = ""
    gaps: list[tuple[int, int]] = field(default_factory=list)
    #: what reading the record left out: a last line its writer never finished (see :func:`record_lines`)
    notes: list[str] = field(default_factory=list)

    def column(self, name: str) -> np.ndarray:
        return np.array([float(r[name]) if r.get(name) not in (None, "") else math.nan for r in self.rows])

    @property
    def t(self) -> np.ndarray:
        return np.array([int(r["t"]) for r in self.rows])

    def fault_windows(self) -> list[tuple[float, float, str]]:
        """(start tick, end tick, label) of every fault window, from the events (open windows end with the run)."""
        from services.monitor.faultwindows import FaultWindows

        end = float(self.t[-1] + 1) if self.rows else 0.0
        return FaultWindows(self.events).windows(end)

    def crashes(self) -> list[tuple[float, str]]:
        """(tick, agent) of every crash that happened: the supervisor's ``agent.crash`` events, one per kill or pause
        (a planned crash that never came, or the restart that follows one, is not a crash)."""
        return [(float(e["t"]), str((e.get("details") or {}).get("agent", "?"))) for e in self.events
                if e.get("kind") == "agent.crash" and e.get("t") is not None]

    def positions(self) -> dict[int, np.ndarray]:
        path = self.dir / "positions.csv"
        out: dict[int, np.ndarray] = {}
        if not path.exists():
            return out
        n = self.n_agents
        for number, line in record_lines(path, self.notes):
            try:
                cells = line.split(",")
                if len(cells) != 1 + 4 * n:
                    raise ValueError(f"{len(cells)} fields, not 1 + 4 × {n} robots")
                out[int(cells[0])] = np.array(cells[1:], dtype=np.int64).reshape(4, n)
            except ValueError as exc:
                raise _bad_line(path, number, exc) from None
        return out

    def links(self) -> dict[int, np.ndarray]:
        path = self.dir / "links.csv"
        out: dict[int, np.ndarray] = {}
        if not path.exists():
            return out
        n = self.n_agents
        for number, line in record_lines(path, self.notes):
            t, _, pairs = line.partition(",")
            A = np.zeros((n, n), dtype=bool)
            try:
                for p in pairs.split():
                    i, j = map(int, p.split("-"))
                    if not (0 <= i < n and 0 <= j < n):
                        raise ValueError(f"link {p} names a robot outside 0..{n - 1}")
                    A[i, j] = A[j, i] = True
                out[int(t)] = A
            except ValueError as exc:
                raise _bad_line(path, number, exc) from None
        return out


def record_lines(path: Path, notes: list[str]) -> list[tuple[int, str]]:
    """(line number, text) of every whole line of a record file. The writers end every line with a newline and a
    restarted monitor trims an unfinished one before it appends, so only the last line can be unfinished: its
    writer was stopped mid-line (killed, or the disk was full). That line is left out, and ``notes`` says so; the
    lines before it are the record as it was. A file that is not UTF-8 is refused naming the byte."""
    from services.inputs import input_file

    data = input_file(path, "run_dir", limit=None).read_bytes()
    end = data.rfind(b"\n") + 1
    try:
        text = data[:end].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"run_dir: {path} is not UTF-8 text (byte {exc.start})") from None
    lines = text.splitlines()
    if end < len(data):
        notes.append(f"{path} (line {len(lines) + 1})")
    return list(enumerate(lines, start=1))


def _bad_line(path: Path, number: int, why: object) -> ValueError:
    return ValueError(f"run_dir: {path} line {number} is not a line of this table ({why}); the record is damaged")


def _json_file(path: Path):
    from services.inputs import read_text

    try:
        return json.loads(read_text(path, "run_dir"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"run_dir: {path} is not JSON ({exc})") from None


def load(directory: Path) -> Record:
    d = Path(directory)
    if not (d / "metrics.csv").exists():
        raise ValueError(f"run_dir: {d} holds no run record (metrics.csv missing)")
    notes: list[str] = []
    manifest = _json_file(d / "manifest.json") if (d / "manifest.json").exists() else {}
    events = []
    if (d / "events.jsonl").exists():
        for number, line in record_lines(d / "events.jsonl", notes):
            try:
                event = json.loads(line)
            except json.JSONDecodeError as exc:
                raise _bad_line(d / "events.jsonl", number, exc) from None
            if not isinstance(event, dict):
                raise _bad_line(d / "events.jsonl", number, "not a JSON object")
            events.append(event)
    summary = _json_file(d / "summary.json") if (d / "summary.json").exists() else None
    fleet = manifest.get("fleet", {})
    rows = _metrics(d / "metrics.csv", notes)
    rec = Record(d, manifest, rows, events, summary, int(fleet.get("agvs", 0)),
                 int(fleet.get("agvs", 0)) + int(fleet.get("pickers", 0)), name=d.name, notes=notes)
    rec.gaps = [(int(e["details"]["first"]), int(e["details"]["last"])) for e in events
                if e.get("kind") == "monitor.gap" and "first" in e.get("details", {})]
    return rec


def network_text(rec: Record) -> tuple[str, str]:
    """(network, hand-overs) of the report's table: the run's network profile and its access-point hand-overs (the
    ``net.handover`` events of the record), or an ideal network without any."""
    profile = rec.manifest.get("config", {}).get("network")
    if not profile:
        return "ideal (none)", "–"
    handovers = sum(e.get("kind") == "net.handover" for e in rec.events)
    return str(profile), str(handovers)


def numbers(rec: Record) -> dict:
    """The report's table of one record (what a restarted monitor's record must reproduce apart from its gap)."""
    d = rec.column("deliveries")
    links = rec.column("links")
    return {
        "rows": len(rec.rows),
        "deliveries": int(np.nansum(d)),
        "deliveries_total": int(rec.column("deliveries_total")[-1]) if rec.rows else 0,
        "mean_links": float(np.nanmean(links)) if rec.rows else math.nan,
        "final_links": int(links[-1]) if rec.rows and not math.isnan(links[-1]) else None,
        "gaps": rec.gaps,
    }


# -- figures --------------------------------------------------------------------------------------------------------
# Fault windows get colours of their own (not the runs' line colours) and one legend entry each, so overlapping
# windows stay apart; crashes are black dotted lines marked with the agent that was killed.
_WINDOW_COLOURS = ("#e41a1c", "#ff7f00", "#984ea3", "#4daf4a", "#a65628", "#f781bf", "#377eb8", "#999999")


def _shade(ax, recs: list[Record]) -> None:
    many = len(recs) > 1
    k = 0
    for rec in recs:
        who = f"{rec.name}: " if many else ""
        for a, b, label in rec.fault_windows():
            colour = _WINDOW_COLOURS[k % len(_WINDOW_COLOURS)]
            ax.axvspan(a, b, facecolor=colour, alpha=0.18, edgecolor=colour, lw=0.8,
                       label=f"{who}fault {label} [{a:g}, {b:g})")
            k += 1
        for i, (a, b) in enumerate(rec.gaps):
            ax.axvspan(a, b + 1, color="grey", alpha=0.3, hatch="//", label=f"{who}record gap" if i == 0 else None)
        for i, (t, agent) in enumerate(rec.crashes()):
            ax.axvline(t, color="black", lw=0.9, ls=":", label=f"{who}agent crash" if i == 0 else None)
            ax.annotate(f"agent {agent}", (t, 1.0), xycoords=("data", "axes fraction"), fontsize=6, rotation=90,
                        ha="right", va="top")


def _legend(ax) -> None:
    """The legend beside the axes (never over a curve); savefig(bbox_inches="tight") keeps it in the image."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)


def figures(recs: list[Record], out: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths: dict[str, Path] = {}

    def save(fig, name: str) -> None:
        p = out / f"{name}.png"
        fig.savefig(p, dpi=110, bbox_inches="tight")
        plt.close(fig)
        paths[name] = p

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for rec in recs:
        ax.plot(rec.t, np.nancumsum(rec.column("deliveries")), label=rec.name)
    _shade(ax, recs)
    ax.set(xlabel="tick", ylabel="deliveries", title="Cumulative deliveries")
    _legend(ax)
    save(fig, "deliveries")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for rec in recs:
        d = np.nan_to_num(rec.column("deliveries"))
        ax.plot(rec.t, M.rolling_rate(d, RATE_WINDOW), label=rec.name)
    _shade(ax, recs)
    ax.set(xlabel="tick", ylabel=f"deliveries / step ({RATE_WINDOW}-step window)", title="Delivery rate")
    _legend(ax)
    save(fig, "delivery_rate")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for rec in recs:
        ax.plot(rec.t, rec.column("links"), label=rec.name)
    _shade(ax, recs)
    ax.set(xlabel="tick", ylabel="undirected links", title="Coordination links")
    _legend(ax)
    save(fig, "links")

    for k, rec in enumerate(recs):
        snaps = read_snapshots(rec.dir)
        if snaps:
            ts = sorted(snaps)
            pick = sorted({ts[0], ts[len(ts) // 3], ts[2 * len(ts) // 3], ts[-1]})
            # one colour scale for every panel (the colourbar is theirs); no state received yet: light grey
            vmax = max([1e-9] + [float(np.nanmax(snaps[t]["W"])) for t in pick if np.isfinite(snaps[t]["W"]).any()])
            cmap = matplotlib.colormaps["viridis"].with_extremes(bad="#d9d9d9")
            fig, axes = plt.subplots(1, len(pick), figsize=(3.2 * len(pick) + 1.0, 3.4), squeeze=False,
                                     layout="constrained")
            for ax, t in zip(axes[0], pick):
                W = snaps[t]["W"]
                im = ax.imshow(W, cmap=cmap, vmin=0, vmax=vmax)
                b = rec.n_agvs - 0.5
                ax.axhline(b, color="white", lw=1)
                ax.axvline(b, color="white", lw=1)
                ax.set_title(f"W at t={t}", fontsize=9)
                centres = [(rec.n_agvs - 1) / 2, rec.n_agvs + (rec.n_agents - rec.n_agvs - 1) / 2]  # of the blocks
                ax.set_xticks(centres, ["AGV", "picker"])
                ax.set_yticks(centres, ["AGV", "picker"] if ax is axes[0][0] else ["", ""])
                ax.set_xlabel("to agent", fontsize=8)
            axes[0][0].set_ylabel("from agent", fontsize=8)
            fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="W (coordination weight)")
            fig.suptitle(f"{rec.name}: W snapshots (white lines: AGV / picker blocks; grey: no state yet)",
                         fontsize=10)
            p = out / f"w_heatmaps_{k}.png"
            fig.savefig(p, dpi=110)
            plt.close(fig)
            paths[f"w_heatmaps_{k}"] = p

    fig, ax = plt.subplots(figsize=(7, 3.5))
    lifetimes = []
    for rec in recs:
        links = rec.links()
        if not links:
            continue
        tracker = M.LinkTracker(rec.n_agents)
        for t in sorted(links):
            tracker.update(links[t], tick=t)
        life, censored = tracker.lifetimes()
        if life.size:
            lifetimes.append((rec.name, life, censored))
    if lifetimes:
        # one set of bins for every run, and outlines for several runs, so no run's bars hide another's
        top = max(float(life.max()) for _, life, _ in lifetimes)
        bins = np.linspace(0, max(top, 1.0), 31)
        many = len(lifetimes) > 1
        for i, (name, life, censored) in enumerate(lifetimes):
            colour = f"C{i}"
            for part, what, hatch in ((life[~censored], "pruned", None), (life[censored], "alive at end", "//")):
                ax.hist(part, bins=bins, histtype="step" if many else "bar", color=colour, hatch=hatch, lw=1.2,
                        alpha=1.0 if many else (0.9 if hatch is None else 0.45),
                        label=f"{name}: {what}" if many else what)
    ax.set(xlabel="link lifetime (ticks)", ylabel="links", title="Link lifetimes", yscale="log")
    if lifetimes:
        _legend(ax)
    save(fig, "link_lifetimes")
    return paths


GIF_MIN_WIDTH = 640  # px: a warehouse GIF a person can read without zooming (cells of a large layout stay >= 12 px)


def _metrics(path: Path, notes: list[str]) -> list[dict[str, str]]:
    """The rows of ``metrics.csv`` (:func:`record_lines`), each with exactly the header's columns."""
    import csv

    numbered = record_lines(path, notes)
    if not numbered:
        return []
    rows = csv.reader(line for _, line in numbered)
    header = next(rows)
    out = []
    for (number, _), cells in zip(numbered[1:], rows):
        if len(cells) != len(header) or "t" in header and not cells[header.index("t")].isdigit():
            raise _bad_line(path, number, f"{len(cells)} fields, the header has {len(header)}")
        out.append(dict(zip(header, cells)))
    return out


def warehouse_gif(rec: Record, path: Path, *, max_frames: int = 200, cell_px: int | None = None) -> int | None:
    """GIF of the robots with their coordination links, from ``positions.csv`` and ``links.csv``, with a legend of
    the glyphs and colours; ``cell_px`` defaults to what makes it at least GIF_MIN_WIDTH wide. None if absent."""
    from services.world.layout import layout_for, named_sizes
    from services.world.render import RECORD_LEGEND, Frame, link_statuses, write_gif

    positions, links = rec.positions(), rec.links()
    ticks = sorted(set(positions) & set(links))
    if not ticks:
        return None
    config = rec.manifest.get("config", {})
    lay = layout_for(named_sizes()[config.get("scale", "tiny")][0])
    if cell_px is None:
        cell_px = max(12, math.ceil((GIF_MIN_WIDTH - 1) / lay.W) - 1)
    stride = max(1, math.ceil(len(ticks) / max_frames))
    shown = ticks[::stride]
    is_agv = np.arange(rec.n_agents) < rec.n_agvs
    aps = dead = None
    if config.get("network"):  # the run's Wi-Fi: its access points and dead zones on every frame
        from services.faults.network import NetworkModel, load_profile

        try:
            model = NetworkModel(load_profile(config["network"]), lay)
            aps, dead = model.access_points, model.dead
        except ValueError as exc:  # a profile file that is gone or changed: the frames without it
            log.warning("report: network %s not drawn: %s", config["network"], exc)

    def frames():
        prev = None
        for t in shown:
            x, y, heading, carrying = positions[t]
            A = links[t]
            yield Frame(height=lay.H, width=lay.W, highway=lay.highway, goals=np.array(lay.goals, dtype=np.int64),
                        shelves=~lay.highway, requested=np.zeros_like(lay.highway),
                        agent_x=x, agent_y=y, agent_dir=heading, is_agv=is_agv, carrying=carrying > 0,
                        step=t, caption=f"{rec.name}  links {int(np.triu(A, 1).sum())}",
                        links=link_statuses(A, prev), access_points=aps, dead_zone=dead)
            prev = A

    # the legend names every glyph the frames draw: the run's network adds its access points and dead zones
    legend = (*RECORD_LEGEND, *(("access_point",) if aps is not None and len(aps) else ()),
              *(("dead_zone",) if dead is not None and dead.any() else ()))
    return write_gif(frames(), path, fps=8, cell_px=cell_px, legend=legend)


def write_report(run_dirs: list[Path], out: Path, *, gif: bool = True, notes: list[str] | None = None) -> Path:
    """Write ``out/report.md`` with its figures; returns the Markdown path. ``notes`` gets the unfinished last lines
    that were left out of the records (:func:`record_lines`)."""
    recs = [load(Path(d)) for d in run_dirs]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = figures(recs, out)
    lines = ["# morph-sim run report", ""]
    lines += ["| run | scale | policy | seed | network | steps | deliveries | mean links | final links | hand-overs "
              "| gaps |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for rec in recs:
        c = rec.manifest.get("config", {})
        nb = numbers(rec)
        gaps = ", ".join(f"{a}–{b}" for a, b in nb["gaps"]) or "none"
        network, handovers = network_text(rec)
        lines.append(f"| {rec.name} | {c.get('scale')} | {c.get('policy')} | {c.get('seed')} | {network} | "
                     f"{nb['rows']} | {nb['deliveries']} | {nb['mean_links']:.1f} | {nb['final_links']} | "
                     f"{handovers} | {gaps} |")
    lines.append("")
    for rec in recs:
        windows = rec.fault_windows()
        if windows:
            lines.append(f"Fault windows of {rec.name}: " + ", ".join(f"{lab} [{a:g}, {b:g})" for a, b, lab in windows))
    lines += ["", "## Figures", ""]
    titles = {"deliveries": "Cumulative deliveries", "delivery_rate": "Delivery rate (fault windows shaded)",
              "links": "Links over time", "link_lifetimes": "Link-lifetime histogram"}
    for name, p in figs.items():
        title = titles.get(name, "W heatmap snapshots (AGV/picker blocks)")
        lines += [f"### {title}", "", f"![{title}]({p.name})", ""]
    if gif:
        lines += ["## Warehouse animation", ""]
        for k, rec in enumerate(recs):
            g = out / f"warehouse_{k}.gif"
            count = warehouse_gif(rec, g)
            if count is None:
                lines.append(f"{rec.name}: no animation — the record has no positions.csv/links.csv "
                             "(recorded by an older monitor)")
            else:
                lines += [f"![{rec.name}]({g.name})", "",
                          f"{count} frames; the legend under the map names every glyph and colour."]
        lines.append("")
    cut = list(dict.fromkeys(note for rec in recs for note in rec.notes))  # a table read twice is named once
    if cut:
        lines += ["", f"Left out of the records: the unfinished last line of {', '.join(cut)} (its writer stopped "
                  "mid-line: a killed monitor or a full disk)."]
    if notes is not None:
        notes.extend(cut)
    md = out / "report.md"
    md.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return md
