"""The one table of experimental conditions: a condition key names a policy, its MORPH preset and ablation, its
Proximity radius and the label the study tables print.

Every study (the scale and ablation suites, the demand shift, the fault and network studies, the paper-preset
audit) and the sweep's lab engine read their conditions here; a study's own list is a selection of keys from
:data:`CONDITIONS`. ``preset`` None means the study's preset (the suite's ``--preset``, the episode's);
``radius`` None means the study's radius (calibrated by the suite, given by the shift study, RunConfig's default
elsewhere: :data:`DEFAULT_RADIUS`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from services.policies.coordinators import MorphPolicy, ProximityPolicy
from services.policies.interface import CoordinationPolicy
from services.policies.loading import make_policy

#: RunConfig's default link radius of the proximity policy: the radius where a study does not calibrate one
DEFAULT_RADIUS = 4


@dataclass(frozen=True)
class Condition:
    key: str
    label: str
    policy: str  # a policy name of services.policies.coordinators
    ablation: str | None = None  # a MORPH ablation of the preset
    preset: str | None = None  # None: the study's preset
    radius: int | None = None  # None: the study's radius (proximity only)

    @property
    def plastic(self) -> bool:
        return self.policy == "morph"

    def episode_fields(self, preset: str = "reference", radius: int | None = None) -> dict:
        """The lab episode's ``condition``, ``preset`` and ``radius`` of this condition in a study of ``preset`` and
        ``radius``: a pinned preset runs as the study-preset condition of the same policy and ablation, so the
        episode (and its key) is the one that condition gives at that preset. A policy from outside runs by name."""
        from services.policies.coordinators import POLICIES

        if self.policy not in POLICIES:
            return {"condition": self.key, "policy_name": self.policy, "preset": preset, "radius": None}
        return {"condition": key_of(self.policy, self.ablation), "preset": self.preset or preset,
                "radius": (self.radius if self.radius is not None else radius) if self.policy == "proximity" else None}


CONDITIONS: dict[str, Condition] = {c.key: c for c in (
    # the scale and ablation studies' conditions, in the reference's order; MORPH at the study's preset
    Condition("none", "No coordination", "none"),
    Condition("proximity", "Proximity", "proximity"),
    Condition("tsg", "TSG", "tsg"),
    Condition("v1", "MORPH v1", "morph", "v1"),
    Condition("v1_paper", "MORPH v1 (paper: −R4)", "morph", "v1_paper"),
    Condition("no_threshold", "v2 − threshold", "morph", "no_threshold"),
    Condition("no_reward", "v2 − reward", "morph", "no_reward"),
    Condition("no_neuromod", "v2 − neuromod", "morph", "no_neuromod"),
    Condition("morph", "MORPH", "morph"),
    Condition("full", "Full-Graph", "full"),
    Condition("full-broadcast", "Full-Graph (broadcast)", "full-broadcast"),
    Condition("constant", "Constant 0.25", "constant"),
    Condition("reset_at_boundary", "MORPH-reset", "morph", "reset_at_boundary"),
    # MORPH at a named preset: the studies that compare the two presets side by side
    Condition("morph_reference", "MORPH (reference)", "morph", preset="reference"),
    Condition("morph_paper", "MORPH (paper)", "morph", preset="paper"),
    Condition("reset_reference", "MORPH-reset (reference)", "morph", "reset_at_boundary", preset="reference"),
    Condition("reset_paper", "MORPH-reset (paper)", "morph", "reset_at_boundary", preset="paper"),
)}

#: the studies' selections (keys of CONDITIONS, in table order)
SCALE_STUDY = ("none", "proximity", "tsg", "v1", "no_threshold", "no_reward", "no_neuromod", "morph", "full")
ABLATION_STUDY = ("v1", "no_threshold", "no_reward", "no_neuromod", "reset_at_boundary", "morph")
AUDIT_STUDY = ("morph", "v1", "v1_paper", "tsg", "full", "proximity")
SHIFT_STUDY = ("morph_reference", "reset_reference", "morph_paper", "reset_paper", "proximity", "tsg")
FAULT_STUDY = ("morph_reference", "morph_paper", "full", "tsg", "proximity")
NETWORK_STUDY = ("morph_reference", "morph_paper", "full", "full-broadcast", "tsg", "proximity")
#: the fault and network studies' command lines name their two MORPH presets ``morph`` and ``morph-paper``
PRESET_STUDY_KEYS = {"morph": "morph_reference", "morph-paper": "morph_paper"}


def select(keys: Iterable[str]) -> dict[str, Condition]:
    """The conditions of ``keys`` (a study's selection), in the given order; ValueError naming an unknown key."""
    out = {}
    for k in keys:
        if k not in CONDITIONS:
            raise ValueError(f"condition: unknown {k!r} (known: {', '.join(CONDITIONS)})")
        out[k] = CONDITIONS[k]
    return out


def study_condition(name: str, table: Mapping[str, Condition]) -> Condition:
    """A study's condition: ``name``'s entry in the study's ``table``, or a policy from outside by the name
    ``--policy`` takes (its label is that name); ValueError naming ``conditions`` otherwise."""
    if name in table:
        return table[name]
    from services.policies.loading import resolve

    try:
        resolve(name)
    except ValueError as exc:
        raise ValueError(f"conditions: unknown {name!r}; choose from {', '.join(table)} or a policy name "
                         f"({str(exc).removeprefix('policy: ')})") from None
    return Condition(name, name, name)


def by_label(keys: Iterable[str]) -> dict[str, Condition]:
    """A selection keyed by label: the studies whose records name a condition by its label."""
    return {c.label: c for c in select(keys).values()}


def command_line_keys(keys: Iterable[str]) -> dict[str, Condition]:
    """A selection under the names the fault and network studies' command lines give it (``morph`` for the
    reference preset's MORPH, ``morph-paper`` for the paper preset's, the table's key otherwise)."""
    names = {v: k for k, v in PRESET_STUDY_KEYS.items()}
    return {names.get(k, k): c for k, c in select(keys).items()}


def key_of(policy: str, ablation: str | None = None, preset: str | None = None) -> str:
    """The condition key of a RunConfig's policy, ablation and (pinned) preset; ValueError if the table has none."""
    ablation = None if ablation == "full" else ablation
    for c in CONDITIONS.values():
        if (c.policy, c.ablation, c.preset) == (policy, ablation, preset):
            return c.key
    raise ValueError(f"ablation: the lab has no condition for policy {policy!r} with ablation {ablation!r}")


def make_condition_policy(condition: str, preset: str = "reference", radius: int | None = None,
                          reset_every: int | None = None, steps: int | None = None) -> CoordinationPolicy:
    """The policy of condition ``condition`` (its pinned preset, else ``preset``; its radius, else ``radius``)."""
    c = select([condition])[condition]
    if c.policy == "morph":
        return MorphPolicy(preset=c.preset or preset, ablation=c.ablation,
                           reset_every=reset_every if c.ablation == "reset_at_boundary" else None,
                           episode_steps=steps)
    if c.policy == "proximity":
        radius = c.radius if c.radius is not None else radius
        if radius is None:
            raise ValueError("radius: the proximity condition needs a radius (or calibration)")
        return ProximityPolicy(radius=radius)
    return make_policy(c.policy)
