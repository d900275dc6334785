"""Environment variables ⇄ CLI flags ⇄ RunConfig fields: one naming rule for every ``morph-sim`` option.

The rule: the flag ``--some-name`` is the environment variable ``MORPH_SOME_NAME`` and, when it configures the run,
the :class:`~services.runconfig.RunConfig` field ``some_name``. A flag given on the command line wins over
the variable; the variable wins over the default, and the default is the same whichever way the option arrives.
That is what lets ``docker-compose.yml`` configure containers with ``MORPH_SCALE=small`` while the local supervisor
passes ``--scale small``; the CLI's whole mapping (every command's variables, the table in ``docs/deploy.md``) is
:mod:`morph_sim.environment`.

RunConfig fields already read their ``MORPH_*`` variables (``runconfig.config_from_args``); the per-command options
that are not part of the run's config (``agent --id``/``--instance``, ``monitor --prometheus-port``) get theirs from
:func:`apply_env_defaults`, which a command calls at the end of its ``add_arguments``.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from dataclasses import dataclass

from services.runconfig import ENV_PREFIX, RunConfig

# Options that never come from the environment: they only make sense typed by hand.
NOT_FROM_ENV = frozenset({"help", "version"})


#: the one exception to the rule: a repeatable flag names one item, its variable holds them all
REPEATED = {"--policy-option": ENV_PREFIX + "POLICY_OPTIONS"}


def env_for_flag(flag: str) -> str:
    """``--prometheus-port`` -> ``MORPH_PROMETHEUS_PORT``."""
    if not flag.startswith("--") or len(flag) < 3:
        raise ValueError(f"flag {flag!r} is not a long option like --scale")
    return REPEATED.get(flag) or ENV_PREFIX + flag[2:].replace("-", "_").upper()


def flag_for_env(name: str) -> str:
    """``MORPH_PROMETHEUS_PORT`` -> ``--prometheus-port``."""
    if not name.startswith(ENV_PREFIX) or len(name) <= len(ENV_PREFIX):
        raise ValueError(f"environment variable {name!r} does not start with {ENV_PREFIX}")
    for flag, env in REPEATED.items():
        if env == name:
            return flag
    return "--" + name[len(ENV_PREFIX):].lower().replace("_", "-")


@dataclass(frozen=True)
class Variable:
    env: str  # MORPH_SCALE
    flag: str  # --scale
    field: str | None  # RunConfig field, or None for a per-command option
    default: str | None  # as text, None = unset ("generated" for a generated default)
    help: str = ""


def config_variables() -> list[Variable]:
    """One variable per RunConfig field, in field order."""
    out = []
    for name, info in RunConfig.model_fields.items():
        if name == "policy_options":
            default = None  # none: the policy's own defaults
        elif info.default_factory is not None:
            default = "generated"
        else:
            value = info.get_default(call_default_factory=False)
            default = None if value is None else str(value)
        out.append(Variable(RunConfig.env_name(name), RunConfig.flag(name), name, default, info.description or ""))
    return out


def long_flag(action: argparse.Action) -> str | None:
    longs = [s for s in action.option_strings if s.startswith("--")]
    return longs[0] if longs else None


def apply_env_defaults(parser: argparse.ArgumentParser, environ: Mapping[str, str] | None = None) -> None:
    """Make every per-command option of ``parser`` default to its ``MORPH_*`` variable when that is set.

    RunConfig options (dest ``cfg_<field>``) are left alone: ``config_from_args`` reads their variables itself, after
    flags, with one validation path. Values are converted with the option's ``type`` so a bad value fails at parse
    time naming the variable.
    """
    environ = os.environ if environ is None else environ
    for action in parser._actions:
        flag = long_flag(action)
        if flag is None or action.dest in NOT_FROM_ENV or action.dest.startswith("cfg_"):
            continue
        raw = environ.get(env_for_flag(flag))
        if raw in (None, ""):
            continue
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            value: object = raw.strip().lower() in ("1", "true", "yes", "on")
            if isinstance(action, argparse._StoreFalseAction):
                value = not value
        elif isinstance(action, argparse._StoreAction):
            try:
                value = action.type(raw) if action.type is not None else raw
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{env_for_flag(flag)}: {raw!r} is not valid for {flag} ({exc})") from None
            if action.choices is not None and value not in action.choices:
                raise ValueError(f"{env_for_flag(flag)}: {raw!r} is not one of {sorted(action.choices)}")
        else:
            continue  # counters and lists are not configured from the environment
        parser.set_defaults(**{action.dest: value})
