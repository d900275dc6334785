"""Any sweep: a grid over RunConfig fields and fault parameters × seeds, with one tidy table and a Welch comparison.

A *condition* is one point of the grid (e.g. ``policy=tsg, faults.loss=10, scale=small``); every condition runs the
same seeds (common random numbers: condition A and B at seed s start from the same warehouse and the same agent
streams), so differences between conditions are not differences between draws. An *episode* is one condition at one
seed. Axes name:

* a :class:`~services.runconfig.RunConfig` field (``policy``, ``scale``, ``preset``, ``ablation``, ``radius``, ``steps``,
  ``seed`` is the ``seeds`` list …), validated by RunConfig itself: a bad value fails with the field's name;
* a fault parameter ``faults.<section>.<field>`` of :class:`~schemas.faults.FaultSpec` (``faults.loss.percent``,
  ``faults.latency.delay``, …); ``faults.loss`` is short for ``faults.loss.percent``.

Two engines run an episode:

* ``lab`` (default): the lab's pure core (:func:`morph_sim.lab.runner.run_episode`): fast, no bus. It models the
  fields that change the dynamics (scale, policy, preset, ablation, radius, seed, steps) and message loss on the
  dispatch messages (``faults.loss``, bursty Gilbert–Elliott as the fault experiment); anything else is refused with
  a line naming the field;
* ``services``: the real services over the in-process bus (``morph-sim run``), any RunConfig field and any fault
  parameter (applied from tick 0 by a fault schedule), each episode with its own run record.

The sweep's record ``<out>/<sweep-id>/``: ``manifest.json`` (the plan), ``episodes.jsonl`` (one line per finished
episode, appended and flushed as each finishes: an interrupted sweep started again with the same plan skips them),
``results.csv`` (+ ``results.parquet`` with pyarrow; rows in grid order, one per episode) and ``comparison.csv`` /
``comparison.md`` (per condition: mean ± std per metric over seeds, Welch p against the baseline condition).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import os
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from morph_sim.lab.faults_experiment import BURST as LAB_BURST  # the lab's bursty loss: mean burst, messages
from morph_sim.lab.grid import RecordMismatch, count_done, read_done as _read_done, run_grid  # noqa: F401 - API
from services.inputs import at_most, read_text
from services.metrics import catalogue
from services.runconfig import RunConfig

FAULTS = "faults."
ENGINES = ("lab", "services")
#: the metrics of an episode, columns of the tidy table after the condition and the seed (the catalogue's
#: per-episode metrics: the same meaning on both engines; ``lab_*`` are measured inside the gates, by the lab alone)
METRICS = catalogue.episode_metrics("deliveries", "mean_links", "requests", "commits", "lab_gate_decisions",
                                    "lab_mean_p_respond", "median_lifetime", "eta_mean")
#: RunConfig fields the lab engine models; others change nothing on the pure core and are refused there
LAB_FIELDS = ("scale", "policy", "policy_options", "preset", "ablation", "p", "radius", "seed", "steps", "network")
#: fields the sweep sets itself (per episode or per sweep)
MANAGED_FIELDS = ("run_id", "seed", "output_dir", "fault_schedule", "endpoint", "listen")
PARQUET_HINT = "pip install pyarrow (or 'morph-sim[data]') for results.parquet"
#: fewest seeds on each side for which the comparison gives a Welch p: with two, each variance rests on one degree of
#: freedom and one episode can swing p anywhere between significant and not
WELCH_MIN_N = 3
WELCH_WITHHELD = f"n < {WELCH_MIN_N}"
#: Most episodes (conditions × seeds) a sweep may plan. The plan lists every episode before the first runs, and the
#: record keeps a row for each; the largest study the project runs has a few thousand (the scale study: 2,600 a
#: scale), and 100,000 episodes of a few seconds each are days of CPU, so more is a slip like 1-100000000 for 1-100.
MAX_SWEEP_EPISODES = 100_000


# -- parsing ------------------------------------------------------------------------------------------------------
def parse_seeds(text: str | Sequence[int]) -> tuple[int, ...]:
    """``"1-20"``, ``"1,2,5"``, ``"1-3,7"`` or a list of ints; error names ``seeds``."""
    if not isinstance(text, str):
        values = list(text)
        at_most(len(values), MAX_SWEEP_EPISODES, "seeds", "seeds")
    else:
        parts: list[tuple[int, int]] = []
        for part in text.replace(" ", "").split(","):
            if not part:
                continue
            lo, dash, hi = part.partition("-")
            try:
                a, b = (int(lo), int(hi)) if dash else (int(part), int(part))
                if b < a:
                    raise ValueError
            except ValueError:
                raise ValueError(f"seeds: {part!r} is not a seed or a range like 1-20") from None
            parts.append((a, b))
        # counted before a range is spelled out: 1-100000000 would otherwise fill memory before any check
        at_most(sum(b - a + 1 for a, b in parts), MAX_SWEEP_EPISODES, "seeds", "seeds")
        values = [v for a, b in parts for v in range(a, b + 1)]
    out = []
    seen = set()
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"seeds: {v!r} is not a non-negative integer")
        if v not in seen:
            seen.add(v)
            out.append(v)
    if not out:
        raise ValueError("seeds: at least one seed")
    return tuple(out)


def _scalar(text: Any) -> Any:
    """A grid value from the command line: int, float, bool or string (TOML values arrive typed)."""
    if not isinstance(text, str):
        return text
    t = text.strip()
    if t.lower() in ("true", "false"):
        return t.lower() == "true"
    if t.lower() in ("none", "null"):
        return None
    for cast in (int, float):
        try:
            return cast(t)
        except ValueError:
            pass
    return t


def parse_grid_arg(text: str) -> tuple[str, list[Any]]:
    """``policy=morph,full,tsg`` -> (``policy``, [values])."""
    name, eq, values = text.partition("=")
    name = name.strip()
    if not eq or not name:
        raise ValueError(f"grid: {text!r} is not like field=v1,v2,…")
    vals = [_scalar(v) for v in values.split(",") if v.strip() != ""]
    if not vals:
        raise ValueError(f"{name}: no values in --grid {text!r}")
    return name, vals


def canonical_axis(name: str) -> str:
    if name == "faults.loss":
        return "faults.loss.percent"
    return name


def _fault_spec(params: Mapping[str, Any], seed: int):
    """The FaultSpec of one condition's fault parameters (``faults.a.b`` -> spec.a.b), or None without faults."""
    from schemas.faults import FaultSpec

    nested: dict[str, Any] = {}
    active = False
    for name, value in params.items():
        path = name[len(FAULTS):].split(".")
        node = nested
        for part in path[:-1]:
            node = node.setdefault(part, {})
        node[path[-1]] = value
    # faults.loss alone means the lab's loss model (bursty Gilbert–Elliott, mean burst 4), in both engines
    loss = nested.get("loss")
    if isinstance(loss, dict) and "model" not in loss:
        loss.update(model="gilbert_elliott", burst_length=loss.get("burst_length", LAB_BURST))
    # a section whose level is zero is no fault at all (loss 0 %, latency 0 s): the clean baseline of the sweep
    for section, body in list(nested.items()):
        level = body.get("percent", body.get("delay")) if isinstance(body, dict) else body
        if level in (0, 0.0, None) and section in ("loss", "latency", "duplicate", "reorder"):
            del nested[section]
        else:
            active = True
    if not active:
        return None
    try:
        return FaultSpec(**nested, id="sweep", seed=seed)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        loc = ".".join(str(p) for p in err.get("loc", ()))
        raise ValueError(f"faults.{loc}: {err.get('msg')}") from None


