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
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from services.monitor.catalogue import COLUMNS  # per-tick columns; ``deliveries`` of step t come with tick t+1
from services.runconfig import RunConfig

FLUSH_SECONDS = 1.0


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
            for name in ("metrics.csv", "events.jsonl", "positions.csv", "links.csv"):
                _trim_partial_line(self.dir / name)  # a killed monitor may have left half a line
            rows = read_metrics(self.dir)
            last = rows[-1] if rows else None
            self.resume_from = (int(last["t"]), int(last["deliveries_total"] or 0)) if last else (-1, 0)
        self._metrics_file = open(metrics, "a", newline="", encoding="utf-8")
        self._csv = csv.writer(self._metrics_file)
        if fresh:
            self._csv.writerow(COLUMNS)
        self._events_file = open(self.dir / "events.jsonl", "a", encoding="utf-8")
        self.resumed = not fresh  # a restarted monitor appends to the record (it declares the gap)
        self._positions_file = open(self.dir / "positions.csv", "a", encoding="utf-8")
        self._links_file = open(self.dir / "links.csv", "a", encoding="utf-8")
        self._last_flush = time.monotonic()
        self.rows = 0
        self.closed = False

    @staticmethod
    def _write_json(path: Path, data: Any) -> None:
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n", encoding="utf-8")
        os.replace(tmp, path)  # atomic: a reader never sees half a file

    def row(self, values: dict[str, Any]) -> None:
        self._csv.writerow([_cell(values.get(c)) for c in COLUMNS])
        self.rows += 1
        self._maybe_flush()

    def event(self, data: dict[str, Any]) -> None:
        self._events_file.write(json.dumps(data, sort_keys=True, default=str) + "\n")
        self._maybe_flush()

    def positions(self, t: int, x, y, heading, carrying) -> None:
        self._positions_file.write(",".join(map(str, (t, *x, *y, *heading, *(int(c) for c in carrying)))) + "\n")

    def links(self, t: int, A: np.ndarray) -> None:
        pairs = np.argwhere(np.triu(A | A.T, k=1))
        self._links_file.write(f"{t}," + " ".join(f"{i}-{j}" for i, j in pairs) + "\n")

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
        if force or now - self._last_flush >= FLUSH_SECONDS:
            self._metrics_file.flush()
            self._events_file.flush()
            self._positions_file.flush()
            self._links_file.flush()
            self._last_flush = now

    def flush(self) -> None:
        self._maybe_flush(force=True)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.flush()
        self._metrics_file.close()
        self._events_file.close()
        self._positions_file.close()
        self._links_file.close()


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
