"""In-process episodes: the warehouse, the CTA controller and every agent's brain in one process, no bus.

One episode is ``T`` ticks of the tick protocol (docs/services.md) driven directly on the pure core:

1. the controller runs steps 1-2 and produces the tick's observation;
2. every agent applies its plasticity update for the previous step (``Coordinator.learn``);
3. AGVs that need a picker pick a candidate and draw their gate; pickers resolve the requests;
4. the controller applies the commitments, releases pickers and steps the warehouse.

After the last step the agents get one more observation to learn from, so the link count of step t is
the one after the update for step t, as the reference logs it.

Two switches reproduce the reference: ``dispatch="sequential"`` (an AGV whose nearest free picker was
just taken asks the next-nearest in the same tick) instead of the protocol's concurrent
resolution, and ``shared_stream=True`` (gate draws from the warehouse's request stream re-seeded after
reset) instead of each agent's own generator. The other mode's outcome is computed each tick
with the same draws and the number of ticks where the two differ is reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from morph_sim.lab.network import FLEET_KEY, DispatchStats, EventNetwork, LabDispatch, Team, dispatch_faults
from schemas.faults import FaultSpec
from services.metrics import catalogue, measures
from services.policies.conditions import make_condition_policy, select
from services.policies.coordinators import MorphPolicy
from services.policies.interface import CoordinationPolicy, Fleet
from services.policies.loading import make_policy
from services.protocol.dispatch import DEFAULT_REQUEST_TIMEOUT
from services.protocol.tick import (
    DemandShift,
    TickStep,
    concurrent_commits,
    distinct_cells,
    sequential_commits,
)
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig

SCALES = ("tiny", "small", "medium", "large")
REFERENCE_SEEDS = (42, 7, 123, 999, 2024)
DT = 1.0  # Δ, sim seconds per step
#: the catalogue's row metrics the lab's tick table has (with the dispatch protocol also the dispatch outcomes and the
#: fleet view's age), each meaning what it means in a run's metrics.csv
LAB_ROW_COLUMNS = ("deliveries", "deliveries_total", "requests", "commits", "links", "lambda2", "eta")
BURST_LENGTH = 4.0  # mean burst of the loss_percent shorthand's Gilbert–Elliott loss, messages

def check_choices(values, known, what: str):
    """A settings validator's check that every value is one of ``known``; the error names the bad value."""
    for v in values:
        if v not in known:
            raise ValueError(f"unknown {what} {v!r}; choose from {', '.join(known)}")
    return values


def check_nonempty(values, what: str):
    """A settings validator's check that a list of ``what`` is not empty."""
    if not values:
        raise ValueError(f"at least one {what}")
    return values


