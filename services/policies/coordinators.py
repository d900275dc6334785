"""Coordination policies: what an agent needs to decide dispatch requests and to learn.

One small interface, used unchanged by the in-process lab and by the per-agent services:

* a :class:`CoordinationPolicy` is a stateless description (``full``, ``constant``, ``tsg``,
  ``proximity``, ``none``, ``morph``) that builds :class:`Coordinator`;
* :class:`Coordinator` hold the coordination state of a set of *owned* agents (one agent in a service
  process, all agents in the lab, where the updates are vectorised across them). Each owned agent has
  its own state slice and its own seeded :class:`numpy.random.Generator` for gate draws; nothing is
  read across agents. An agent learns only from :class:`~.observation.TickObservation` objects.

Per tick (docs/services.md): ``learn(obs)`` applies the update for step ``t-1``; then each AGV that needs a
picker takes ``candidate(agv, obs, free)`` and, if ``draws`` is true, draws ``draw(agv)`` and asks
when the draw is below ``probability(agv, picker, obs)``. Policies with ``draws = False`` (full, none)
dispatch with P = 1 or 0 and consume no random number, as in the reference.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import Field, field_validator

from schemas.tick import NEEDS_PICKER, TickObservation
from services.policies.interface import (
    CoordinationPolicy,
    Coordinator,
    PolicyParams,
    SavedState,
    validate_options,
)
from services.policies.plasticity import PaperInputs, PaperState, ReferenceState
from services.policies.presets import ABLATIONS, MorphParams, load_preset

W_FLOOR = 0.25  # the reference's gate floor for the memoryless gates (TSG, Proximity)


def _mean(a: np.ndarray) -> float:
    """``np.mean(a)`` to the last bit (a float64 sum, integers summed as float64, over the count) without its Python
    wrapper, which costs more than the sum itself on a fleet's few values (these are taken every tick)."""
    if a.dtype.kind in "biu":
        return float(np.add.reduce(a, axis=None, dtype=np.float64) / a.size)
    if a.dtype == np.float64:
        return float(np.add.reduce(a, axis=None) / a.size)
    return float(np.mean(a))


# --------------------------------------------------------------------------------------------------
# memoryless policies


class _FixedBrains(Coordinator):
    """Brains whose decisions read no view: nothing to learn, for any robot."""

    def learn_for(self, obs, agents):
        pass


class _FullBrains(_FixedBrains):
    draws = False

    def probability(self, agv, picker, obs):
        return 1.0

    def link_rows(self):
        rows = np.ones((len(self.owners), self.fleet.n))
        rows[np.arange(len(self.owners)), self.owners] = 0.0
        return rows


class _BroadcastBrains(_FullBrains):
    """All-to-all as the paper means it: every AGV that needs a picker asks every free picker it knows of at once;
    several may accept, the sim applies one commitment and refuses the rest (services/protocol/dispatch.py)."""

    broadcast = True


class _NoneBrains(_FixedBrains):
    draws = False

    def probability(self, agv, picker, obs):
        return 0.0

    def link_rows(self):
        return np.zeros((len(self.owners), self.fleet.n))


class _ConstantBrains(_FixedBrains):
    def __init__(self, fleet, owners, seed, p: float) -> None:
        super().__init__(fleet, owners, seed)
        self.p = p

    def probability(self, agv, picker, obs):
        return self.p

    def link_rows(self):
        return np.zeros((len(self.owners), self.fleet.n))


class _TopologyBrains(Coordinator):
    """Gate 0.25 + 0.75·A[agv, picker] with A recomputed from the current tick."""

    def __init__(self, fleet, owners, seed) -> None:
        super().__init__(fleet, owners, seed)
        self._rows = np.zeros((len(self.owners), fleet.n))

    def learn(self, obs):
        self._rows = self._topology(obs, self.owners)

    def learn_for(self, obs, agents):
        slots = [self.slot(a) for a in agents]
        self._rows[slots] = self._topology(obs, self.owners[slots])

    @abstractmethod
    def _topology(self, obs: TickObservation, agents: np.ndarray) -> np.ndarray:
        """(len(agents), n) link rows of ``agents`` in ``obs``."""

    def probability(self, agv, picker, obs):
        return W_FLOOR + (1.0 - W_FLOOR) * float(self._rows[self.slot(agv), picker])

    def link_rows(self):
        return self._rows


class _TSGBrains(_TopologyBrains):
    def _topology(self, obs, agents):
        # pairs sharing a current mission target (before dispatch): a free picker has none, so the
        # gate entry for the candidate is always 0 — TSG behaves as a constant 0.25 gate (docs/morph.md)
        return obs.coassignment(previous=False)[agents]


