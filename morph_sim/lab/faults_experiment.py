"""The fault experiment: deliveries, links and dispatch delay against message loss (0–50 %, Bernoulli vs
bursty Gilbert–Elliott) and latency (0–5 ticks), for MORPH (both presets), full, TSG and proximity, several seeds.

Each episode runs on the lab's pure core (warehouse, CTA controller, every agent's brain in one process, as
:mod:`.runner`), with the dispatch protocol's messages passed through the bus's own fault decision
(:meth:`FaultLayer.fate`, per-link seeded streams) under virtual time (docs/faults.md, Δ = 1 s):

* an AGV whose gate opens sends ``HelpRequest`` (AGV → picker) and its ``Ack`` (AGV → sim) at t·Δ; both must arrive
  by the TICK deadline t·Δ + Δ/2 (latency ≤ Δ/2), else the request is stale / the ack is late and the AGV gets no
  picker this tick — it asks again next tick, since the world still says it needs one (retry by design);
* the sim resolves the requests that made it (the picker takes the first requester in mission order);
  ``Resolve`` (sim → picker) and ``Commit`` (picker → sim) are sent at t·Δ + Δ/2 and must arrive by (t+1)·Δ;
* ``HelpReply`` (picker → AGV) is sent too, but a lost reply costs nothing: the commit reached the sim, and the next
  Tick tells the AGV (world state is authoritative);
* ``Tick`` itself is not faulted here (every brain learns from every tick; the services layer, where an agent that
  misses a Tick skips that tick, is the end-to-end version — see docs/faults.md).

Measured per episode: deliveries, mean undirected links, mean dispatch delay (ticks an AGV waits from first needing
a picker until one is committed), and the fraction of dispatch attempts lost to faults.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.faults import FaultSpec, Latency, Loss
from schemas.keys import RunKeys
from services.agent.policies import Fleet
from services.faults.layer import FaultLayer
from morph_sim.lab.runner import REFERENCE_SEEDS, _gate, make_condition_policy
from services.sim.world.cta import CTAController, resolve_requests
from services.sim.world.warehouse import Warehouse, WarehouseConfig

RUN = "faults-lab"
K = RunKeys(RUN)
DT = 1.0
DEADLINE = DT / 2  # a message is on time if it arrives within its phase

#: condition label -> (lab condition, MORPH preset)
CONDITIONS: dict[str, tuple[str, str]] = {
    "MORPH (reference)": ("morph", "reference"),
    "MORPH (paper)": ("morph", "paper"),
    "Full-Graph": ("full", "reference"),
    "TSG": ("tsg", "reference"),
    "Proximity": ("proximity", "reference"),
}
LOSS_PCT = (0, 10, 20, 30, 40, 50)
LATENCY_TICKS = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0)
BURST = 4.0  # Gilbert–Elliott mean burst length, messages
PROXIMITY_RADIUS = 4  # RunConfig's default


def fault_spec(kind: str, level: float, seed: int) -> FaultSpec | None:
    """The network fault of one sweep point: ``bernoulli``/``bursty`` loss in percent, or ``latency`` in ticks
    (normal, jitter a quarter of the delay)."""
    if level == 0:
        return None
    if kind == "bernoulli":
        return FaultSpec(loss=Loss(percent=level), seed=seed)
    if kind == "bursty":
        return FaultSpec(loss=Loss(model="gilbert_elliott", percent=level, burst_length=BURST), seed=seed)
    if kind == "latency":
        return FaultSpec(latency=Latency(delay=level * DT, jitter=0.25 * level * DT, distribution="normal"),
                         seed=seed)
    raise ValueError(f"kind: unknown {kind!r} (bernoulli, bursty, latency)")


@dataclass
class FaultEpisode:
    condition: str
    kind: str
    level: float
    seed: int
    deliveries: int
    mean_links: float
    dispatch_delay: float
    attempts: int
    lost_attempts: int
    wall_s: float


def _on_time(layer: FaultLayer, key: str, sender, receiver) -> bool:
    fate = layer.fate(key, sender, receiver)
    return bool(fate) and min(fate) <= DEADLINE + 1e-9  # a duplicate only helps if one copy is on time


def run_fault_episode(condition: str, kind: str, level: float, seed: int, *, scale: str = "tiny",
                      steps: int = 500) -> FaultEpisode:
    t0 = time.perf_counter()
    lab_condition, preset = CONDITIONS[condition]
    cfg = WarehouseConfig.named(scale, max_steps=steps + 1)
    cta = CTAController(Warehouse(cfg))
    cta.reset(seed)
    fleet = Fleet(cta.n_agvs, cta.n_pickers, scale)
    policy = make_condition_policy(lab_condition, preset, PROXIMITY_RADIUS if lab_condition == "proximity" else None,
                                   steps=steps)
    brains = policy.brains(fleet, range(fleet.n), seed)
    layer = FaultLayer(RUN, base_seed=seed)  # the one receiver-side decision, per link
    spec = fault_spec(kind, level, seed)
    if spec is not None:
        layer.set(spec)
    links = np.zeros(steps)
    waiting_since: dict[int, int] = {}
    delays: list[int] = []
    attempts = lost = 0
    for t in range(steps):
        obs = cta.begin_tick()
        brains.learn(obs)
        A = brains.team_links()
        on = A != 0
        links[t] = np.count_nonzero(on | on.T) // 2
        requesters = obs.requesters().tolist()
        for agv in set(waiting_since) - set(requesters):
            waiting_since.pop(agv)  # no longer needs a picker (its mission changed)
        for agv in requesters:
            waiting_since.setdefault(agv, t)
        requests = []
        for agv in requesters:
            picker = brains.candidate(agv, obs)
            if picker < 0:
                continue
            u = brains.draw(agv) if brains.draws else None
            ok, _p = _gate(brains, agv, picker, obs, u)
            if not ok:
                continue
            attempts += 1
            # both the request (to the picker) and the ack announcing it (to the sim) must be on time
            if _on_time(layer, K.request(agv, picker), agv, picker) and _on_time(layer, K.ack(agv), agv, "sim"):
                requests.append((agv, picker))
            else:
                lost += 1
        commits = []
        for picker, agv in resolve_requests(requests):
            if _on_time(layer, K.resolve, "sim", picker) and _on_time(layer, K.commit(picker), picker, "sim"):
                commits.append((picker, agv))
                layer.fate(K.reply(picker, agv), picker, agv)  # sent; its loss is healed by the next Tick
            else:
                lost += 1
        for _picker, agv in cta.commit(commits):
            start = waiting_since.pop(agv, t)
            delays.append(t - start)
        cta.finish_tick()
    return FaultEpisode(condition, kind, float(level), seed, int(cta.deliveries), float(links.mean()),
                        float(np.mean(delays)) if delays else float("nan"), attempts, lost,
                        time.perf_counter() - t0)


def sweep(*, seeds=REFERENCE_SEEDS, conditions=tuple(CONDITIONS), loss=LOSS_PCT, latency=LATENCY_TICKS,
          scale: str = "tiny", steps: int = 800, progress=None) -> list[FaultEpisode]:
    points = [("bernoulli", x) for x in loss] + [("bursty", x) for x in loss if x > 0] + \
             [("latency", x) for x in latency if x > 0]
    out = []
    for condition in conditions:
        for kind, level in points:
            for seed in seeds:
                ep = run_fault_episode(condition, kind, level, seed, scale=scale, steps=steps)
                out.append(ep)
                if progress is not None:
                    progress(ep)
    return out


def summarize(episodes: list[FaultEpisode]) -> list[dict]:
    """Mean and standard deviation over seeds per (condition, kind, level); level 0 is shared by every kind."""
    groups: dict[tuple, list[FaultEpisode]] = {}
    for ep in episodes:
        kinds = ("bernoulli", "bursty", "latency") if ep.level == 0 else (ep.kind,)
        for kind in kinds:
            groups.setdefault((ep.condition, kind, ep.level), []).append(ep)
    rows = []
    for (condition, kind, level), eps in sorted(groups.items(), key=lambda kv: (list(CONDITIONS).index(kv[0][0]),
                                                                               kv[0][1], kv[0][2])):
        row = {"condition": condition, "kind": kind, "level": level, "seeds": len(eps)}
        for name in ("deliveries", "mean_links", "dispatch_delay"):
            vals = np.array([getattr(e, name) for e in eps], dtype=float)
            row[name] = float(np.nanmean(vals)) if np.isfinite(vals).any() else float("nan")
            row[name + "_sd"] = float(np.nanstd(vals)) if np.isfinite(vals).any() else float("nan")
        row["lost_share"] = float(sum(e.lost_attempts for e in eps) / max(1, sum(e.attempts for e in eps)))
        rows.append({k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()})  # JSON
    return rows


def plot(rows: list[dict], path: str | Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = (("deliveries", "deliveries"), ("mean_links", "mean links"), ("dispatch_delay", "dispatch delay, ticks"))
    kinds = (("bernoulli", "Bernoulli loss, %"), ("bursty", f"Gilbert–Elliott loss (burst {BURST:g}), %"),
             ("latency", "latency, ticks"))
    fig, axes = plt.subplots(len(metrics), len(kinds), figsize=(15, 11), squeeze=False)
    for i, (metric, mlabel) in enumerate(metrics):
        for j, (kind, klabel) in enumerate(kinds):
            ax = axes[i][j]
            for condition in CONDITIONS:
                pts = [r for r in rows if r["condition"] == condition and r["kind"] == kind]
                if not pts:
                    continue
                nan = float("nan")  # no dispatch at all: no delay to show
                ax.errorbar([r["level"] for r in pts], [nan if r[metric] is None else r[metric] for r in pts],
                            yerr=[nan if r[metric + "_sd"] is None else r[metric + "_sd"] for r in pts], marker="o", capsize=3, label=condition)
            ax.set_xlabel(klabel)
            ax.set_ylabel(mlabel)
            if kind == "latency":
                levels = sorted({r["level"] for r in rows if r["kind"] == kind})
                ax.set_xscale("symlog", linthresh=1.0)  # the cliff sits below one tick; keep 0–1 linear
                ax.set_xticks(levels, [f"{x:g}" for x in levels])
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle("MORPH and baselines under message faults (virtual time, mean ± sd over seeds)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_experiment(out_dir: str | Path, *, quick: bool = False, progress=None) -> dict:
    """Run the sweep (``quick``: the reduced CI version), write ``faults.json`` and ``faults.png`` under
    ``out_dir``; returns {"rows", "json", "png", "wall_s"}. The lead wires this to ``morph-sim experiment faults``."""
    t0 = time.perf_counter()
    if quick:
        episodes = sweep(seeds=(1,), conditions=("MORPH (reference)", "Full-Graph"), loss=(0, 30),
                         latency=(0.0, 1.0), steps=150, progress=progress)
    else:
        episodes = sweep(progress=progress)
    rows = summarize(episodes)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "faults.json").write_text(json.dumps(
        {"rows": rows, "episodes": [{k: None if isinstance(v, float) and math.isnan(v) else v
                                     for k, v in e.__dict__.items()} for e in episodes]}, indent=1))
    png = plot(rows, out / "faults.png")
    return {"rows": rows, "json": str(out / "faults.json"), "png": str(png), "wall_s": time.perf_counter() - t0}
