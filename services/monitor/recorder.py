"""The run record: ``runs/<run-id>/`` written incrementally, so a killed monitor loses at most a second.

Files:

* ``manifest.json`` — config, seeds, versions, git revision, command line, start time;
* ``metrics.csv`` — one row per tick (columns :data:`COLUMNS`), appended and flushed at least once a second;
* ``events.jsonl`` — one JSON object per event (run start/finish, faults, crashes, restarts, rejects …);
* ``snapshots/t<tick>.npz`` — periodic W and A matrices assembled from the agents' published state rows;
* ``positions.csv`` — per tick: every robot's x, y, heading and carrying flag (``t, x0…, y0…, dir0…, carry0…``);
* ``links.csv`` — per row t: the undirected links as ``i-j`` pairs separated by spaces (replays the topology);
* ``summary.json`` — totals written at the end of the run.

Every experiment table can be recomputed from these files alone.
"""

from __future__ import annotations

import csv
import json
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Callable

import numpy as np

from services.metrics.catalogue import COLUMNS  # per-tick columns; ``deliveries`` of step t come with tick t+1
from services.runconfig import RunConfig

FLUSH_SECONDS = 1.0
#: pending characters that make a flush happen before its second is up (a fast run keeps little in memory)
FLUSH_CHARS = 1 << 20


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def git_revision(path: Path | None = None) -> str | None:
    """The git commit of the source tree (with ``-dirty`` if modified), or None outside a checkout."""
    where = path or Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=5)
        if rev.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=where,
                               capture_output=True, text=True, timeout=5)
        return rev.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def manifest(config: RunConfig, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "run_id": config.run_id,
        "config": config.model_dump(mode="json"),
        "seeds": {
            "seed": config.seed,
            "warehouse": f"numpy RandomState({config.seed})",
            "agents": f"numpy default_rng(SeedSequence(entropy={config.seed}, spawn_key=(agent,)))",
        },
        "fleet": {"agvs": config.n_agvs, "pickers": config.n_pickers},
        "versions": {
            "morph_sim": _version("morph-sim"), "python": platform.python_version(), "numpy": np.__version__,
            "eclipse-zenoh": _version("eclipse-zenoh"), "msgpack": _version("msgpack"),
            "pydantic": _version("pydantic"),
        },
        "git_revision": git_revision(),
        "command_line": list(sys.argv),
        "host": platform.node(),
        "started_at": time.time(),
        **(extra or {}),
    }


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        return repr(round(value, 12))
    return value