class EpisodeSpec(BaseModel):
    """One episode of the lab: which warehouse, which condition, which seed, which switches."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scale: str
    #: a key of services.policies.conditions.CONDITIONS, or (with ``policy_name``) the episode's label
    condition: str
    seed: int
    #: a policy by name, any ``--policy`` takes (shipped, installed, package.module:Class), built with
    #: ``policy_options``; None: the condition's policy
    policy_name: str | None = None
    policy_options: dict[str, str | int | float | bool | None] = Field(default_factory=dict)
    #: every robot learns from its own view even where every robot holds the same one (the conformance kit
    #: compares the two)
    per_robot_brains: bool = False
    #: robots with views of their own learn in one brain for the fleet where the policy has one
    #: (CoordinationPolicy.fleet_brains: vectorised across robots, the same numbers); False: a brain per robot
    fleet_brain: bool = True
    #: count the ticks where the other dispatch mode would have committed otherwise (it replays every gate: the
    #: conformance kit, which watches each decision, turns it off)
    compare_dispatch: bool = True
    steps: int = Field(default=800, ge=1)
    preset: str = "reference"
    radius: int | None = Field(default=None, ge=0)
    dispatch: Literal["concurrent", "sequential"] = "concurrent"
    shared_stream: bool = False
    fiedler_every: int = Field(default=1, ge=1, description="compute λ₂ every this many ticks")
    #: demand shift: the side of each consecutive ``phase_steps``-long phase; empty = no shift
    demand_phases: tuple[Literal["left", "right"], ...] = ()
    phase_steps: int = Field(default=400, ge=1)
    #: "requests": new requests drawn from the active half (the paper); "assignment": shift.py's filter;
    #: "none": phases only mark boundaries (the no-shift control: same episode length, same resets)
    demand_mode: Literal["requests", "assignment", "none"] = "requests"
    #: bursty message loss (Gilbert–Elliott, mean burst 4 messages) on the dispatch messages (request, reply,
    #: commitment, refusal), in percent; 0 = none. Shorthand for one entry of ``faults``.
    loss_percent: float = Field(default=0.0, ge=0.0, lt=100.0)
    #: network faults on the protocol's messages, scoped by key like the services' (docs/faults.md); the lab's
    #: discrete-event network applies them per link (morph_sim/lab/network.py)
    faults: tuple[FaultSpec, ...] = ()
    #: an AGV's request timeout, sim seconds (RunConfig.request_timeout)
    request_timeout: float = Field(default=DEFAULT_REQUEST_TIMEOUT, gt=0.0)
    #: network profile (a name in services/faults/profiles/ or a .toml path; docs/faults.md): the services' radio
    #: model (hand-overs, dead zones, queues) under the fault specs, with the robots' positions of every tick
    network: str | None = None

    @field_validator("network")
    @classmethod
    def _network(cls, value: str | None) -> str | None:
        if value is not None:
            from services.faults.network import load_profile

            try:
                load_profile(value)
            except ValueError as exc:
                raise ValueError(str(exc).removeprefix("network: ")) from None
        return value

    @model_validator(mode="after")
    def _phases_fill_episode(self) -> EpisodeSpec:
        if self.demand_phases and self.steps != len(self.demand_phases) * self.phase_steps:
            raise ValueError(f"steps: {self.steps} != {len(self.demand_phases)} phases × {self.phase_steps} steps")
        return self

    @model_validator(mode="after")
    def _policy_known(self) -> EpisodeSpec:
        if self.policy_name is None:
            if self.policy_options:
                raise ValueError("policy_options: options need policy_name")
            select([self.condition])
        else:
            self.policy()  # one line naming the policy or the option
        return self

    def policy(self) -> CoordinationPolicy:
        if self.policy_name is not None:
            return make_policy(self.policy_name, self.policy_options)
        # MORPH-reset clears its state at every phase boundary of a shift episode
        reset = self.phase_steps if self.demand_phases else None
        return make_condition_policy(self.condition, self.preset, self.radius, reset_every=reset, steps=self.steps)

    def demand_shift(self) -> DemandShift | None:
        """The episode's demand phases as the tick step takes them (None: no shift)."""
        return DemandShift(self.demand_phases, self.phase_steps, self.demand_mode) if self.demand_phases else None

    def boundaries(self) -> list[int]:
        return [p * self.phase_steps for p in range(len(self.demand_phases))] if self.demand_phases else [0]

    @property
    def key(self) -> str:
        return f"{self.scale}_{self.condition}_s{self.seed}"


def episode_faults(spec: EpisodeSpec) -> list[FaultSpec]:
    """The network faults of an episode: its ``faults`` and the ``loss_percent`` shorthand."""
    faults = list(spec.faults)
    if spec.loss_percent > 0:
        from schemas.faults import Loss

        faults += dispatch_faults(FaultSpec(id="loss", seed=spec.seed, loss=Loss(
            model="gilbert_elliott", percent=spec.loss_percent, burst_length=BURST_LENGTH)))
    return faults


@dataclass
class EpisodeResult:
    spec: EpisodeSpec
    ticks: dict[str, np.ndarray]
    summary: dict
    wall_s: float
    final_weights: np.ndarray | None = field(default=None, repr=False)
    final_links: np.ndarray | None = field(default=None, repr=False)
    mean_distance: np.ndarray | None = field(default=None, repr=False)
    tracker: measures.LinkTracker | None = field(default=None, repr=False)
    snapshots: dict[int, np.ndarray] = field(default_factory=dict, repr=False)


