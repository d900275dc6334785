"""The Python API: run and load morph-sim from a notebook or a script (docs/notebook-example.md).

Everything takes the configuration model the CLI uses, :class:`~services.runconfig.RunConfig` (or its fields as
keywords), and gives back a :class:`Record`: the run record on disk with its manifest as a typed object and one table
per file. Tables are pandas DataFrames when pandas is installed (``pip install 'morph-sim[data]'``), otherwise plain
dicts of numpy arrays (column -> array) with the same columns; :meth:`Record.frame` insists on a DataFrame.

=====================  =================================================================================
``run(config)``        the services in this process over the in-process bus (= ``morph-sim run``)
``up(config)``         a distributed run: sim, one process per agent, monitor over Zenoh (= ``morph-sim up``)
``episode(config)``    one episode on the lab's pure core (no bus, no record): summary and per-tick series
``sweep(grid, seeds)`` any grid × seeds (= ``morph-sim sweep``), locally or on a Dask cluster
``load(path)``         any record: a run (``run``/``up``/``replay``), a study (``experiment scale|ablation``), a sweep
=====================  =================================================================================
"""

from __future__ import annotations

import asyncio
import csv
import json
import threading
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from services.metrics import catalogue
from services.runconfig import RunConfig

DATA_HINT = "pip install 'morph-sim[data]'"

#: the documented columns of each table (docs/notebook-example.md); ``episodes`` and ``ticks`` depend on the record
RUN_TABLES: dict[str, tuple[str, ...]] = {
    "metrics": catalogue.COLUMNS,
    "events": ("t", "sim_time", "kind", "source", "details", "wall_time"),
    "links": ("t", "i", "j"),
    "positions": ("t", "agent", "x", "y", "heading", "carrying"),
}

def has_pandas() -> bool:
    try:
        import pandas  # noqa: F401
    except ImportError:
        return False
    return True


_warned = False


def _table(columns: Mapping[str, Sequence[Any] | np.ndarray]):
    """A DataFrame if pandas is installed, else the dict of numpy arrays (with a one-time hint)."""
    cols = {k: (v if isinstance(v, np.ndarray) else _array(v)) for k, v in columns.items()}
    if has_pandas():
        import pandas as pd

        return pd.DataFrame(cols)
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(f"pandas is not installed: tables are dicts of numpy arrays; for DataFrames {DATA_HINT}",
                      stacklevel=3)
    return cols


def _array(values: Sequence[Any]) -> np.ndarray:
    vals = list(values)
    if vals and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in vals):
        return np.asarray(vals, dtype=np.int64)
    if vals and all(isinstance(v, (int, float, np.number)) or v is None for v in vals) and \
            not all(isinstance(v, bool) for v in vals):
        return np.asarray([np.nan if v is None else v for v in vals], dtype=float)
    out = np.empty(len(vals), dtype=object)
    out[:] = vals
    return out