class Recorder:
    """Writes one run record. Appends when the directory already holds one (a restarted monitor)."""

    def __init__(self, config: RunConfig, directory: Path | None = None, *, manifest_extra: dict | None = None):
        self.config = config
        self.dir = Path(directory or config.record_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / "snapshots").mkdir(exist_ok=True)
        mpath = self.dir / "manifest.json"
        if not mpath.exists():
            self._write_json(mpath, manifest(config, manifest_extra))
        metrics = self.dir / "metrics.csv"
        fresh = not metrics.exists() or metrics.stat().st_size == 0
        #: (last row t, its deliveries_total) of the record a restarted monitor continues, else None
        self.resume_from: tuple[int, int] | None = None
        if not fresh:
            _check_same_run(mpath, config)
            for name in ("metrics.csv", "events.jsonl", "positions.csv", "links.csv"):
                _trim_partial_line(self.dir / name)  # a killed monitor may have left half a line
            self.resume_from = _align_tables(self.dir)
        # Lines wait here, not in the files' own buffers, which reach the disk whenever they fill: the wide metrics
        # rows would get there long before the per-tick tables, and a killed monitor would leave rows on disk whose
        # positions never were. Each flush writes the tables in this order, metrics last, so every row on disk has
        # its positions and links on disk too (positions of tick t are taken before row t is made).
        self._files = {name: open(self.dir / name, "a", newline="", encoding="utf-8")
                       for name in ("positions.csv", "links.csv", "events.jsonl", "metrics.csv")}
        self._pending: dict[str, list[str]] = {name: [] for name in self._files}
        self._pending_chars = 0
        self._csv = csv.writer(_Lines(lambda line: self._add("metrics.csv", line)), lineterminator="\r\n")
        if fresh:
            self._csv.writerow(COLUMNS)
        self.resumed = not fresh  # a restarted monitor appends to the record (it declares the gap)
        self._last_flush = time.monotonic()
        self.rows = 0
        self.closed = False

    @staticmethod
    def _write_json(path: Path, data: Any) -> None:
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n", encoding="utf-8")
        os.replace(tmp, path)  # atomic: a reader never sees half a file

    def row(self, values: dict[str, Any], links: np.ndarray | None = None) -> None:
        """Row ``values["t"]`` of the metrics, with that row's coordination links when the run has them."""
        if links is not None:
            pairs = np.argwhere(np.triu(links | links.T, k=1)).tolist()  # Python ints format 3× faster
            self._add("links.csv", f"{values['t']}," + " ".join(f"{i}-{j}" for i, j in pairs) + "\n")
        self._csv.writerow([_cell(values.get(c)) for c in COLUMNS])
        self.rows += 1
        self._maybe_flush()

    def event(self, data: dict[str, Any]) -> None:
        self._add("events.jsonl", json.dumps(data, sort_keys=True, default=str) + "\n")
        self._maybe_flush()

    def positions(self, t: int, x, y, heading, carrying) -> None:
        self._add("positions.csv", ",".join(map(str, (t, *x, *y, *heading, *(int(c) for c in carrying)))) + "\n")

    def _add(self, name: str, line: str) -> None:
        self._pending[name].append(line)
        self._pending_chars += len(line)

    def snapshot(self, t: int, W: np.ndarray, A: np.ndarray) -> Path:
        path = self.dir / "snapshots" / f"t{t:07d}.npz"
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez_compressed(tmp, t=np.int64(t), W=W, A=A)
        os.replace(tmp, path)
        return path

    def summary(self, data: dict[str, Any]) -> None:
        self._write_json(self.dir / "summary.json", data)

    def _maybe_flush(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_flush >= FLUSH_SECONDS or self._pending_chars >= FLUSH_CHARS:
            failure: OSError | None = None
            for name, f in self._files.items():  # metrics last (see __init__)
                lines = self._pending[name]
                try:
                    if lines:
                        f.write("".join(lines))
                    f.flush()
                except OSError as exc:  # one table that cannot grow does not keep the others from what they hold
                    failure = failure or exc
                lines.clear()
            self._pending_chars = 0
            self._last_flush = now
            if failure is not None:
                raise failure

    def flush(self) -> None:
        self._maybe_flush(force=True)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.flush()
        finally:
            for f in self._files.values():
                f.close()


class _Lines:
    """The file-like end of the metrics csv.writer: it hands each formatted row to the recorder's pending lines."""

    def __init__(self, add: Callable[[str], None]):
        self.write = add


#: config fields that may differ between a run's monitor and its restarted successor (where it connects)
_PLACE_FIELDS = ("endpoint", "listen", "output_dir")


def _check_same_run(manifest_path: Path, config: RunConfig) -> None:
    """A record is continued only by a monitor of the same run: same id and same configuration (else ValueError)."""
    try:
        recorded = json.loads(manifest_path.read_text(encoding="utf-8")).get("config", {})
    except (OSError, ValueError):
        return  # no readable manifest: nothing to compare with (a monitor killed while starting)
    mine = config.model_dump(mode="json")
    differ = sorted(k for k in mine if k not in _PLACE_FIELDS and k in recorded and recorded[k] != mine[k])
    if differ:
        name = differ[0]
        raise ValueError(f"run_id: {manifest_path.parent} holds the record of another run with this id ({name} "
                         f"{recorded[name]!r} there, {mine[name]!r} here); choose another run id")


def _table_ts(path: Path) -> list[int]:
    if not path.exists():
        return []
    with open(path, encoding="utf-8") as f:
        return [int(line.split(",", 1)[0]) for line in f if line[:1].isdigit()]


def _keep_upto(path: Path, last: int) -> None:
    """Drop the lines of a per-tick table whose tick is beyond ``last`` (the header, if any, stays)."""
    if not path.exists():
        return
    with open(path, encoding="utf-8") as f:
        lines = f.readlines()
    kept = [ln for ln in lines if not ln[:1].isdigit() or int(ln.split(",", 1)[0]) <= last]
    if len(kept) != len(lines):
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text("".join(kept), encoding="utf-8")
        os.replace(tmp, path)


def _align_tables(directory: Path) -> tuple[int, int]:
    """Before a restarted monitor appends: cut metrics, links and positions back to the last tick all three hold
    (each was flushed at its own moment before the kill), so that the declared gap is the same for every table.
    Returns (last row t, its deliveries_total); (-1, 0) for a record without rows."""
    rows = read_metrics(directory)
    if not rows:
        return (-1, 0)
    last = int(rows[-1]["t"])
    links, positions = _table_ts(directory / "links.csv"), _table_ts(directory / "positions.csv")
    # (a table without any line was never written by this recorder's user: it does not hold the others back)
    last = min([last] + [table[-1] for table in (links, positions) if table])
    for name in ("metrics.csv", "links.csv", "positions.csv"):
        _keep_upto(directory / name, last)
    rows = [r for r in rows if int(r["t"]) <= last]
    return (last, int(rows[-1]["deliveries_total"] or 0)) if rows else (-1, 0)


def _trim_partial_line(path: Path) -> None:
    """Cut an unterminated last line (a write interrupted by a kill), so appended lines stay whole."""
    if not path.exists() or path.stat().st_size == 0:
        return
    data = path.read_bytes()
    if not data.endswith(b"\n"):
        with open(path, "r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)


def read_metrics(directory: Path) -> list[dict[str, str]]:
    """The per-tick rows of a record as dicts of strings."""
    with open(Path(directory) / "metrics.csv", newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def read_snapshots(directory: Path) -> dict[int, dict[str, np.ndarray]]:
    out = {}
    for path in sorted((Path(directory) / "snapshots").glob("t*.npz")):
        if ".tmp" in path.name:
            continue
        with np.load(path) as z:
            out[int(z["t"])] = {"W": z["W"], "A": z["A"]}
    return out


@dataclass
class RecordCheck:
    """What a finished run record says about itself (:func:`check_record`): ``problems`` empty means complete."""

    rows: int = 0
    deliveries: int | None = None  # the last row's deliveries_total
    final_links: int | None = None
    steps: int | None = None  # ticks the sim ran (its run.finished event)
    stopped_early: str | None = None  # why the sim ended before its steps (run.finished), if it did
    gaps: list[tuple[int, int]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return not self.problems


def check_record(directory: Path, steps: int) -> RecordCheck:
    """Check a run record against itself and the sim's own account of the run (``run.finished``): every row of the
    steps the sim ran, once and in order, a summary whose totals equal the rows, and the sim's deliveries."""
    directory = Path(directory)
    out = RecordCheck()
    try:
        rows = read_metrics(directory)
    except (OSError, csv.Error, UnicodeDecodeError) as exc:
        out.problems.append(f"metrics.csv cannot be read ({exc})")
        return out
    finished: dict[str, Any] | None = None
    try:
        with open(directory / "events.jsonl", encoding="utf-8") as f:
            for line in f:
                try:
                    event = json.loads(line)
                except ValueError:
                    continue
                if event.get("kind") == "run.finished" and event.get("source") == "sim":
                    finished = event.get("details") or {}
                elif event.get("kind") == "monitor.gap":
                    d = event.get("details") or {}
                    out.gaps.append((int(d.get("first", -1)), int(d.get("last", -1))))
    except OSError:
        pass
    out.rows = len(rows)
    if rows:
        last = rows[-1]
        out.deliveries = int(last["deliveries_total"] or 0)
        out.final_links = int(last["links"] or 0)
    if finished is None:
        out.problems.append("the record has no run.finished event of the sim")
        expected = steps
    else:
        out.steps = int(finished.get("steps", 0))
        out.stopped_early = finished.get("stopped_early")
        expected = out.steps
        if out.deliveries is not None and finished.get("deliveries") is not None \
                and int(finished["deliveries"]) != out.deliveries:
            out.problems.append(f"the rows end at {out.deliveries} deliveries, the sim counted "
                                f"{finished['deliveries']}")
    ts = [int(r["t"]) for r in rows]
    if ts != list(range(expected)):
        missing = sorted(set(range(expected)) - set(ts))
        if missing:
            declared = " (declared lost: monitor restarted)" if out.gaps else ""
            out.problems.append(f"{len(missing)} of {expected} rows missing, first {missing[0]}{declared}")
        else:
            out.problems.append(f"{len(ts)} rows for {expected} steps (duplicate or extra rows)")
    try:
        summary = json.loads((directory / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        out.problems.append("no summary.json")
        return out
    if summary.get("steps") != out.rows:
        out.problems.append(f"summary.json says {summary.get('steps')} steps, the record has {out.rows} rows")
    if out.deliveries is not None and summary.get("deliveries_total") != out.deliveries:
        out.problems.append(f"summary.json says {summary.get('deliveries_total')} deliveries, the rows "
                            f"{out.deliveries}")
    return out