class _ProximityBrains(_TopologyBrains):
    def __init__(self, fleet, owners, seed, radius: int) -> None:
        super().__init__(fleet, owners, seed)
        self.radius = radius

    def _topology(self, obs, agents):
        c = obs.cells
        mine = c[agents]
        d = np.abs(mine[:, None, 0] - c[None, :, 0]) + np.abs(mine[:, None, 1] - c[None, :, 1])
        rows = (d <= self.radius).astype(float)
        rows[np.arange(len(agents)), agents] = 0.0
        return rows


class _SimplePolicy(CoordinationPolicy):
    """A shipped policy whose brains are ``BRAINS(fleet, owners, seed, *parameters)``: a frozen dataclass whose
    parameter fields are its ``Params`` model's (the model validates them on creation and names a bad one)."""

    BRAINS: ClassVar[type[Coordinator]]

    def __post_init__(self):
        validate_options(type(self), self.options())

    @classmethod
    def from_params(cls, params):
        return cls(**params.model_dump())

    def options(self):
        return {name: getattr(self, name) for name in self.Params.model_fields}

    def brains(self, fleet, owners, seed):
        return self.BRAINS(fleet, owners, seed, *self.options().values())

    def fleet_brains(self, fleet, seed):
        return self.brains(fleet, range(fleet.n), seed)  # each robot's row depends on its own view alone


@dataclass(frozen=True)
class FullPolicy(_SimplePolicy):
    """Full-Graph: every AGV asks the nearest free picker (P = 1), as the reference's baseline."""

    name: str = "full"
    BRAINS: ClassVar[type[Coordinator]] = _FullBrains


@dataclass(frozen=True)
class BroadcastPolicy(_SimplePolicy):
    """Full-Graph as the paper means it: every AGV asks every free picker at once; the sim applies one commitment."""

    name: str = "full-broadcast"
    broadcast: ClassVar[bool] = True
    BRAINS: ClassVar[type[Coordinator]] = _BroadcastBrains


@dataclass(frozen=True)
class NonePolicy(_SimplePolicy):
    """No coordination: no AGV ever asks (P = 0)."""

    name: str = "none"
    BRAINS: ClassVar[type[Coordinator]] = _NoneBrains


class ConstantParams(PolicyParams):
    p: float = Field(default=0.25, ge=0.0, le=1.0, description="gate probability of every request")


@dataclass(frozen=True)
class ConstantPolicy(_SimplePolicy):
    """Every AGV asks the nearest free picker with one fixed probability ``p``."""

    p: float = 0.25
    name: str = "constant"
    Params: ClassVar[type[PolicyParams]] = ConstantParams
    BRAINS: ClassVar[type[Coordinator]] = _ConstantBrains


@dataclass(frozen=True)
class TSGPolicy(_SimplePolicy):
    """TSG: gate 0.25 + 0.75 · (the pair shares a mission target now), recomputed every tick."""

    name: str = "tsg"
    BRAINS: ClassVar[type[Coordinator]] = _TSGBrains


class ProximityParams(PolicyParams):
    radius: int = Field(default=4, ge=0, description="link radius: robots within this Manhattan distance link")


@dataclass(frozen=True)
class ProximityPolicy(_SimplePolicy):
    """Proximity: gate 0.25 + 0.75 · (the pair is within ``radius`` cells), recomputed every tick."""

    radius: int = 4
    name: str = "proximity"
    Params: ClassVar[type[PolicyParams]] = ProximityParams
    BRAINS: ClassVar[type[Coordinator]] = _ProximityBrains


#: the radii the reference's calibration tries (docs/morph.md)
PROXIMITY_RADII = (2, 3, 4, 5, 6, 8, 10)


def calibrate_radius(target_links: float, mean_links_for_radius, radii=PROXIMITY_RADII) -> int:
    """The reference's calibration: the radius whose mean link count is closest to ``target_links``.

    ``mean_links_for_radius(r)`` runs one Proximity episode (seed 42 in the reference) and returns its
    mean link count. Ties keep the first radius (strict improvement only, as in the reference).
    """
    best_r, best = radii[0], float("inf")
    for r in radii:
        diff = abs(mean_links_for_radius(r) - target_links)
        if diff < best:
            best_r, best = r, diff
    return best_r


# --------------------------------------------------------------------------------------------------
# MORPH


_PICKING, _RETURNING = (int(m) for m in NEEDS_PICKER)  # plain ints: numpy compares them without enum lookups