class Manifest(BaseModel):
    """The manifest of a record, typed. Every record has ``run_id`` and ``kind``; the rest depends on the kind:
    a run's ``config`` is a RunConfig (:attr:`run_config`), a sweep's ``plan`` a SweepPlan (:attr:`sweep_plan`)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    run_id: str
    kind: str = "run"  # run | scale | ablation | sweep
    config: dict[str, Any] = {}
    git_revision: str | None = None
    command_line: list[str] = []
    versions: dict[str, Any] = {}
    seeds: Any = None
    started_at: float | None = None
    host: str | None = None
    fleet: dict[str, int] | None = None
    plan: dict[str, Any] | None = None

    @property
    def run_config(self) -> RunConfig | None:
        """The RunConfig of a run record (None for a study or a sweep)."""
        return RunConfig(**self.config) if self.kind == "run" and self.config else None

    @property
    def sweep_plan(self):
        from morph_sim.lab.sweep import SweepPlan

        return SweepPlan(**self.plan) if self.kind == "sweep" and self.plan else None


@dataclass
class Record:
    """One record on disk. Tables load lazily; ``tables`` names those this kind of record has."""

    path: Path
    manifest: Manifest

    @property
    def kind(self) -> str:
        return self.manifest.kind

    @property
    def is_run(self) -> bool:
        return self.kind == "run"

    @property
    def tables(self) -> tuple[str, ...]:
        if self.is_run:
            return tuple(RUN_TABLES)
        if self.kind == "sweep":
            return ("episodes", "comparison")
        return ("episodes", "ticks", "summary")

    def table(self, name: str):
        """The table ``name`` (DataFrame with pandas, else dict of numpy arrays)."""
        if name not in self.tables:
            raise KeyError(f"table: {self.kind} record {self.path} has {', '.join(self.tables)}, not {name!r}")
        return getattr(self, name)

    def frame(self, name: str):
        """The table ``name`` as a pandas DataFrame; ImportError saying how to get pandas otherwise."""
        if not has_pandas():
            raise ImportError(f"Record.frame needs pandas: {DATA_HINT} (without it, Record.table({name!r}) "
                              "returns a dict of numpy arrays)")
        return self.table(name)

    @property
    def totals(self) -> dict[str, Any]:
        """``summary.json`` of a run (totals at the end), or {} if the run did not finish."""
        p = self.path / "summary.json"
        return json.loads(p.read_text()) if p.exists() else {}

    # -- run records ------------------------------------------------------------------------------------------------
    @cached_property
    def metrics(self):
        """One row per tick: :data:`RUN_TABLES` ``["metrics"]``; empty cells are NaN."""
        self._need_run("metrics")
        cols: dict[str, list] = {c: [] for c in RUN_TABLES["metrics"]}
        with open(self.path / "metrics.csv", newline="", encoding="utf-8") as f:
            for row in csv.DictReader(f):
                for c in cols:
                    cell = row.get(c, "")
                    cols[c].append(np.nan if cell in ("", None) else float(cell))
        out = {c: np.asarray(v, dtype=float) for c, v in cols.items()}
        out["t"] = out["t"].astype(np.int64)
        return _table(out)

    @cached_property
    def events(self):
        """One row per event: tick ``t``, ``sim_time``, ``kind`` (run.started, fault.set, …), ``source``,
        ``details`` (a dict), ``wall_time``."""
        self._need_run("events")
        rows = []
        p = self.path / "events.jsonl"
        if p.exists():
            for line in p.read_text(encoding="utf-8").splitlines():
                if line.strip():
                    rows.append(json.loads(line))
        cols = {c: [r.get(c) for r in rows] for c in RUN_TABLES["events"]}
        out = {c: _array(v) for c, v in cols.items()}
        out["details"] = _objects(cols["details"])
        out["kind"] = _objects(cols["kind"])
        out["source"] = _objects(cols["source"])
        return _table(out)

    @cached_property
    def links(self):
        """One row per undirected link per row ``t``: ``t``, ``i`` < ``j`` (robot ids)."""
        self._need_run("links")
        t, i, j = [], [], []
        p = self.path / "links.csv"
        if p.exists():
            for line in p.read_text(encoding="utf-8").splitlines():
                tick, _, pairs = line.partition(",")
                for pair in pairs.split():
                    a, b = pair.split("-")
                    t.append(int(tick))
                    i.append(int(a))
                    j.append(int(b))
        return _table({"t": np.asarray(t, dtype=np.int64), "i": np.asarray(i, dtype=np.int64),
                       "j": np.asarray(j, dtype=np.int64)})

    @cached_property
    def positions(self):
        """One row per robot per tick: ``t``, ``agent``, cell ``x``, ``y``, ``heading``, ``carrying`` (0/1)."""
        self._need_run("positions")
        fleet = self.manifest.fleet or {}
        n = int(fleet.get("agvs", 0)) + int(fleet.get("pickers", 0))
        data = []
        p = self.path / "positions.csv"
        if p.exists():
            for line in p.read_text(encoding="utf-8").splitlines():
                if line.strip():
                    data.append([int(v) for v in line.split(",")])
        arr = np.asarray(data, dtype=np.int64).reshape(-1, 1 + 4 * n) if data else np.zeros((0, 1 + 4 * n), np.int64)
        rows = arr.shape[0]
        block = lambda k: arr[:, 1 + k * n:1 + (k + 1) * n].reshape(-1)  # noqa: E731 - row-major: tick, then agent
        return _table({"t": np.repeat(arr[:, 0], n), "agent": np.tile(np.arange(n, dtype=np.int64), rows),
                       "x": block(0), "y": block(1), "heading": block(2), "carrying": block(3)})

    def snapshots(self) -> dict[int, dict[str, np.ndarray]]:
        """W and A matrices by tick (``snapshots/``)."""
        from services.monitor.recorder import read_snapshots

        self._need_run("snapshots")
        return read_snapshots(self.path)

    def _need_run(self, what: str) -> None:
        if not self.is_run:
            raise KeyError(f"{what}: a {self.kind} record has {', '.join(self.tables)}")

    # -- studies and sweeps ----------------------------------------------------------------------------------------
    @cached_property
    def episodes(self):
        """One row per episode. Sweep: the grid's axes, ``seed`` and the sweep's metrics (its ``results.csv``, with
        the episodes finished so far). Study: each episode's summary (``scale``, ``condition``, ``seed``,
        ``deliveries``, ``mean_links``, …)."""
        if self.kind == "sweep":
            from morph_sim.lab.sweep import METRICS, SweepPlan, _read_done, tidy_rows

            plan = SweepPlan(**(self.manifest.plan or {}))
            rows = tidy_rows(plan, _read_done(self.path / "episodes.jsonl"))
            cols = [*plan.axes, "seed", *METRICS]
            return _table({c: [r.get(c) for r in rows] for c in cols})
        if self.is_run:
            raise KeyError(f"episodes: a run record has {', '.join(self.tables)}")
        summaries = [json.loads(p.read_text()) for p in sorted((self.path / "episodes").glob("*/summary.json"))]
        keys: list[str] = []
        for s in summaries:
            keys += [k for k in s if k not in keys]
        return _table({k: [s.get(k) for s in summaries] for k in keys})

    @cached_property
    def ticks(self):
        """Study records: every episode's per-tick series, long form: ``episode`` (its key), ``t`` and the
        lab's tick table (the catalogue's names and meanings: ``deliveries`` per tick, ``deliveries_total``,
        ``links``, …)."""
        if self.kind in ("run", "sweep"):
            raise KeyError(f"ticks: a {self.kind} record has {', '.join(self.tables)}")
        cols: dict[str, list] = {"episode": []}
        for p in sorted((self.path / "episodes").glob("*/ticks.csv")):
            with open(p, newline="", encoding="utf-8") as f:
                for row in csv.DictReader(f):
                    cols["episode"].append(p.parent.name)
                    for k, v in row.items():
                        cols.setdefault(k, []).append(float(v) if v != "" else np.nan)
        out = {k: (_objects(v) if k == "episode" else np.asarray(v, dtype=float)) for k, v in cols.items()}
        if "t" in out:
            out["t"] = out["t"].astype(np.int64)
        return _table(out)

    @cached_property
    def comparison(self):
        """Sweep records: the Welch comparison table (one row per condition)."""
        if self.kind != "sweep":
            raise KeyError(f"comparison: a {self.kind} record has {', '.join(self.tables)}")
        from morph_sim.lab.sweep import SweepPlan, _read_done, compare, tidy_rows

        plan = SweepPlan(**(self.manifest.plan or {}))
        rows = compare(plan, tidy_rows(plan, _read_done(self.path / "episodes.jsonl")))
        keys = list(rows[0]) if rows else [*plan.axes, "n"]
        return _table({k: [r.get(k) for r in rows] for k in keys})

    @cached_property
    def summary(self):
        """Study records: the study's ``summary.csv`` (one row per condition and scale, as written)."""
        if self.kind in ("run", "sweep"):
            raise KeyError(f"summary: a {self.kind} record has {', '.join(self.tables)}")
        with open(self.path / "summary.csv", newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        keys = list(rows[0]) if rows else []
        return _table({k: [_number(r[k]) for r in rows] for k in keys})


def _objects(values: Sequence[Any]) -> np.ndarray:
    out = np.empty(len(values), dtype=object)
    out[:] = list(values)
    return out


def _number(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text




def load(path: str | Path) -> Record:
    """Load any record directory: a run (``runs/<id>`` of ``run``/``up``/``replay``), a study or a sweep."""
    path = Path(path)
    mpath = path / "manifest.json"
    if not mpath.exists():
        raise FileNotFoundError(f"path: {path} is not a record (no manifest.json)")
    data = json.loads(mpath.read_text())
    if "kind" not in data:
        if not (path / "metrics.csv").exists():
            raise ValueError(f"path: {path} has a manifest but neither metrics.csv nor a kind")
        data["kind"] = "run"
    return Record(path, Manifest(**data))


# -- running --------------------------------------------------------------------------------------------------------
def config(base: RunConfig | Mapping[str, Any] | None = None, **fields: Any) -> RunConfig:
    """A RunConfig from another one and/or fields, validated like the CLI (ValueError naming the field)."""
    values: dict[str, Any] = {}
    if isinstance(base, RunConfig):
        values.update(base.model_dump())
    elif base is not None:
        values.update(base)
    values.update(fields)
    return RunConfig.coerce(values)


def _in_fresh_loop(coro_factory):
    """asyncio.run, also from inside a running loop (a Jupyter kernel): then in a helper thread."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(coro_factory())
    box: dict[str, Any] = {}

    def target():
        try:
            box["value"] = asyncio.run(coro_factory())
        except BaseException as exc:  # handed to the caller's thread
            box["error"] = exc

    th = threading.Thread(target=target, name="morph-sim-run")
    th.start()
    th.join()
    if "error" in box:
        raise box["error"]
    return box["value"]


#: what a run record directory may hold (services/monitor/recorder.py, the supervisor's credentials and logs, a
#: report): ``overwrite=True`` removes a directory only when everything in it is one of these
RECORD_ENTRIES = frozenset({"manifest.json", "metrics.csv", "events.jsonl", "snapshots", "positions.csv", "links.csv",
                            "summary.json", "credentials", "logs", "report"})


def _claim(cfg: RunConfig, overwrite: bool) -> None:
    """Make ``cfg``'s record directory this run's, as the CLI does: an existing one is refused (ValueError naming
    ``run_id``), so a second call with the same id never writes into the first run's record; ``overwrite`` removes
    the old record wholly first (a run cannot be continued: its world restarts at tick 0)."""
    import shutil

    from morph_sim.commands.up import claim_record_dir

    directory = cfg.record_dir
    if overwrite and directory.is_dir():
        strangers = sorted(p.name for p in directory.iterdir() if p.name not in RECORD_ENTRIES)
        if strangers:
            raise ValueError(f"run_id: {directory} is not a run record (it holds {', '.join(strangers[:3])}); "
                             "overwrite removes only a run record")
        shutil.rmtree(directory)
    claim_record_dir(directory, how="choose another run_id, remove it, or pass overwrite=True")


def run(base: RunConfig | Mapping[str, Any] | None = None, *, overwrite: bool = False, **fields: Any) -> Record:
    """Run the services in this process over the in-process bus (``morph-sim run``); returns the run's record.
    A run id that already has a record is refused (ValueError naming ``run_id``) unless ``overwrite=True``, which
    removes that record wholly before the run starts.

    >>> rec = run(policy="full", scale="tiny", steps=100, seed=1, output_dir="runs")
    """
    from morph_sim.local import run_local

    cfg = config(base, **fields)
    _claim(cfg, overwrite)
    _in_fresh_loop(lambda: run_local(cfg, record=True))
    return load(cfg.record_dir)


def up(base: RunConfig | Mapping[str, Any] | None = None, *, overwrite: bool = False, **fields: Any) -> Record:
    """A distributed run on this machine (``morph-sim up``): one OS process per agent; returns the run's record.
    Raises RuntimeError if the run did not complete (its record is kept). An existing run id is refused as by
    :func:`run` (``overwrite=True`` removes its record first)."""
    import shutil

    from services.supervisor.launcher import StartError, Supervisor

    cfg = config(base, **fields)
    _claim(cfg, overwrite)
    try:
        supervisor = Supervisor(cfg)
    except (StartError, ValueError):
        shutil.rmtree(cfg.record_dir, ignore_errors=True)  # nothing started: the run id stays free, as in the CLI
        raise
    code = _in_fresh_loop(supervisor.run)
    if code != 0:
        raise RuntimeError(f"up: run {cfg.run_id} did not complete (exit {code}); record: {cfg.record_dir}")
    return load(cfg.record_dir)


@dataclass
class Episode:
    """One lab episode: its ``summary`` (deliveries, mean_links, …) and per-tick ``ticks`` table: ``t`` and the
    catalogue's row metrics under their names and meanings, as in a run's ``metrics`` (``deliveries`` per tick,
    ``deliveries_total``, ``requests``, ``commits``, ``links``, ``lambda2``, ``eta``, …), then the lab's own columns
    (``catalogue.LAB_TICKS``)."""

    config: RunConfig
    summary: dict[str, Any]
    ticks: Any


def episode(base: RunConfig | Mapping[str, Any] | None = None, *, loss: float = 0.0, **fields: Any) -> Episode:
    """One episode on the lab's pure core, from the same RunConfig (fields the pure core does not model are refused,
    naming the field); ``loss``: bursty message loss on the dispatch messages, percent."""
    from morph_sim.lab.runner import run_episode
    from morph_sim.lab.sweep import SweepPlan

    cfg = config(base, **fields)
    dumped = cfg.model_dump(mode="json")
    defaults = RunConfig(run_id="x").model_dump(mode="json")
    fixed = {k: v for k, v in dumped.items()
             if k not in ("run_id", "seed", "output_dir", "endpoint", "listen") and v != defaults[k]}
    plan = SweepPlan.build(seeds=[cfg.seed], base={**fixed, **({"faults.loss": loss} if loss else {})},
                           fiedler_every=1)
    res = run_episode(plan.episode_spec({}, cfg.seed))
    ticks = {"t": np.arange(res.spec.steps, dtype=np.int64), **{k: v.copy() for k, v in res.ticks.items()}}
    return Episode(cfg, dict(res.summary), _table(ticks))


def sweep(grid: Mapping[str, Sequence[Any]], seeds: Any = (1,), *, base: Mapping[str, Any] | None = None,
          engine: str = "lab", baseline: Mapping[str, Any] | None = None, out: str | Path = "runs",
          run_id: str | None = None, executor: str = "local", jobs: int = 2, scheduler: Any = None,
          progress: bool = False) -> Record:
    """Run a sweep (``morph-sim sweep``) and return its record: ``.episodes`` (tidy: axes, seed, metrics) and
    ``.comparison`` (Welch table). ``scheduler``: a Dask address, Client or LocalCluster with ``executor="dask"``.
    Calling again with the same ``run_id`` resumes (finished episodes are skipped)."""
    from morph_sim.lab.sweep import SweepPlan, run_sweep

    plan = SweepPlan.build(grid=grid, seeds=seeds, base=base, engine=engine, baseline=baseline)
    result = run_sweep(plan, out, run_id, executor=executor, jobs=jobs, scheduler=scheduler, progress=progress,
                       argv=[])
    return load(result.dir)


__all__ = ["DATA_HINT", "RUN_TABLES", "Episode", "Manifest", "Record", "RunConfig", "config", "episode", "has_pandas",
           "load", "run", "sweep", "up"]
