"""A grid of episodes as one resumable run record, with a progress bar: the one implementation behind
``morph-sim sweep`` and the studies ``experiment faults`` and ``experiment network``.

A run record ``<dir>/`` holds ``manifest.json`` (what the grid is: its ``plan``, plain data) and ``episodes.jsonl``
(one line per finished episode, appended and flushed as each finishes). Started again on the same directory with
the same plan, only the episodes missing from ``episodes.jsonl`` run; a different plan is refused
(:class:`RecordMismatch`), so a record never mixes two grids. Tables are computed from the record, in the plan's
order, so an interrupted and resumed grid gives the same tables as one that ran straight through.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MANIFEST = "manifest.json"
EPISODES = "episodes.jsonl"


class RecordMismatch(ValueError):
    pass


def read_done(path: Path) -> dict[str, dict]:
    """The finished episodes of ``episodes.jsonl`` by key; a half-written last line (a kill mid-write) is cut."""
    done: dict[str, dict] = {}
    if not path.exists():
        return done
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):  # a kill mid-write: drop the half line so appends stay whole
        with open(path, "r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)
    for line in path.read_text().splitlines():
        if line.strip():
            rec = json.loads(line)
            done[rec["key"]] = rec
    return done


def count_done(run_dir: str | Path) -> int:
    """Episodes already in a run record (what a resumed grid skips)."""
    return len(read_done(Path(run_dir) / EPISODES))


@dataclass
class GridRun:
    done: dict[str, dict]  # every finished episode's record by key (this call's and the earlier ones')
    ran: int  # episodes run by this call
    skipped: int  # episodes found in the record
    wall_s: float


def run_grid(run_dir: str | Path, *, kind: str, plan: Mapping[str, Any], tasks: Sequence[tuple[str, Any]],
             fn: Callable[[Any], dict], record: Callable[[Any, dict], dict] | None = None,
             executor: str = "local", jobs: int = 2, scheduler: Any = None,
             progress: bool | Callable[[int, int], None] = True, argv: Sequence[str] | None = None,
             manifest_extra: Mapping[str, Any] | None = None,
             extends: Callable[[Mapping[str, Any], Mapping[str, Any]], bool] | None = None) -> GridRun:
    """Run ``fn(task)`` for every (key, task) not yet in ``run_dir``'s record.

    ``fn`` is module-level (it is pickled to worker processes) and returns a dict with the task's ``key``;
    ``record(task, result)`` makes the line kept in ``episodes.jsonl`` (default: the result itself). ``plan`` is the
    grid's identity: a record made by another plan (or another ``kind``) is refused, naming ``kind`` and what
    differs, unless ``extends(stored plan, plan)`` says the new plan only adds episodes to the stored one (a sweep
    given more seeds): then the manifest takes the new plan and only the new episodes run.
    """
    from morph_sim.lab.executors import make_executor

    t0 = time.perf_counter()
    run_dir = Path(run_dir)
    from schemas.keys import validate_run_id

    validate_run_id(run_dir.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    plan = json.loads(json.dumps(plan))  # plain JSON data, as it is stored
    mpath = run_dir / MANIFEST
    if mpath.exists():
        stored = json.loads(mpath.read_text())
        if stored.get("kind") != kind:
            raise RecordMismatch(f"{kind}: {run_dir} holds a different {stored.get('kind') or 'run'}; give another "
                                 "--run-id or --out")
        if stored.get("plan") != plan:
            old = stored.get("plan") or {}
            if extends is None:
                raise RecordMismatch(f"{kind}: {run_dir} holds a different {kind}; give another --run-id or --out")
            if not extends(old, plan):
                differ = sorted(k for k in {*old, *plan} if old.get(k) != plan.get(k))
                raise RecordMismatch(f"{kind}: {run_dir} holds a different {kind} (not the same {', '.join(differ)}; "
                                     "only more seeds extend it); give another --run-id or --out")
            stored.update(plan=plan, **(manifest_extra or {}))
            tmp = mpath.with_suffix(".tmp")
            tmp.write_text(json.dumps(stored, indent=2))
            os.replace(tmp, mpath)
    else:
        from morph_sim.lab.suite import _git_revision, _versions

        manifest = {"run_id": run_dir.name, "kind": kind, "plan": plan, **(manifest_extra or {}),
                    "git_revision": _git_revision(), "versions": _versions(),
                    "command_line": list(argv) if argv is not None else sys.argv, "started_at": time.time()}
        tmp = mpath.with_suffix(".tmp")
        tmp.write_text(json.dumps(manifest, indent=2))
        os.replace(tmp, mpath)
    log = run_dir / EPISODES
    done = read_done(log)
    todo = [(key, task) for key, task in tasks if key not in done]
    if len({key for key, _ in tasks}) != len(tasks):
        raise ValueError(f"{kind}: two episodes of the grid share a key")
    skipped = len(tasks) - len(todo)
    bar = Progress(progress, len(tasks), skipped, label=kind)
    ex = make_executor(executor, jobs=jobs, scheduler=scheduler)
    try:
        with open(log, "a", encoding="utf-8") as f, bar:
            by_key = dict(todo)
            for res in ex.map_unordered(fn, [task for _, task in todo]):
                rec = record(by_key[res["key"]], res) if record is not None else res
                f.write(json.dumps(rec) + "\n")
                f.flush()
                done[res["key"]] = rec
                bar.advance()
    finally:
        ex.close()
    return GridRun(done, len(todo), skipped, time.perf_counter() - t0)


class Progress:
    """A progress bar on stderr (rich when installed), or a callback ``progress(done, total)``."""

    def __init__(self, progress, total: int, done: int, label: str = "sweep"):
        self.total, self.done, self.label = total, done, label
        self.callback = progress if callable(progress) else None
        self.enabled = bool(progress) and self.callback is None
        self._rich = None
        if self.enabled:
            try:
                from rich.console import Console
                from rich.progress import (
                    BarColumn,
                    MofNCompleteColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                    TimeRemainingColumn,
                )

                self._rich = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                      TimeRemainingColumn(), console=Console(stderr=True), transient=False)
            except ImportError:
                pass

    def __enter__(self):
        if self._rich is not None:
            self._rich.start()
            self._task = self._rich.add_task(self.label, total=self.total, completed=self.done)
        return self

    def advance(self) -> None:
        self.done += 1
        if self.callback is not None:
            self.callback(self.done, self.total)
        elif self._rich is not None:
            self._rich.update(self._task, completed=self.done)
        elif self.enabled:
            print(f"\r{self.label} {self.done}/{self.total}", end="" if self.done < self.total else "\n",
                  file=sys.stderr, flush=True)

    def __exit__(self, *exc):
        if self._rich is not None:
            self._rich.stop()


# -- statistics over the seeds of a grid point (the studies' tables) ---------------------------------------------
def mean_sd(values) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation of the finite values (None when there are none; sd None below two)."""
    import numpy as np

    v = np.array([x for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None, None
    return float(v.mean()), (float(v.std(ddof=1)) if v.size > 1 else None)


def welch(a, b) -> float | None:
    """Two-sided Welch p of two samples over seeds; None when undefined (fewer than two values, no variance)."""
    from morph_sim.lab.suite import _welch

    a = [x for x in a if x is not None]
    b = [x for x in b if x is not None]
    p = _welch(a, b)
    return None if p != p else p


def bonferroni(ps, alpha: float = 0.05) -> tuple[int, float]:
    """(number of comparisons, the per-test threshold for a family-wise ``alpha``)."""
    m = sum(p is not None for p in ps)
    return m, alpha / max(m, 1)


def p_text(p: float | None, threshold: float) -> str:
    """``p = 0.012``; **bold** below the Bonferroni threshold."""
    if p is None:
        return "p = –"
    s = f"{p:.2g}" if p < 0.001 else f"{p:.3f}".rstrip("0").rstrip(".") if p < 0.995 else "1.00"
    s = f"p = {s}"
    return f"**{s}**" if p < threshold else s