def reference_hint(obs: TickObservation) -> np.ndarray:
    """The reference's predictive hint δ_pred (docs/morph.md) for the step before ``obs``.

    For every AGV that had a PICKING or RETURNING mission, the picker nearest (Manhattan, from the
    pickers' post-move cells, busy ones included, first on ties) to the AGV's target is hinted.
    """
    n, na = obs.n, obs.n_agvs
    pred = np.zeros((n, n))
    pm = obs.prev_mission[:na]
    agvs = np.flatnonzero((pm == _PICKING) | (pm == _RETURNING))
    if agvs.size == 0 or obs.n_pickers == 0:
        return pred
    # Manhattan distances (AGV target, picker cell): |dx| + |dy| summed over the last axis (integers, exact)
    d = np.abs(obs.cells[None, na:] - obs.prev_target[agvs, None]).sum(axis=2)
    nearest = na + d.argmin(axis=1)
    pred[agvs, nearest] = 1.0
    pred[nearest, agvs] = 1.0
    return pred


def open_request_hint(obs: TickObservation) -> np.ndarray:
    """The paper preset's non-spatial predictive hint: an AGV waiting for a picker and a free picker.

    Both will be co-assigned as soon as one of them is dispatched to the other, so the pair is an
    anticipated co-assignment; no position enters.
    """
    pairs = np.outer(obs.needs_picker, obs.free_picker)  # (waiting AGV, free picker), both ways below
    hint = (pairs | pairs.T).astype(float)
    np.fill_diagonal(hint, 0.0)
    return hint


HANDLING_REWARD = 0.1  # TA-RWARE's reward for a load or unload (paid to the picker only)


def paper_step_reward(obs: TickObservation) -> np.ndarray:
    """r_i^t for the paper preset: the reward of the step's events agent i took part in.

    TA-RWARE's individual reward (+1 delivery to the AGV, +0.1 per load/unload to the picker, -0.001
    per step), with the +0.1 of a load or unload also counted for the AGV that made it: the event is
    joint, and only an AGV's row gates dispatch.
    """
    r = obs.reward.astype(float).copy()
    agv = np.zeros(obs.n, dtype=bool)
    agv[: obs.n_agvs] = True
    r[agv & obs.handled] += HANDLING_REWARD
    return r


