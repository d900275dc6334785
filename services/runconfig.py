"""The one configuration model of a run, shared by every service, the supervisor and the compose file.

A :class:`RunConfig` travels three ways, all derived from the field list below so they cannot drift apart:

* CLI flags: ``--scale medium --policy morph --seed 42`` (``add_config_arguments`` / ``from_args``);
* environment variables with the same names: ``MORPH_SCALE=medium MORPH_POLICY=morph`` (``from_env`` / ``to_env``),
  what docker-compose.yml sets;
* argv for a child process (``to_argv``), what the supervisor passes to ``morph-sim sim|agent|monitor``.

Invalid values raise ``ValueError`` naming the field (pydantic ``ValidationError`` is one).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Mapping
from functools import cached_property
from pathlib import Path
from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from schemas.keys import validate_run_id

ENV_PREFIX = "MORPH_"
OptionValue = str | int | float | bool | None
#: a policy's own fields that RunConfig also sets by a flag of its own (kept: the CLI is stable)
POLICY_FLAGS = {"constant": ("p",), "proximity": ("radius",), "morph": ("preset", "ablation")}
PRESETS = ("reference", "paper")
#: Most ticks a run may have: 10 million is 115 days of robot time at Δ = 1 s, and the monitor's record grows by a
#: row per tick (a few GB at this bound), so a larger count is a typing slip, not a study.
MAX_STEPS = 10_000_000


def default_run_id() -> str:
    # Wall-clock based: run ids name directories under runs/, they never enter the simulation.
    return time.strftime("run-%Y%m%d-%H%M%S", time.gmtime()) + f"-{os.getpid() % 10000:04d}"


class RunConfig(BaseModel):
    """Everything that defines one run. Same config and seed ⇒ same trajectory (faults aside)."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)

    run_id: str = Field(default_factory=default_run_id, description="run id: key prefix morph/<run>/ and record dir")
    scale: str = Field(default="tiny", description="warehouse size: tiny, small, medium, large, extralarge")
    agvs: int | None = Field(default=None, ge=1, le=2048, description="number of AGVs (default: the scale's)")
    pickers: int | None = Field(default=None, ge=1, le=2048, description="number of pickers (default: the scale's)")
    policy: str = Field(
        default="morph", description="coordination policy: a shipped name (full, full-broadcast, constant, tsg, "
        "proximity, none, morph), an installed one (entry point group morph_sim.policies) or package.module:Class")
    policy_options: dict[str, OptionValue] = Field(
        default_factory=dict, description="a parameter of the policy (`morph-sim policy show NAME` lists them); "
        "in the environment KEY=VALUE,KEY=VALUE or a JSON object")
    preset: Literal["reference", "paper"] = Field(default="reference", description="MORPH preset")
    ablation: str | None = Field(default=None, description="MORPH ablation name (None = full model)")
    p: float = Field(default=0.25, ge=0.0, le=1.0, description="gate probability of the constant policy")
    radius: int = Field(default=4, ge=0, description="link radius of the proximity policy")
    seed: int = Field(default=42, ge=0, lt=2**63, description="seed of the warehouse and of every agent's RNG")
    steps: int = Field(default=200, ge=1, le=MAX_STEPS, description="ticks to run")
    dt: float = Field(default=1.0, gt=0.0, le=3600.0, description="Δ: seconds of robot time per step")
    mode: Literal["lockstep", "paced"] = Field(
        default="lockstep", description="lockstep: next tick when every agent answered; paced: real period")
    period: float = Field(default=0.1, gt=0.0, le=60.0, description="paced mode: wall seconds per tick")
    phase_timeout: float = Field(
        default=10.0, gt=0.0, le=3600.0,
        description="lockstep: wall seconds a phase waits before marking silent agents absent")
    ready_timeout: float = Field(default=120.0, gt=0.0, description="wall seconds to wait for every agent before tick 0")
    request_timeout: float = Field(
        default=5.0, gt=0.0, le=3600.0,
        description="sim seconds an AGV waits for the answer to a help request before it may ask again "
        "(services/protocol/dispatch.py: DEFAULT_REQUEST_TIMEOUT)")
    state_every: int = Field(default=10, ge=1, description="k: agents publish their state every k ticks")
    snapshot_every: int = Field(default=50, ge=1, description="monitor: W/A snapshot every this many ticks")
    cold_restart: bool = Field(
        default=False, description="a restarted agent starts from zero instead of the monitor's latest state")
    fault_schedule: Path | None = Field(
        default=None, description="TOML schedule of timed faults (docs/faults.md); crash faults go to the supervisor")
    fault_time: Literal["virtual", "wall"] = Field(
        default="virtual", description="fault latency and heals in sim seconds at phase boundaries (virtual: "
        "reproducible) or in real seconds (wall: real sleeps, for paced demos)")
    network: str | None = Field(
        default=None, description="network profile (lan, wifi-fast-roaming, wifi-legacy-roaming, lossy-mesh, ... or "
        "a .toml file; docs/faults.md): position-dependent Wi-Fi under the fault specs; None = ideal network")
    endpoint: str | None = Field(
        default=None, description="Zenoh endpoint to connect to (e.g. tcp/127.0.0.1:7447); None = LocalBus/listen")
    listen: str | None = Field(default=None, description="Zenoh endpoint the sim listens on (supervisor sets it)")
    output_dir: Path = Field(default=Path("runs"), description="parent directory of run records")

    @field_validator("run_id")
    @classmethod
    def _run_id(cls, value: str) -> str:
        return validate_run_id(value)

    @field_validator("scale")
    @classmethod
    def _scale(cls, value: str) -> str:
        from services.world.layout import named_sizes

        if value not in named_sizes():
            raise ValueError(f"unknown size {value!r}; choose one of {', '.join(named_sizes())}")
        return value

    @field_validator("network")
    @classmethod
    def _network(cls, value: str | None) -> str | None:
        if value is None or value == "":
            return None
        from services.faults.network import load_profile

        try:
            load_profile(value)
        except ValueError as exc:
            # "network wifi.toml: …" once, under the field's own name
            raise ValueError(str(exc).removeprefix("network: ").removeprefix("network ")) from None
        return value

    @model_validator(mode="after")
    def _network_time(self) -> RunConfig:
        if self.network is not None and self.fault_time != "virtual":
            raise ValueError("network: a network profile needs --fault-time virtual (positions and hand-overs are "
                             "in sim time)")
        if self.network is not None and self.mode == "paced" and self.shared_air:
            raise ValueError(f"network: profile {self.network!r} limits rates (link_rate/ap_rate), which the air "
                             "judges an instant at a time once all of it was sent; a paced fleet acts on what it has "
                             "in time: use --mode lockstep")
        return self

    @property
    def shared_air(self) -> bool:
        """Whether the run's network profile has shared capacity: the air process then judges its radio
        (services/faults/air.py)."""
        if self.network is None:
            return False
        from services.faults.air import has_shared_capacity
        from services.faults.network import load_profile

        return has_shared_capacity(load_profile(self.network))

    @field_validator("endpoint", "listen")
    @classmethod
    def _endpoint(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is None or value == "":
            return None
        from services.inputs import endpoint

        return endpoint(value, info.field_name, listen=info.field_name == "listen")

    @field_validator("policy_options", mode="before")
    @classmethod
    def _policy_options(cls, value: Any) -> Any:
        return parse_policy_options(value)

    @model_validator(mode="after")
    def _ablation(self) -> RunConfig:
        if self.ablation is not None and self.policy == "morph":
            from services.policies.presets import ABLATIONS

            if self.ablation != "full" and self.ablation not in ABLATIONS:
                raise ValueError(f"ablation: unknown {self.ablation!r} (known: {', '.join(ABLATIONS)})")
        return self

    @model_validator(mode="after")
    def _policy(self) -> RunConfig:
        from services.policies.loading import check_name

        check_name(self.policy)
        for key, option in self.policy_options.items():
            # a shipped policy's own flag and the option name one parameter: the option wins over the flag's default
            # (as a child's command line carries both), two different values given are refused
            if key in POLICY_FLAGS.get(self.policy, ()):
                flag = getattr(self, key)
                if flag != type(self).model_fields[key].default and option_text(flag) != option_text(option):
                    raise ValueError(f"policy-option {key}: {option_text(option)} differs from "
                                     f"{self.flag(key)} {option_text(flag)}; give it once")
        self.make_policy()  # one line naming the policy or the option when either is bad
        return self

    @model_validator(mode="after")
    def _fleet_fits(self) -> RunConfig:
        # Checked here, not only in the sim: `up` would otherwise start one process per robot of a fleet the layout
        # cannot hold before the sim refuses it.
        if self.agvs is None and self.pickers is None:
            return self
        from services.world.warehouse import WarehouseConfig

        try:
            WarehouseConfig.named(self.scale, self.n_agvs, self.n_pickers)
        except ValidationError as exc:
            why = "; ".join(str(e.get("msg", "")).removeprefix("Value error, ") for e in exc.errors())
            raise ValueError(f"{why} (scale {self.scale})") from None
        except ValueError as exc:
            raise ValueError(f"{exc} (scale {self.scale})") from None
        return self

    # -- derived ---------------------------------------------------------------------------------------------------
    # cached: services read these on every message
    @cached_property
    def n_agvs(self) -> int:
        from services.world.layout import named_sizes

        return self.agvs if self.agvs is not None else named_sizes()[self.scale][1]

    @cached_property
    def n_pickers(self) -> int:
        from services.world.layout import named_sizes

        return self.pickers if self.pickers is not None else named_sizes()[self.scale][2]

    @cached_property
    def n_agents(self) -> int:
        return self.n_agvs + self.n_pickers

    @property
    def record_dir(self) -> Path:
        return Path(self.output_dir) / self.run_id

    def policy_arguments(self) -> dict[str, Any]:
        """The options the policy is built with: a shipped policy's own flags (``--radius``, ``--preset`` …), then
        ``policy_options``; MORPH also takes the episode length."""
        out: dict[str, Any] = {name: getattr(self, name) for name in POLICY_FLAGS.get(self.policy, ())}
        if self.policy == "morph":
            out["episode_steps"] = self.steps
        out.update(self.policy_options)
        return out

    def make_policy(self):
        from services.policies.loading import make_policy

        return make_policy(self.policy, self.policy_arguments())

    def policy_announcement(self):
        """The policy this configuration builds, as the sim announces it and an agent compares it."""
        from schemas.messages import PolicyAnnouncement

        return PolicyAnnouncement(policy=self.policy, options=self.make_policy().options())

    def role_of(self, agent: int) -> str:
        if not 0 <= agent < self.n_agents:
            raise ValueError(f"agent: id {agent} outside 0..{self.n_agents - 1}")
        return "agv" if agent < self.n_agvs else "picker"

    # -- transports: CLI flags, environment, argv --------------------------------------------------------------------
    @staticmethod
    def flag(name: str) -> str:
        # a repeatable flag names one item (--policy-option KEY=VALUE), its field holds them all
        return "--policy-option" if name == "policy_options" else "--" + name.replace("_", "-")

    @staticmethod
    def env_name(name: str) -> str:
        return ENV_PREFIX + name.upper()

    @classmethod
    def coerce(cls, values: Mapping[str, Any]) -> RunConfig:
        """Validate, turning pydantic's error into one ValueError line naming the field."""
        try:
            return cls(**{k: v for k, v in values.items() if v is not None})
        except ValidationError as exc:
            from schemas.errors import explain

            raise ValueError(explain(exc, first_only=True)) from None

    def to_env(self) -> dict[str, str]:
        """Environment variables (``MORPH_<FIELD>``) that reproduce this config through :meth:`from_env`."""
        out = {}
        for name, value in self.model_dump(mode="json").items():
            if name == "policy_options":
                if value:
                    out[self.env_name(name)] = json.dumps(value, sort_keys=True)
            elif value is not None:
                out[self.env_name(name)] = str(value)
        return out

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **overrides: Any) -> RunConfig:
        environ = os.environ if environ is None else environ
        values: dict[str, Any] = {}
        for name in cls.model_fields:
            raw = environ.get(cls.env_name(name))
            if raw not in (None, ""):
                values[name] = raw
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls.coerce(values)

    def to_argv(self, fields: tuple[str, ...] | None = None) -> list[str]:
        """``--flag value`` pairs for a child ``morph-sim`` command (only fields that differ from None)."""
        argv: list[str] = []
        dumped = self.model_dump(mode="json")
        for name in fields or tuple(type(self).model_fields):
            value = dumped[name]
            if value is None:
                continue
            if name == "policy_options":
                for key, option in value.items():
                    argv += [self.flag(name), f"{key}={option_text(option)}"]
                continue
            if is_switch(name):
                argv.append(self.flag(name) if value else "--no-" + self.flag(name)[2:])
            else:
                argv += [self.flag(name), str(value)]
        return argv