# -- the plan -----------------------------------------------------------------------------------------------------
class SweepPlan(BaseModel):
    """What to run: axes (name -> values, in order), seeds, fixed fields, the engine. Validated on construction."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    grid: dict[str, list[Any]] = Field(default_factory=dict)
    seeds: tuple[int, ...] = (1,)
    base: dict[str, Any] = Field(default_factory=dict)
    engine: Literal["lab", "services"] = "lab"
    baseline: dict[str, Any] | None = None
    fiedler_every: int = Field(default=10, ge=1, description="lab engine: λ₂ every this many ticks")

    @classmethod
    def build(cls, grid: Mapping[str, Sequence[Any]] | Sequence[tuple[str, Sequence[Any]]] = (), seeds: Any = (1,),
              base: Mapping[str, Any] | None = None, engine: str = "lab",
              baseline: Mapping[str, Any] | None = None, fiedler_every: int = 10) -> SweepPlan:
        """Normalise and check everything a sweep will meet, before any episode runs."""
        if engine not in ENGINES:
            raise ValueError(f"engine: unknown {engine!r} (choose from {', '.join(ENGINES)})")
        items = list(grid.items()) if isinstance(grid, Mapping) else list(grid)
        axes: dict[str, list[Any]] = {}
        for name, values in items:
            name = canonical_axis(str(name))
            if name in axes:
                raise ValueError(f"{name}: given twice in the grid")
            if name == "seed":
                raise ValueError("seed: sweep seeds with --seeds (every condition runs the same seeds)")
            if not isinstance(values, (list, tuple)) or not values:
                raise ValueError(f"{name}: the grid needs a list of values")
            axes[name] = [_scalar(v) for v in values]
        base_norm = {canonical_axis(k): _scalar(v) for k, v in (base or {}).items()}
        for name in base_norm:
            if name in axes:
                raise ValueError(f"{name}: both fixed and swept")
        seeds = parse_seeds(seeds)
        conditions = math.prod(len(values) for values in axes.values())  # before each is listed and checked
        at_most(conditions * len(seeds), MAX_SWEEP_EPISODES, "grid",
                f"episodes ({conditions:,} conditions × {len(seeds):,} seeds)")
        plan = cls(grid=axes, seeds=seeds, base=base_norm, engine=engine,
                   baseline=dict(baseline) if baseline else None, fiedler_every=fiedler_every)
        plan = plan.model_copy(update={"grid": {n: plan._normalise(n, vs) for n, vs in axes.items()},
                                       "base": {n: plan._normalise(n, [v])[0] for n, v in base_norm.items()}})
        for cond in plan.conditions():  # every combination must be a valid run (e.g. an ablation needs morph)
            plan.config(cond, plan.seeds[0])
            plan.fault_params(cond)
            if engine == "lab":
                plan.episode_spec(cond, plan.seeds[0])
        if plan.baseline is not None:
            unknown = [k for k in plan.baseline if k not in plan.grid]
            if unknown:
                raise ValueError(f"baseline: {unknown[0]} is not a grid axis")
            bl = {k: plan._normalise(k, [_scalar(v)])[0] for k, v in plan.baseline.items()}
            for k, v in bl.items():
                if v not in plan.grid[k]:
                    raise ValueError(f"baseline: {k}={v!r} is not one of the grid's values")
            plan = plan.model_copy(update={"baseline": bl})
        return plan

    def _normalise(self, name: str, values: list[Any]) -> list[Any]:
        """Each value as RunConfig (or FaultSpec) would store it; the error names the field."""
        out = []
        for v in values:
            if name.startswith(FAULTS):
                if len(name.split(".")) < 3:
                    raise ValueError(f"{name}: name a fault parameter like faults.loss.percent or faults.latency.delay")
                _fault_spec({name: v}, seed=0)  # validates the value (the error names the parameter)
                out.append(v)
                continue
            if name not in RunConfig.model_fields:
                raise ValueError(f"{name}: not a RunConfig field or a faults.* parameter "
                                 f"(fields: {', '.join(RunConfig.model_fields)})")
            if name in MANAGED_FIELDS:
                raise ValueError(f"{name}: set by the sweep itself, not sweepable")
            if self.engine == "lab" and name not in LAB_FIELDS:
                raise ValueError(f"{name}: the lab engine does not model it (it models "
                                 f"{', '.join(LAB_FIELDS)}); use --engine services")
            if name == "policy_options":  # a policy's options mean something only beside its policy: checked with it
                from services.runconfig import parse_policy_options

                out.append(parse_policy_options(v))
                continue
            cfg = RunConfig.coerce({"run_id": "sweep", name: v})
            out.append(cfg.model_dump(mode="json")[name])
        if len(set(map(json.dumps, out))) != len(out):
            raise ValueError(f"{name}: a value is given twice")
        return out

    # -- enumeration --------------------------------------------------------------------------------------------
    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(self.grid)

    def conditions(self) -> list[dict[str, Any]]:
        names = self.axes
        return [dict(zip(names, combo)) for combo in itertools.product(*(self.grid[n] for n in names))]

    def episodes(self) -> list[tuple[dict[str, Any], int]]:
        """Every (condition, seed), conditions in grid order, seeds in the given order."""
        return [(c, s) for c in self.conditions() for s in self.seeds]

    @staticmethod
    def condition_key(condition: Mapping[str, Any]) -> str:
        return ",".join(f"{k}={json.dumps(v)}" for k, v in condition.items()) or "-"

    def episode_key(self, condition: Mapping[str, Any], seed: int) -> str:
        return f"{self.condition_key(condition)}|seed={seed}"

    # -- one episode's inputs -----------------------------------------------------------------------------------
    def fields(self, condition: Mapping[str, Any]) -> dict[str, Any]:
        merged = {**self.base, **condition}
        return {k: v for k, v in merged.items() if not k.startswith(FAULTS)}

    def fault_params(self, condition: Mapping[str, Any]) -> dict[str, Any]:
        merged = {**self.base, **condition}
        return {k: v for k, v in merged.items() if k.startswith(FAULTS)}

    def config(self, condition: Mapping[str, Any], seed: int, run_id: str = "sweep") -> RunConfig:
        return RunConfig.coerce({**self.fields(condition), "seed": seed, "run_id": run_id})

    def episode_spec(self, condition: Mapping[str, Any], seed: int):
        """The lab's EpisodeSpec of one episode (lab engine); refuses what the pure core does not model."""
        from morph_sim.lab.runner import EpisodeSpec
        from services.policies.conditions import key_of

        cfg = self.config(condition, seed)
        from services.policies.coordinators import POLICIES

        # a policy from outside, or one with options of its own: built by name, as the services build it
        by_name = cfg.policy not in POLICIES or bool(cfg.policy_options) or (cfg.policy == "constant" and cfg.p != 0.25)
        lab_condition = cfg.policy if by_name else key_of(cfg.policy, cfg.ablation if cfg.policy == "morph" else None)
        loss = 0.0
        for name, value in self.fault_params(condition).items():
            if name == "faults.loss.percent":
                loss = float(value)
            elif (name, value) in (("faults.loss.model", "gilbert_elliott"), ("faults.loss.burst_length", LAB_BURST)):
                pass
            else:
                raise ValueError(f"{name}: the lab engine models message loss only (faults.loss, bursty); "
                                 "use --engine services")
        return EpisodeSpec(scale=cfg.scale, condition=lab_condition, seed=seed, steps=cfg.steps, preset=cfg.preset,
                           policy_name=cfg.policy if by_name else None,
                           policy_options=cfg.policy_arguments() if by_name else {},
                           radius=cfg.radius if lab_condition == "proximity" and not by_name else None,
                           fiedler_every=min(self.fiedler_every, cfg.steps), loss_percent=loss,
                           network=cfg.network)