class MorphBrains(Coordinator):
    memoryless = False

    def __init__(self, fleet, owners, seed, preset: str, params: MorphParams, share_replicas: bool = True) -> None:
        super().__init__(fleet, owners, seed)
        self.preset = preset
        self.params = params
        d_exp = params.d_exp(fleet.scale)
        b = len(self.owners)
        # Every owned agent has its own replica of what it learns from the ticks (reference: the whole symmetric
        # state; paper: its task history, update count, d̂, baseline and η). Replicas created at the same tick and
        # fed the same ticks are identical, so a bank that owns several agents may store them once
        # (``share_replicas``); ``_rep[k]`` is where owned agent k's replica lives.
        copies = 1 if (share_replicas and b > 0) else max(b, 1)
        self._rep = np.zeros(b, dtype=int) if copies == 1 else np.arange(b)
        if preset == "reference":
            self.state = ReferenceState(params, fleet.n, copies, d_exp)
        else:
            self.state = PaperState(params, fleet.n, self.owners, d_exp, replicas=copies)

    def learn(self, obs: TickObservation) -> None:
        self._learn(obs, None)

    def learn_for(self, obs: TickObservation, agents) -> None:
        """Brains with a replica per owned agent: only ``agents``' replicas take ``obs``."""
        if len(set(self._rep.tolist())) != len(self.owners):
            raise ValueError("learn_for: needs one replica per owned agent")
        self._learn(obs, self._rep[[self.slot(a) for a in agents]])

    def _learn(self, obs: TickObservation, replicas) -> None:
        p = self.params
        if obs.has_previous:
            if self.preset == "reference":
                positions = pred = None
                if self.state.structural_due(replicas):  # the only step that reads them (two of three are not)
                    rows, cols = obs.grid_shape
                    positions = obs.cells / np.array([cols, rows], dtype=float)
                    pred = reference_hint(obs) if p.use_pred_hint else None
                self.state.step(positions, obs.coassignment(previous=True), obs.deliveries, pred, replicas)
            else:
                hint = open_request_hint(obs) if p.use_pred_hint else np.zeros((obs.n, obs.n))
                self.state.step(
                    PaperInputs(
                        task=obs.prev_task,
                        reward=paper_step_reward(obs),
                        delivered=obs.delivered,
                        loader=obs.loader,
                        deliveries=obs.deliveries,
                        hint=hint,
                    ),
                    replicas,  # with a replica per owned agent, replica k is row k
                )
        if p.reset_every and obs.t > 0 and obs.t % p.reset_every == 0 and not obs.final:
            self.state.reset_links(replicas)

    def eta(self, agent: int) -> float:
        """The arousal signal η of ``agent``'s last update."""
        s = self.state
        return float(s.eta[self._rep[self.slot(agent)]])

    def _rows(self, arr: np.ndarray) -> np.ndarray:
        if self.preset == "reference":
            return arr[self._rep, self.owners]
        return arr

    def candidate(self, agv, obs, free=None):
        if self.params.candidate == "nearest":
            return obs.nearest_free_picker(agv, free)
        free = obs.free_picker if free is None else free
        pickers = np.flatnonzero(free)
        if pickers.size == 0:
            return -1
        k = self.slot(agv)
        if self.preset == "reference":
            r = self._rep[k]
            w, a = self.state.W[r, agv, pickers], self.state.A[r, agv, pickers]
        else:
            w, a = self.state.W[k, pickers], self.state.A[k, pickers]
        tx, ty = obs.target[agv]
        d = np.abs(obs.cells[pickers, 0] - tx) + np.abs(obs.cells[pickers, 1] - ty)
        # ask over a link first, the most preferred partner first, then the nearest, then the lowest index
        best = np.lexsort((pickers, d, -w, -a))[0]
        return int(pickers[best])

    def probability(self, agv, picker, obs):
        k = self.slot(agv)
        w = self.state.W[self._rep[k], agv, picker] if self.preset == "reference" else self.state.W[k, picker]
        return self.params.w_floor + (1.0 - self.params.w_floor) * float(w)

    def link_rows(self):
        return self._rows(self.state.A)

    def out_links(self, agent):
        k = self.slot(agent)
        row = self.state.A[self._rep[k], agent] if self.preset == "reference" else self.state.A[k]
        return np.flatnonzero(row).tolist()

    def weight_rows(self):
        return self._rows(self.state.W)

    def save(self, agent):
        s, k = self.state, self.slot(agent)
        r = self._rep[k]
        eta, dhat = s.eta[r], s.dhat[r]
        if self.preset == "reference":
            theta, age, h = s.theta_bcm[r, agent], s.age[r, agent], s.h[r, agent]
            # the previous step's co-assignment: the credit of the next update
            scalars, rows = {}, {"j_prev": [float(v) for v in s.j_prev[r, agent]]}
        else:
            theta, age, h = s.theta_bcm[k], s.age[k], s.h[k]
            # the task labels of the mutual-information window (small integers), and how far it is filled
            scalars = {"filled": float(s.filled[r]), "baseline": float(s.baseline[r])}
            history = s.history[r]
            rows = {f"history_{i}": [int(v) for v in history[i]] for i in range(len(history))}
        return SavedState(theta_row=[float(v) for v in theta], age_row=[int(v) for v in age], h=float(h),
                          eta=float(eta), d_hat=float(dhat), scalars=scalars, rows=rows)

    def restore(self, agent, states):
        """Paper preset (directed rows): the robot's own row of W, A, BCM thresholds and link ages, its h, η, d̂.
        Reference preset (each robot holds a replica of the symmetric state): every robot's row from that robot's
        latest state (rows may come from different ticks: the replica is as fresh as the record), the own row last
        so it wins where the symmetric halves disagree; the fleet-level d̂ and η from the own state. The step counter
        is set to the state's tick, so structural updates stay in phase."""
        own = states.get(agent)
        if own is None:
            return None
        s = self.state
        if self.preset == "reference":
            r = self._rep[self.slot(agent)]
            for j, st in sorted(states.items(), key=lambda kv: kv[0] == agent):  # own row last
                s.W[r, j] = st.w_row
                s.A[r, j] = np.asarray(st.a_row, dtype=float)
                s.theta_bcm[r, j] = st.theta_row
                s.age[r, j] = st.age_row
                s.h[r, j] = st.h
                if "j_prev" in st.rows:  # a state published before it was saved restarts it empty
                    s.j_prev[r, j] = st.rows["j_prev"]
            s.dhat[r], s.eta[r], s.t[r] = own.d_hat, own.eta, own.t
            return own.t
        k = self.slot(agent)
        r = self._rep[k]
        s.W[k] = own.w_row
        s.A[k] = np.asarray(own.a_row, dtype=float)
        s.theta_bcm[k] = own.theta_row
        s.age[k] = own.age_row
        s.h[k] = own.h
        window = [own.rows.get(f"history_{i}") for i in range(s.history.shape[1])]
        if all(row is not None for row in window):
            s.history[r] = np.asarray(window, dtype=np.int64)
            s.filled[r] = int(own.scalars.get("filled", s.filled[r]))
            s.baseline[r] = float(own.scalars.get("baseline", s.baseline[r]))
        s.dhat[r], s.eta[r], s.t[r] = own.d_hat, own.eta, own.t
        return own.t

    def extra_metrics(self):
        s = self.state
        # the fleet's mean over robots, each robot's from its own replica
        eta = float(s.eta[0]) if len(s.eta) == 1 else _mean(s.eta[self._rep])
        return {
            "eta": eta,
            "h_mean": _mean(self._h_rows()),
            "formed": _mean(s.formed),
            "pruned": _mean(s.pruned),
        }

    def _h_rows(self):
        if self.preset == "reference":
            return self.state.h[self._rep, self.owners]
        return self.state.h

    def h(self) -> np.ndarray:
        """(B,) homeostatic variable of each owned agent."""
        return self._h_rows()