def option_text(value: Any) -> str:
    """A policy option's value as ``--policy-option`` writes it (JSON's spelling of true, false and null)."""
    return value if isinstance(value, str) else json.dumps(value)


def parse_policy_options(value: Any) -> Any:
    """Policy options from a mapping, ``KEY=VALUE`` strings (the repeated flag), or one string (the environment:
    a JSON object, or KEY=VALUE pairs separated by commas); ValueError naming the option otherwise. Values given as
    text stay text: the policy's own parameter model converts them."""
    from services.policies.loading import parse_option

    if value is None:
        return {}
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("{"):
            try:
                value = json.loads(text)
            except json.JSONDecodeError as exc:
                raise ValueError(f"policy_options: not a JSON object: {exc.msg}") from None
            if not isinstance(value, dict):
                raise ValueError("policy_options: not a JSON object")
            return value
        value = [part for part in text.split(",") if part.strip()]
    if isinstance(value, list | tuple):
        out: dict[str, str] = {}
        for item in value:
            key, text = parse_option(str(item))
            if key in out:
                raise ValueError(f"policy-option {key}: given twice")
            out[key] = text
        return out
    return value


def field_choices(name: str) -> tuple[str, ...] | None:
    """The values a RunConfig field takes, when it is a closed set (a Literal, or the named warehouse sizes)."""
    if name == "scale":
        from services.world.layout import named_sizes

        return tuple(named_sizes())
    if name == "ablation":
        from services.policies.presets import ABLATIONS

        return ("full", *ABLATIONS)
    args = get_args(RunConfig.model_fields[name].annotation)
    return tuple(args) if args and all(isinstance(a, str) for a in args) else None


