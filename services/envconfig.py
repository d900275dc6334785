"""Environment variables ⇄ CLI flags ⇄ RunConfig fields: one naming rule for every ``morph-sim`` option.

The rule: the flag ``--some-name`` is the environment variable ``MORPH_SOME_NAME`` and, when it configures the run,
the :class:`~services.runconfig.RunConfig` field ``some_name``. A flag given on the command line wins over
the variable; the variable wins over the default, and the default is the same whichever way the option arrives.
That is what lets ``docker-compose.yml`` configure containers with ``MORPH_SCALE=small`` while the local supervisor
passes ``--scale small``, and what ``docs/deploy.md`` tabulates (:func:`markdown_table`).

RunConfig fields already read their ``MORPH_*`` variables (``runconfig.config_from_args``); the per-command options
that are not part of the run's config (``agent --id``/``--instance``, ``monitor --prometheus-port``) get theirs from
:func:`apply_env_defaults`, which a command calls at the end of its ``add_arguments``.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from dataclasses import dataclass

from services.runconfig import ENV_PREFIX, RunConfig, is_switch

# Options that never come from the environment: they only make sense typed by hand.
NOT_FROM_ENV = frozenset({"help", "version"})


def env_for_flag(flag: str) -> str:
    """``--prometheus-port`` -> ``MORPH_PROMETHEUS_PORT``."""
    if not flag.startswith("--") or len(flag) < 3:
        raise ValueError(f"flag {flag!r} is not a long option like --scale")
    return ENV_PREFIX + flag[2:].replace("-", "_").upper()


def flag_for_env(name: str) -> str:
    """``MORPH_PROMETHEUS_PORT`` -> ``--prometheus-port``."""
    if not name.startswith(ENV_PREFIX) or len(name) <= len(ENV_PREFIX):
        raise ValueError(f"environment variable {name!r} does not start with {ENV_PREFIX}")
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
        if info.default_factory is not None:
            default = "generated"
        else:
            value = info.get_default(call_default_factory=False)
            default = None if value is None else str(value)
        out.append(Variable(RunConfig.env_name(name), RunConfig.flag(name), name, default, info.description or ""))
    return out


def _long_flag(action: argparse.Action) -> str | None:
    longs = [s for s in action.option_strings if s.startswith("--")]
    return longs[0] if longs else None


def command_parser(command: str) -> argparse.ArgumentParser:
    """The argparse parser of ``morph-sim <command>`` (built by the real CLI)."""
    from morph_sim.cli import build_parser

    parser = build_parser()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            if command not in action.choices:
                raise ValueError(f"command {command!r} does not exist (known: {', '.join(sorted(action.choices))})")
            return action.choices[command]
    raise ValueError("the morph-sim parser has no subcommands")


def command_variables(command: str) -> list[Variable]:
    """Every long option of ``morph-sim <command>`` as a variable (RunConfig fields and per-command options)."""
    fields = {RunConfig.flag(name): name for name in RunConfig.model_fields}
    by_flag = {v.flag: v for v in config_variables()}
    out = []
    for action in command_parser(command)._actions:
        flag = _long_flag(action)
        if flag is None or action.dest in NOT_FROM_ENV:
            continue
        if flag in by_flag:
            out.append(by_flag[flag])
        else:
            default = None if action.default in (None, argparse.SUPPRESS) else str(action.default)
            out.append(Variable(env_for_flag(flag), flag, fields.get(flag), default, action.help or ""))
    return out


def apply_env_defaults(parser: argparse.ArgumentParser, environ: Mapping[str, str] | None = None) -> None:
    """Make every per-command option of ``parser`` default to its ``MORPH_*`` variable when that is set.

    RunConfig options (dest ``cfg_<field>``) are left alone: ``config_from_args`` reads their variables itself, after
    flags, with one validation path. Values are converted with the option's ``type`` so a bad value fails at parse
    time naming the variable.
    """
    environ = os.environ if environ is None else environ
    for action in parser._actions:
        flag = _long_flag(action)
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


def env_to_argv(command: str, environ: Mapping[str, str]) -> list[str]:
    """The command-line flags that ``environ`` stands for, for ``morph-sim <command>`` (unknown MORPH_* rejected).

    Used to check that a compose file's environment means the same as the supervisor's command lines.
    """
    known = {v.env: v for v in command_variables(command)}
    argv: list[str] = []
    for name, value in environ.items():
        if not name.startswith(ENV_PREFIX):
            continue
        if name not in known:
            raise ValueError(f"{name}: no option {flag_for_env(name)} in 'morph-sim {command}'")
        if value == "":
            continue
        field = known[name].field
        if field is not None and is_switch(field):  # a switch: --flag or --no-flag, no value
            flag = known[name].flag
            argv.append(flag if value.strip().lower() in ("1", "true", "yes", "on") else "--no-" + flag[2:])
        else:
            argv += [known[name].flag, value]
    return argv


def markdown_table(command: str) -> str:
    """A table of ``morph-sim <command>``'s options: variable, flag, default, meaning (for docs/deploy.md)."""
    rows = ["| Variable | Flag | Default | Meaning |", "|---|---|---|---|"]
    for v in command_variables(command):
        default = "—" if v.default is None else f"`{v.default}`"
        rows.append(f"| `{v.env}` | `{v.flag}` | {default} | {v.help.replace('|', '/')} |")
    return "\n".join(rows)
