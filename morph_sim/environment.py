"""The CLI's environment mapping: every option of a ``morph-sim`` command as its ``MORPH_*`` variable.

The naming rule itself (``--some-name`` ⇄ ``MORPH_SOME_NAME``) and the reading of variables by a service process are
:mod:`services.envconfig`; this module adds what needs the whole CLI's parser: the variables of any command, the
command line a container's environment stands for (used to check the compose file and the manifests against the
supervisor's command lines), and the table of them in docs/deploy.md.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping

from services.envconfig import NOT_FROM_ENV, Variable, config_variables, env_for_flag, flag_for_env, long_flag
from services.runconfig import ENV_PREFIX, RunConfig, is_switch


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
        flag = long_flag(action)
        if flag is None or action.dest in NOT_FROM_ENV:
            continue
        if flag in by_flag:
            out.append(by_flag[flag])
        else:
            default = None if action.default in (None, argparse.SUPPRESS) else str(action.default)
            out.append(Variable(env_for_flag(flag), flag, fields.get(flag), default, action.help or ""))
    return out


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
        if field == "policy_options":  # one flag per option
            from services.runconfig import option_text, parse_policy_options

            for key, option in parse_policy_options(value).items():
                argv += [known[name].flag, f"{key}={option_text(option)}"]
        elif field is not None and is_switch(field):  # a switch: --flag or --no-flag, no value
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
