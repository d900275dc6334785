"""MORPH presets: parameter sets as data (``services/policies/presets/morph_*.toml``), validated by pydantic.

A preset names its rule set (``reference`` or ``paper``), its parameters, and its ablations as
parameter overrides. :func:`load_preset` reads a bundled preset by name or a TOML file by path;
:meth:`MorphPreset.resolve` applies an ablation and returns the validated :class:`MorphParams`.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from schemas.errors import invalid

ABLATIONS = ("v1", "v1_paper", "no_threshold", "no_reward", "no_neuromod", "reset_at_boundary")


class MorphParams(BaseModel):
    """Every MORPH parameter (names follow the paper's Table 2 where it has one)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    alpha: float = Field(ge=0, description="synaptic learning rate α")
    beta: float = Field(ge=0, description="homeostatic rate β")
    gamma: float = Field(gt=0, le=1, description="base decay (retention) γ")
    theta_form_start: float = Field(ge=0)
    theta_form_end: float = Field(ge=0)
    theta_form_anneal: int = Field(ge=1, description="steps over which θ_form anneals")
    theta_form_anneal_over: Literal["updates", "episode"] = Field(
        default="updates", description="anneal θ_form over theta_form_anneal updates (reference), or over the "
        "episode, 0 → T (paper's Table 2, θ_form^{0/T}; theta_form_anneal is then the fallback T when the policy "
        "is not told the episode length)")
    theta_adj_floor: float = Field(
        default=0.8, ge=0, le=1, description="θ_form,adj is floored at this fraction of θ_form's end value "
        "(reference: 0.8 → 0.36; the paper states no floor)")
    theta_prune: float = Field(ge=0)
    rho_target: float = Field(ge=0, le=1, description="target degree fraction")
    grace: int = Field(ge=0, description="grace period g (steps)")
    k: int = Field(ge=1, description="structural/homeostatic period (steps)")
    max_new_floor: int = Field(ge=0)
    max_new_cap: int = Field(ge=0)
    max_new_divisor: int = Field(ge=1)
    bcm_tau: float = Field(ge=0, le=1)
    bcm_gain: float = Field(ge=0)
    reward_alpha: float = Field(ge=0, description="delivery-burst learning rate α_r")
    credit_threshold: float = Field(ge=0, le=1)
    neuromod_gain: float = Field(ge=0)
    neuromod_explore: float = Field(ge=0)
    neuromod_ema: float = Field(gt=0, le=1)
    baseline_ema: float = Field(default=0.0, ge=0, le=1, description="rate of the running delivery baseline "
                                "η compares against (paper); 0 keeps the fixed d_exp (reference)")
    pred_boost: float = Field(ge=0)
    use_pred_hint: bool
    w_floor: float = Field(ge=0, le=1, description="dispatch floor: P = w_floor + (1 - w_floor) W")
    candidate: Literal["nearest", "preferred"] = Field(
        default="nearest",
        description="whom an AGV asks: the nearest free picker (reference), or (paper) a free picker it is "
        "linked to, the most preferred (W_ij) first, nearest among equals, else the nearest free picker",
    )
    cov: float = Field(ge=0, description="the reference's constant r^t; the paper preset's no_reward r^t")
    expected_delivery_rate: dict[str, float]
    default_expected_delivery_rate: float = Field(gt=0)
    reset_every: int = Field(default=0, ge=0, description="clear the state every this many steps (0: never)")
    # paper preset only
    use_step_reward: bool = True
    mi_window: int = Field(default=30, ge=2, description="ticks of task history kept (MI window)")
    mi_estimator: Literal["coassignment_rate", "nmi"] = Field(
        default="coassignment_rate",
        description="the paper's MI between task-assignment histories: plug-in NMI of the task-label sequences "
        "(0 whenever one agent held a single task all window, the usual AGV case) or the co-assignment rate",
    )
    task_window: int = Field(default=20, ge=1, description="ticks over which a task set T_i is collected")
    h_min: float = 0.0
    h_max: float = 1.0

    @model_validator(mode="after")
    def _check(self) -> MorphParams:
        if self.theta_form_end > self.theta_form_start:
            raise ValueError("theta_form_end must not exceed theta_form_start")
        if self.task_window > self.mi_window:
            raise ValueError("task_window must not exceed mi_window")
        if self.h_min > self.h_max:
            raise ValueError("h_min must not exceed h_max")
        for scale, rate in self.expected_delivery_rate.items():
            if rate <= 0:
                raise ValueError(f"expected_delivery_rate.{scale} must be > 0")
        return self

    def max_new(self, n: int) -> int:
        """Links formed per structural step at fleet size ``n`` (the reference's min(6, max(3, N//6)))."""
        return min(self.max_new_cap, max(self.max_new_floor, n // self.max_new_divisor))

    def d_exp(self, scale: str | None) -> float:
        if scale is None:
            return self.default_expected_delivery_rate
        return self.expected_delivery_rate.get(scale, self.default_expected_delivery_rate)


class MorphPreset(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    rules: Literal["reference", "paper"]
    description: str = ""
    params: MorphParams
    ablations: dict[str, dict[str, Any]] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check_ablations(self) -> MorphPreset:
        for name in self.ablations:
            self.resolve(name)  # raises ValueError naming the bad field
        return self

    def resolve(self, ablation: str | None = None) -> MorphParams:
        """Parameters with ``ablation`` applied (None or "full": the complete system)."""
        if ablation in (None, "", "full"):
            return self.params
        if ablation not in self.ablations:
            known = ", ".join(sorted(self.ablations)) or "none"
            raise ValueError(f"ablation: unknown {ablation!r} for preset {self.name!r} (known: {known})")
        data = self.params.model_dump()
        data.update(self.ablations[ablation])
        try:
            return MorphParams.model_validate(data)
        except ValidationError as exc:
            raise invalid(exc, f"ablations.{ablation}") from None


def _read_toml(text: str, source: str) -> MorphPreset:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"preset {source}: invalid TOML: {exc}") from None
    try:
        return MorphPreset.model_validate(data)
    except ValidationError as exc:
        raise invalid(exc, f"preset {source}") from None


_CACHE: dict[str, MorphPreset] = {}


def load_preset(name_or_path: str | Path) -> MorphPreset:
    """A bundled preset by name (``reference``, ``paper``) or a preset TOML file by path."""
    key = str(name_or_path)
    if key in _CACHE:
        return _CACHE[key]
    path = Path(key)
    if path.suffix == ".toml" and path.exists():
        preset = _read_toml(path.read_text(), key)
    else:
        res = resources.files("services.policies").joinpath("presets", f"morph_{key}.toml")
        if not res.is_file():
            raise ValueError(f"preset: unknown {key!r} (bundled: reference, paper; or a .toml path)")
        preset = _read_toml(res.read_text(), f"morph_{key}.toml")
    _CACHE[key] = preset
    return preset