# -- running one episode (module level: it is pickled to worker processes and Dask workers) ------------------------
@dataclass(frozen=True)
class EpisodeTask:
    key: str
    plan: dict[str, Any]  # SweepPlan.model_dump(): plain data, so any worker can rebuild it
    condition: dict[str, Any]
    seed: int
    record_dir: str | None = None  # services engine: where its run record goes


def run_task(task: EpisodeTask) -> dict[str, Any]:
    """One episode -> {"key", "metrics", "wall_s"}. Deterministic in (plan, condition, seed)."""
    plan = SweepPlan(**task.plan)
    t0 = time.perf_counter()
    if plan.engine == "lab":
        from morph_sim.lab.runner import run_episode

        res = run_episode(plan.episode_spec(task.condition, task.seed))
        values = episode_values(res.summary, res.ticks)
    else:
        values = _run_services(plan, task)
    return {"key": task.key, "metrics": {k: _clean(v) for k, v in values.items()}, "wall_s": time.perf_counter() - t0}


def _run_services(plan: SweepPlan, task: EpisodeTask) -> dict[str, Any]:
    import asyncio
    import hashlib

    from morph_sim.local import run_local

    root = Path(task.record_dir or "runs")
    run_id = "ep-" + hashlib.sha1(task.key.encode()).hexdigest()[:12]
    cfg = plan.config(task.condition, task.seed, run_id=run_id).model_copy(update={"output_dir": root})
    spec = _fault_spec(plan.fault_params(task.condition), seed=task.seed)
    if spec is not None:
        schedule = root / f"{run_id}.faults.toml"
        schedule.parent.mkdir(parents=True, exist_ok=True)
        schedule.write_text(_schedule_toml(spec))
        cfg = cfg.model_copy(update={"fault_schedule": schedule})
    if cfg.record_dir.exists():  # a half-written record of an interrupted sweep: this episode starts over
        import shutil

        shutil.rmtree(cfg.record_dir)
    result = asyncio.run(run_local(cfg, record=True))
    summary = json.loads((cfg.record_dir / "summary.json").read_text())
    rows = result.monitor.rows
    return {"deliveries": result.sim.deliveries, "mean_links": summary.get("mean_links"),
            "requests": sum(int(r.get("requests") or 0) for r in rows),
            "commits": sum(int(r.get("commits") or 0) for r in rows),
            "lab_gate_decisions": None, "lab_mean_p_respond": None,
            "median_lifetime": _median_lifetime(cfg, rows), "eta_mean": _mean([r.get("eta") for r in rows])}