def run_episode(spec: EpisodeSpec, trace_hook=None, snapshot_ticks=(), policy: CoordinationPolicy | None = None
                ) -> EpisodeResult:
    """Run one episode on the pure core. ``trace_hook(obs, brains)`` is called after each update; ``policy``
    replaces the spec's (the conformance kit runs a policy wrapped to watch its decisions).

    ``snapshot_ticks``: copies of the team's W after the update that opens each of these ticks (tick T: the
    final update), returned in ``EpisodeResult.snapshots``.
    """
    t0 = time.perf_counter()
    cfg = WarehouseConfig.named(spec.scale, max_steps=max(spec.steps, 1) + 1)
    wh = Warehouse(cfg)
    cta = CTAController(wh)
    cta.reset(spec.seed)
    fleet = Fleet(cta.n_agvs, cta.n_pickers, spec.scale)
    n, T = fleet.n, spec.steps
    policy = spec.policy() if policy is None else policy
    shared = cta.shared_rng if spec.shared_stream else None
    faults = episode_faults(spec)
    driver: LabDispatch | None = None
    model = _network_model(spec, wh)
    if spec.dispatch == "concurrent":
        net = EventNetwork(faults, seed=spec.seed, model=model)
        own_views = net.touches(FLEET_KEY) or spec.per_robot_brains
        # the fleet broadcast can be late or lost: every agent learns and gates from its own view, in one brain for
        # the fleet where the policy has one (each robot's state stepped from its own view), else in a brain each
        bank = policy.fleet_brains(fleet, spec.seed) if own_views and spec.fleet_brain else None
        if bank is not None:
            brains = bank
            driver = LabDispatch(fleet.n_agvs, fleet.n_pickers, dt=DT, timeout=spec.request_timeout, network=net,
                                 fleet_brain=bank)
        elif own_views:
            agent_brains = [policy.brains(fleet, [i], spec.seed) for i in range(n)]
            brains = Team(agent_brains)
            driver = LabDispatch(fleet.n_agvs, fleet.n_pickers, dt=DT, timeout=spec.request_timeout, network=net,
                                 agent_brains=agent_brains)
        else:
            brains = policy.brains(fleet, range(n), spec.seed)
            driver = LabDispatch(fleet.n_agvs, fleet.n_pickers, dt=DT, timeout=spec.request_timeout, network=net,
                                 team_brain=brains)
    else:
        if faults or model is not None:
            field = "loss_percent/faults" if faults else "network"
            raise ValueError(f"{field}: network faults act on the dispatch protocol (concurrent dispatch); the "
                             "reference's sequential switch has no messages to fault")
        brains = policy.brains(fleet, range(n), spec.seed)
    if shared is not None:
        draw = lambda agv: float(shared.random_sample())  # noqa: E731 - the reference's one stream
    else:
        draw = brains.draw if driver is None or driver.agent_brains is None else None
    is_agv = np.arange(n) < fleet.n_agvs
    directed = isinstance(policy, MorphPolicy) and policy.params is not None and _rules(policy) == "paper"
    tracker = measures.LinkTracker(n, directed=directed)
    stats = DispatchStats()

    # the tick table: the catalogue's row metrics under their names and meanings, then the lab's own columns
    # (catalogue.LAB_TICKS); NaN where a value is not measured, as the monitor leaves the cell empty
    cols = {name: np.zeros(T) for name in (*LAB_ROW_COLUMNS, *catalogue.LAB_TICKS)}
    for name in ("lambda2", "fiedler_ref", "eta", "h_mean", "formed", "pruned"):
        cols[name][:] = np.nan
    if driver is not None:  # the dispatch outcomes by the end of each step, as the monitor's rows have them
        cols.update((name, np.zeros(T)) for name in catalogue.outcome_values({}))
    # Σ_t of each pair's Manhattan distance: integers, so summed exactly in blocks of ticks (one numpy pass per block
    # instead of one per tick; the episode's whole stack would be T·n² integers)
    dist_sum = np.zeros((n, n), dtype=np.int64)
    cells_block: list[np.ndarray] = []

    def fold_distances() -> None:
        nonlocal dist_sum
        if cells_block:
            c = np.stack(cells_block)
            dist_sum = dist_sum + (np.abs(c[:, :, None, 0] - c[:, None, :, 0])
                                   + np.abs(c[:, :, None, 1] - c[:, None, :, 1])).sum(axis=0)
            cells_block.clear()
    graph: list = [None, 0.0, 0.0]  # the last link matrix measured (its bytes), its reference Fiedler value and λ₂

    def record(step: int) -> None:
        A = brains.team_links()
        on = A != 0  # diagonal is zero by construction
        cols["links"][step] = np.count_nonzero(on | on.T) // 2  # = measures.undirected_link_count(A)
        cols["links_directed"][step] = np.count_nonzero(on)  # = measures.directed_link_count(A)
        if not brains.memoryless:
            W = brains.team_weights()
            linked = W[on]  # (its mean as ndarray.mean takes it, without the wrapper)
            cols["mean_w_links"][step] = float(np.add.reduce(linked) / linked.size) if linked.size else 0.0
            tracker.update(A, step)
        else:
            cols["mean_w_links"][step] = 1.0 if policy.name in ("full", "full-broadcast") else 0.0
        if step % spec.fiedler_every == 0:
            key = A.tobytes()  # links change on a third of MORPH's ticks: the spectra are those of the last change
            if key != graph[0]:
                graph[:] = [key, measures.reference_normalized_fiedler(A), measures.algebraic_connectivity(A)]
            cols["fiedler_ref"][step], cols["lambda2"][step] = graph[1], graph[2]
        for k, v in brains.extra_metrics().items():
            if k in cols:
                cols[k][step] = v

    snaps = set(snapshot_ticks)
    snapshots: dict[int, np.ndarray] = {}
    step = TickStep(cta, dt=DT, demand=spec.demand_shift())
    delivered = requested = 0
    for t in range(T):
        obs = step.begin()
        if driver is not None:
            driver.learn(obs)
        else:
            brains.learn(obs)
        if t in snaps:
            snapshots[t] = brains.team_weights().copy()
        if t > 0 and not brains.memoryless:
            record(t - 1)
        if brains.memoryless:
            record(t)
        if trace_hook is not None:
            trace_hook(obs, brains)
        cells_block.append(obs.cells)
        if len(cells_block) == 64:
            fold_distances()
        if driver is not None:
            driver.dispatch(obs, step.settle, stats, draw)
            sent = driver.sent_commits
            if not faults and driver.team_brain is not None and spec.compare_dispatch:
                draws = driver.last_draws
                other = sequential_commits(obs, brains, lambda agv, draws=draws: draws.get(agv, float("inf")))
                rank = {int(a): i for i, a in enumerate(obs.request_order)}
                sent = sorted(driver.sent_commits, key=lambda pa: rank.get(pa[1], len(rank)))
                stats.divergent_ticks += distinct_cells(obs, sent) != distinct_cells(obs, other)
        else:
            draws: dict[int, float] = {}

            def live(agv: int, draws=draws) -> float:
                draws[agv] = draw(agv)
                return draws[agv]

            commits = sequential_commits(obs, brains, live, stats.count)
            sent = commits
            other = concurrent_commits(obs, brains, lambda agv, draws=draws: draws.get(agv, float("inf")))
            stats.divergent_ticks += distinct_cells(obs, commits) != distinct_cells(obs, other)
            step.commit_now(commits)
        step.finish(radio=model)
        cols["deliveries_total"][t] = cta.deliveries
        cols["deliveries"][t] = cta.deliveries - delivered
        cols["requests"][t] = stats.requests - requested  # the help requests sent in tick t (a broadcasting AGV's
        # one decision asks several pickers: a request each, as the catalogue and a run's record count them)
        cols["commits"][t] = len(sent)  # the commitments the pickers sent in tick t
        delivered, requested = cta.deliveries, stats.requests
        cols["gate_p_sum"][t] = stats.p_sum  # Σ P(respond) over the gate decisions so far
        if driver is not None:
            for name, v in catalogue.outcome_values(driver.outcomes.as_dict()).items():
                cols[name][t] = v
    final = step.final()
    if not brains.memoryless:
        if driver is not None:
            driver.learn(final)
        else:
            brains.learn(final)
        record(T - 1)
        if T in snaps:
            snapshots[T] = brains.team_weights().copy()
        if trace_hook is not None:
            trace_hook(final, brains)

    if driver is not None:
        # the monitor's view_age_mean / view_age_max columns: with one team brain every agent holds the broadcast
        # of its own tick (age 0)
        for name, ages in (("view_age_mean", driver.view_ages), ("view_age_max", driver.view_age_max)):
            cols[name] = np.array(ages[:T], dtype=float) if driver.views is not None else np.zeros(T)
    W = brains.team_weights()
    A = brains.team_links()
    blocks = measures.mean_w_by_block(W, is_agv)
    fold_distances()
    mean_dist = dist_sum.astype(float) / T
    summary = {
        "scale": spec.scale,
        "condition": spec.condition,
        "seed": spec.seed,
        "steps": T,
        "n_agents": n,
        # how the robots learnt: "team" (one brain, every robot holds the sim's tick), "fleet" (one brain, each robot
        # stepped from its own view) or "per-robot" (a brain per robot, each with its own view)
        "brains": ("team" if driver is None or driver.views is None
                   else "fleet" if driver.fleet_brain is not None else "per-robot"),
        "deliveries": int(cta.deliveries),
        "mean_links": float(cols["links"].mean()),
        # the second half of the episode: the link count MORPH has converged to (the paper calibrates Proximity to it)
        "mean_links_converged": float(cols["links"][T // 2:].mean()),
        "max_links": n * (n - 1) // 2,
        "mean_links_directed": float(cols["links_directed"].mean()),
        "dispatch_decisions": stats.decisions,
        "dispatched": stats.dispatched,
        "committed": step.commits_applied,
        "mean_p_respond": stats.p_sum / stats.decisions if stats.decisions else float("nan"),
        "share_above_floor": stats.w_positive / stats.decisions if stats.decisions else float("nan"),
        "divergent_dispatch_ticks": stats.divergent_ticks,
        **({f"protocol_{k}": v for k, v in driver.outcomes.as_dict().items()} if driver is not None else {}),
        **(_network_summary(driver) if driver is not None else {}),
        **(_radio_summary(model, step.network_stops) if model is not None else {}),
        **catalogue.w_block_values(blocks),
        "w_asymmetry": float(np.abs(W - W.T).max()),
    }
    if not brains.memoryless:
        life, _ = tracker.lifetimes()
        summary["link_events"] = int(life.size)
        summary["median_lifetime"] = float(np.median(life)) if life.size else float("nan")
        summary["core_links"] = tracker.core_periphery()[0]
        h = getattr(brains, "h", None)
        summary["final_h_mean"] = float(np.mean(h())) if h else float("nan")
        summary["eta_mean"] = float(cols["eta"].mean())
        summary["eta_positive_share"] = float((cols["eta"] > 0).mean())
        if np.any(W):
            summary["spearman_agv_picker"] = measures.spearman_agv_picker(W, mean_dist, is_agv, n_permutations=0).rho
            summary["spearman_all_pairs"] = measures.spearman_reference_pairs(W, mean_dist).rho
    summary["wall_s"] = time.perf_counter() - t0
    return EpisodeResult(spec, cols, summary, summary["wall_s"], W, A, mean_dist,
                         tracker if not brains.memoryless else None, snapshots)


def _network_summary(driver: LabDispatch) -> dict:
    st = driver.net.stats
    out = {"messages_sent": st.sent, "messages_delivered": st.delivered, "messages_dropped": st.dropped,
           "bytes_sent": st.bytes,
           "dispatch_delay": float(np.mean(driver.dispatch_delays)) if driver.dispatch_delays else float("nan")}
    if driver.view_ages:
        ages = np.array(driver.view_ages, dtype=float)
        out["view_age_mean"] = float(np.nanmean(ages)) if np.isfinite(ages).any() else float("nan")
        finite = [a for a in driver.view_age_max if np.isfinite(a)]
        out["view_age_max"] = float(max(finite)) if finite else float("nan")
    return out


def _network_model(spec: EpisodeSpec, wh: Warehouse):
    """The episode's radio network (the services' model, seeded with the run's seed as theirs), or None."""
    if spec.network is None:
        return None
    from services.faults.network import NetworkModel, load_profile
    from services.world.layout import LayoutConfig, layout_for

    return NetworkModel(load_profile(spec.network), layout_for(LayoutConfig.named(spec.scale)), seed=spec.seed)


def _radio_summary(model, network_stops: int) -> dict:
    st = model.stats
    return {"network_handovers": st.handovers, "network_outage_seconds": st.outage_seconds,
            "network_stops": network_stops,
            **{f"network_lost_{cause}": n for cause, n in st.lost.items()}}


def _rules(policy: MorphPolicy) -> str:
    from services.policies.presets import load_preset

    return load_preset(policy.preset).rules