class MorphOptions(PolicyParams):
    preset: str = Field(default="reference", description="MORPH preset: reference, paper, or a preset .toml path")
    ablation: str | None = Field(default=None, description="ablation of the preset (None or full: the whole model)")
    reset_every: int | None = Field(default=None, ge=0, description="clear the links every this many ticks "
                                    "(None: the preset's period)")
    episode_steps: int | None = Field(default=None, ge=1, description="the episode length T, for a preset that "
                                      "anneals its formation threshold over the episode (the run's --steps)")

    @field_validator("preset")
    @classmethod
    def _preset(cls, value: str) -> str:
        load_preset(value)
        return value

    @field_validator("ablation")
    @classmethod
    def _ablation(cls, value: str | None) -> str | None:
        if value not in (None, "full") and value not in ABLATIONS:
            raise ValueError(f"unknown ablation {value!r} (known: {', '.join(ABLATIONS)})")
        return value


@dataclass(frozen=True)
class MorphPolicy(CoordinationPolicy):
    """MORPH: synaptic, homeostatic, structural and metaplastic rules learn whom each robot coordinates with."""

    preset: str = "reference"
    ablation: str | None = None
    name: str = "morph"
    #: store identical reference replicas of co-owned agents once (see MorphBrains)
    share_replicas: bool = True
    #: override of the preset's reset period (the shift experiment's phase length for MORPH-reset); None: keep
    reset_every: int | None = None
    #: the episode length T, for a preset that anneals θ_form over the episode (paper); None: the preset's fallback
    episode_steps: int | None = None
    Params: ClassVar[type[PolicyParams]] = MorphOptions

    def __post_init__(self):
        validate_options(type(self), self.options())
        load_preset(self.preset).resolve(self.ablation)

    @classmethod
    def from_params(cls, params):
        return cls(**params.model_dump())

    def options(self):
        return {name: getattr(self, name) for name in self.Params.model_fields}

    @property
    def params(self) -> MorphParams:
        params = load_preset(self.preset).resolve(self.ablation)
        if self.reset_every is not None:
            params = params.model_copy(update={"reset_every": self.reset_every})
        if params.theta_form_anneal_over == "episode" and self.episode_steps is not None:
            params = params.model_copy(update={"theta_form_anneal": self.episode_steps})
        return params

    def brains(self, fleet, owners, seed):
        preset = load_preset(self.preset)
        return MorphBrains(fleet, owners, seed, preset.rules, self.params, self.share_replicas)

    def fleet_brains(self, fleet, seed):
        # a replica per robot in one array, each stepped from its robot's view: the reference preset's whole
        # symmetric state, the paper preset's task history, update count, d̂, baseline and η beside its own row
        preset = load_preset(self.preset)
        return MorphBrains(fleet, range(fleet.n), seed, preset.rules, self.params, share_replicas=False)

    def describe(self):
        return {"name": self.name, "preset": self.preset, "ablation": self.ablation or "full"}


#: The shipped coordination policies by name (services/policies/loading.py adds installed and importable ones).
POLICIES: dict[str, type[CoordinationPolicy]] = {
    "full": FullPolicy,
    "full-broadcast": BroadcastPolicy,
    "constant": ConstantPolicy,
    "tsg": TSGPolicy,
    "proximity": ProximityPolicy,
    "none": NonePolicy,
    "morph": MorphPolicy,
}
POLICY_NAMES = tuple(POLICIES)