def episode_values(summary: Mapping[str, Any], ticks: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """The sweep's metrics of one lab episode (its summary and tick table), as the services engine has them."""
    return {"deliveries": summary["deliveries"], "mean_links": summary["mean_links"],
            "requests": int(ticks["requests"].sum()), "commits": int(ticks["commits"].sum()),
            "lab_gate_decisions": summary["dispatch_decisions"], "lab_mean_p_respond": summary["mean_p_respond"],
            "median_lifetime": summary.get("median_lifetime"), "eta_mean": summary.get("eta_mean")}


def _median_lifetime(cfg: RunConfig, rows: Sequence[Mapping[str, Any]]) -> float | None:
    """The median link lifetime of a services run from its record's links of every row, as the lab measures it:
    plastic policies only; the paper rules' directed links are not in the record (it keeps undirected pairs)."""
    from services.metrics.measures import LinkTracker
    from services.policies.presets import load_preset

    if cfg.policy != "morph" or load_preset(cfg.preset).rules == "paper":
        return None
    n = cfg.n_agvs + cfg.n_pickers
    tracker = LinkTracker(n)
    path = cfg.record_dir / "links.csv"
    for line in path.read_text(encoding="utf-8").splitlines():
        tick, _, pairs = line.partition(",")
        A = np.zeros((n, n), dtype=bool)
        for pair in pairs.split():
            i, j = map(int, pair.split("-"))
            A[i, j] = True
        tracker.update(A, int(tick))
    life, _ = tracker.lifetimes()
    return float(np.median(life)) if life.size else None


def _schedule_toml(spec) -> str:
    """A one-command fault schedule: the condition's faults from tick 0 for the whole episode."""
    def emit(prefix: str, data: dict) -> list[str]:
        scalars = [f"{k} = {json.dumps(v)}" for k, v in data.items() if not isinstance(v, dict) and v is not None]
        lines = [f"[{prefix}]", *scalars]
        for k, v in data.items():
            if isinstance(v, dict):
                lines += emit(f"{prefix}.{k}", v)
        return lines

    return "[[at]]\ntick = 0\n" + "\n".join(emit("at.spec", spec.model_dump(mode="json", exclude_none=True))) + "\n"


def _mean(values) -> float | None:
    v = [float(x) for x in values if x not in (None, "")]
    return float(np.mean(v)) if v else None


def _clean(v: Any) -> Any:
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return None if math.isnan(f) else f
    return v


# -- the sweep ----------------------------------------------------------------------------------------------------
@dataclass
class SweepResult:
    plan: SweepPlan
    dir: Path
    rows: list[dict[str, Any]]  # the tidy table, grid order
    comparison: list[dict[str, Any]]
    ran: int  # episodes run by this call
    skipped: int  # episodes found in the record (resumed)
    wall_s: float
    files: dict[str, Path] = field(default_factory=dict)


def run_sweep(plan: SweepPlan, out: str | Path = "runs", sweep_id: str | None = None, *, executor: str = "local",
              jobs: int = 2, scheduler: Any = None, progress: bool | Callable[[int, int], None] = True,
              argv: Sequence[str] | None = None) -> SweepResult:
    """Run every episode of ``plan`` not already in ``<out>/<sweep_id>/episodes.jsonl``; write the tables."""
    t0 = time.perf_counter()
    sweep_id = sweep_id or default_sweep_id()
    run_dir = Path(out) / sweep_id
    plan_data = plan.model_dump(mode="json")
    tasks = [(key, EpisodeTask(key, plan_data, cond, seed, str(run_dir / "episodes")))
             for cond, seed in plan.episodes() for key in (plan.episode_key(cond, seed),)]

    def record(task: EpisodeTask, res: dict) -> dict:
        return {"key": res["key"], "condition": task.condition, "seed": task.seed, "metrics": res["metrics"],
                "wall_s": res["wall_s"]}

    grid = run_grid(run_dir, kind="sweep", plan=plan_data, tasks=tasks, fn=run_task, record=record,
                    executor=executor, jobs=jobs, scheduler=scheduler, progress=progress, argv=argv,
                    manifest_extra={"axes": list(plan.axes), "seeds": list(plan.seeds), "metrics": list(METRICS)},
                    extends=more_seeds)
    rows = tidy_rows(plan, grid.done)
    comparison = compare(plan, rows)
    files = write_tables(plan, run_dir, rows, comparison)
    return SweepResult(plan, run_dir, rows, comparison, grid.ran, grid.skipped, time.perf_counter() - t0, files)


def more_seeds(stored: Mapping[str, Any], plan: Mapping[str, Any]) -> bool:
    """Whether ``plan`` is the ``stored`` sweep with seeds added and nothing else changed: every episode already
    run is then an episode of the new plan too, with the same key and the same result (an episode depends on its
    condition and seed alone), so the record is kept and only the new seeds run."""
    old_seeds, new_seeds = list(stored.get("seeds") or ()), list(plan.get("seeds") or ())
    rest = lambda p: {k: v for k, v in p.items() if k != "seeds"}  # noqa: E731
    return rest(stored) == rest(plan) and set(old_seeds) < set(new_seeds)


def default_sweep_id() -> str:
    return time.strftime("sweep-%Y%m%d-%H%M%S", time.gmtime())


# -- tables -------------------------------------------------------------------------------------------------------
def tidy_rows(plan: SweepPlan, done: Mapping[str, dict]) -> list[dict[str, Any]]:
    """One row per finished episode, in grid order: the axes, ``seed``, then :data:`METRICS`."""
    rows = []
    for cond, seed in plan.episodes():
        rec = done.get(plan.episode_key(cond, seed))
        if rec is not None:
            rows.append({**cond, "seed": seed, **{m: rec["metrics"].get(m) for m in METRICS}})
    return rows


def _baseline_of(plan: SweepPlan, condition: Mapping[str, Any]) -> dict[str, Any] | None:
    if plan.baseline is not None:
        return {**condition, **plan.baseline}
    if not plan.axes:
        return None
    # default: MORPH when policy is swept (the existing studies' reference), else the first axis' first value
    if "policy" in plan.grid and "morph" in plan.grid["policy"]:
        return {**condition, "policy": "morph"}
    first = plan.axes[0]
    return {**condition, first: plan.grid[first][0]}


def compare(plan: SweepPlan, rows: list[dict[str, Any]], metrics: Sequence[str] = ("deliveries", "mean_links")
            ) -> list[dict[str, Any]]:
    """Per condition: n, mean and std (population, as the studies) of each metric, and Welch's p of deliveries
    against the baseline condition (the same condition with the baseline's value on its axis; seeds paired by
    design, but tested unpaired as the studies do)."""
    from morph_sim.lab.suite import _welch
    from services.metrics.measures import mean_std

    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(plan.condition_key({a: r[a] for a in plan.axes}), []).append(r)
    out = []
    for cond in plan.conditions():
        group = by.get(plan.condition_key(cond), [])
        if not group:
            continue
        row: dict[str, Any] = {**cond, "n": len(group)}
        for m in metrics:
            vals = [r[m] for r in group if r[m] is not None]
            ms = mean_std(vals) if vals else None
            row[f"{m}_mean"] = ms.mean if ms else None
            row[f"{m}_std"] = ms.std if ms else None
        base = _baseline_of(plan, cond)
        differs = {k: v for k, v in (base or {}).items() if cond.get(k) != v}
        row["baseline"] = ",".join(f"{k}={v}" for k, v in differs.items())
        ref = by.get(plan.condition_key(base), []) if base else []
        row["p_note"] = ""
        if base is None or base == cond or not ref:
            row["p_vs_baseline"] = None
        elif min(len(ref), len(group)) < WELCH_MIN_N:
            row["p_vs_baseline"] = None
            row["p_note"] = WELCH_WITHHELD
        else:
            p = _welch([r["deliveries"] for r in ref], [r["deliveries"] for r in group])
            row["p_vs_baseline"] = None if p != p else p
        out.append(row)
    return out


def comparison_markdown(plan: SweepPlan, rows: list[dict[str, Any]]) -> str:
    axes = list(plan.axes)
    head = [*axes, "n", "deliveries", "links", "baseline", "Welch p"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        d = "–" if r["deliveries_mean"] is None else f"{r['deliveries_mean']:.1f} ± {r['deliveries_std']:.1f}"
        lk = "–" if r["mean_links_mean"] is None else f"{r['mean_links_mean']:.1f} ± {r['mean_links_std']:.1f}"
        p = r["p_vs_baseline"]
        ps = (f"withheld ({r['p_note']})" if r.get("p_note") else "–" if p is None
              else (f"**{p:.3f}**" if p < 0.05 else f"{p:.3f}"))
        lines.append("| " + " | ".join([*(str(r[a]) for a in axes), str(r["n"]), d, lk,
                                         r["baseline"] or "–", ps]) + " |")
    lines += ["", f"{len(plan.seeds)} seeds per condition (the same seeds in every condition): "
                  f"{_seed_text(plan.seeds)}; engine `{plan.engine}`. Cells: mean ± population std over seeds; "
                  "Welch p of deliveries against the baseline (the condition that differs only in the named value)."]
    if any(r.get("p_note") == WELCH_WITHHELD for r in rows):
        lines.append(f"Welch p is withheld where a condition or its baseline has fewer than {WELCH_MIN_N} seeds: with "
                     "two, each variance rests on one degree of freedom and a single episode swings p anywhere; run "
                     "more seeds (the same --run-id with more --seeds extends the sweep).")
    return "\n".join(lines) + "\n"


def _seed_text(seeds: Sequence[int]) -> str:
    s = list(seeds)
    if s == list(range(s[0], s[0] + len(s))) and len(s) > 2:
        return f"{s[0]}–{s[-1]}"
    return ", ".join(map(str, s))


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    return v


def write_tables(plan: SweepPlan, run_dir: Path, rows: list[dict], comparison: list[dict]) -> dict[str, Path]:
    files = {}
    cols = [*plan.axes, "seed", *METRICS]
    files["results.csv"] = _write_csv(run_dir / "results.csv", cols, rows)
    comp_cols = list(comparison[0]) if comparison else [*plan.axes, "n"]
    files["comparison.csv"] = _write_csv(run_dir / "comparison.csv", comp_cols, comparison)
    (run_dir / "comparison.md").write_text(comparison_markdown(plan, comparison))
    files["comparison.md"] = run_dir / "comparison.md"
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        pass
    else:
        table = pa.Table.from_pylist([{c: r.get(c) for c in cols} for r in rows]) if rows else pa.table({})
        pq.write_table(table, run_dir / "results.parquet")
        files["results.parquet"] = run_dir / "results.parquet"
    return files


def _write_csv(path: Path, cols: list[str], rows: list[dict]) -> Path:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow([_csv_cell(r.get(c)) for c in cols])
    os.replace(tmp, path)
    return path


# -- TOML ---------------------------------------------------------------------------------------------------------
def plan_from_toml(path: str | Path) -> tuple[SweepPlan, dict[str, Any]]:
    """A sweep file::

        seeds = "1-20"          # or [1, 2, 3]
        engine = "lab"          # or "services"
        [grid]
        policy = ["morph", "full", "tsg"]
        "faults.loss" = [0, 10, 30]
        scale = ["tiny", "small"]
        [base]                  # fixed fields for every episode
        steps = 400
        [baseline]              # optional: what each condition is compared with
        policy = "morph"

    Returns the plan and the file's ``[run]`` table (executor, jobs, scheduler, out) for the CLI."""
    try:
        data = tomllib.loads(read_text(path, "sweep file"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"sweep file: {path}: {exc}") from None
    known = {"seeds", "engine", "grid", "base", "baseline", "fiedler_every", "run"}
    for k in data:
        if k not in known:
            raise ValueError(f"{k}: unknown key in {path} (known: {', '.join(sorted(known))})")
    plan = SweepPlan.build(grid=data.get("grid", {}), seeds=data.get("seeds", (1,)), base=data.get("base"),
                           engine=data.get("engine", "lab"), baseline=data.get("baseline"),
                           fiedler_every=data.get("fiedler_every", 10))
    return plan, dict(data.get("run", {}))