def is_switch(name: str) -> bool:
    """A yes/no field: a switch on the command line (``--cold-restart`` / ``--no-cold-restart``)."""
    return RunConfig.model_fields[name].annotation is bool


def add_config_arguments(parser: argparse.ArgumentParser, *, skip: tuple[str, ...] = ()) -> None:
    """One flag per RunConfig field; every default is None so env variables and model defaults apply. A closed set
    of values is listed in the help (and checked by argparse); a yes/no field is a switch."""
    group = parser.add_argument_group("run configuration (flags override MORPH_* environment variables)")
    for name, info in RunConfig.model_fields.items():
        if name in skip:
            continue
        default = info.get_default(call_default_factory=False)
        shown = "generated" if info.default_factory is not None else default
        where = f"(env {RunConfig.env_name(name)}; default {shown})"
        if is_switch(name):
            group.add_argument(RunConfig.flag(name), dest=f"cfg_{name}", default=None,
                               action=argparse.BooleanOptionalAction, help=f"{info.description} {where}")
            continue
        if name == "policy_options":
            group.add_argument(RunConfig.flag(name), dest=f"cfg_{name}", default=None, action="append",
                               metavar="KEY=VALUE", help=f"{info.description}; repeatable (env {RunConfig.env_name(name)})")
            continue
        choices = field_choices(name)  # shown in the usage as {a,b,…}
        group.add_argument(RunConfig.flag(name), dest=f"cfg_{name}", default=None, choices=choices,
                           metavar=None if choices else name.upper(), help=f"{info.description} {where}")


def config_from_args(args: argparse.Namespace, environ: Mapping[str, str] | None = None, **overrides: Any
                     ) -> RunConfig:
    """Config from flags, falling back to MORPH_* environment variables, then to the model defaults."""
    flags = {name[4:]: value for name, value in vars(args).items() if name.startswith("cfg_") and value is not None}
    flags.update({k: v for k, v in overrides.items() if v is not None})
    return RunConfig.from_env(environ, **flags)
