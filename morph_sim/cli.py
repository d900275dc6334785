"""The ``morph-sim`` command line: discovers subcommands in :mod:`morph_sim.commands`."""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from collections.abc import Sequence

# One BLAS thread per process, set before anything imports numpy: the tool runs many small processes side by side
# (a run's services, a study's workers, operator commands), its matrices are small, and starting OpenBLAS's own
# threads costs each process a tenth of a CPU-second (a run's services get the same from their supervisor).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from morph_sim import __version__, commands  # noqa: E402


def _command_names() -> list[str]:
    """The subcommands, from the module names alone (nothing imported)."""
    return sorted(info.name for info in pkgutil.iter_modules(commands.__path__) if not info.name.startswith("_"))


def _command_modules(only: str | None = None):
    for name in _command_names():
        if only is None or name == only:
            yield importlib.import_module(f"{commands.__name__}.{name}")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole command line, or with ``only`` the one subcommand of that name: a process started as
    ``morph-sim agent …`` (each process of a distributed run) then imports and builds its own command and not
    the others, whose option set-up imports the lab, the presets and the reports."""
    parser = argparse.ArgumentParser(
        prog="morph-sim",
        description="MORPH multi-robot task allocation in a TA-RWARE-style warehouse.",
    )
    parser.add_argument("--version", action="version", version=f"morph-sim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _command_modules(only):
        cmd = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP,
                             epilog=getattr(module, "EPILOG", None))
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run)
    return parser


def _chosen(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost (sub)command parser ``args`` went through, e.g. that of ``morph-sim faults set``."""
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or getattr(args, subs[0].dest, None) not in subs[0].choices:
            return parser
        parser = subs[0].choices[getattr(args, subs[0].dest)]


# Set while `morph-sim up` starts again with room for its children's command lines (see _make_room_for_command_lines).
_ROOM = "MORPH_SIM_UP_ROOM"


def _make_room_for_command_lines(argv: list[str]) -> list[str]:
    """``up`` forks its run's processes from a copy of itself, and each shows its own command line (``ps``,
    ``/proc/<pid>/cmdline``) by writing it into the argument space it inherits, which is as large as the command
    line this process was started with: ``morph-sim up`` alone leaves no room for ``… -m services.agent --id 3 …``.
    So a process started with less starts once more, before it imports anything heavy, with an argument of padding;
    it then shows its own command line without it. The argv to parse."""
    import json

    started_as = os.environ.pop(_ROOM, None)
    if started_as is not None:
        if argv and not argv[-1].strip():
            argv = argv[:-1]
        from services.supervisor.forkserver import set_command_line

        set_command_line(json.loads(started_as))  # as it was first started (`morph-sim up …`)
        return argv
    if not argv or argv[0] != "up" or {"-h", "--help"} & set(argv):
        return argv
    from services.supervisor.forkserver import TITLE_SPACE, argument_space

    if argument_space() >= TITLE_SPACE or not sys.executable:
        return argv
    try:
        with open("/proc/self/cmdline", "rb") as f:
            started_as = f.read().rstrip(b"\0").decode(errors="replace").split("\0")
    except OSError:
        started_as = [sys.executable, *sys.argv]
    os.environ[_ROOM] = json.dumps(started_as)
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        os.execv(sys.executable, [sys.executable, "-m", "morph_sim.cli", *argv, " " * TITLE_SPACE])
    except OSError:  # the interpreter cannot be started again here: the run's processes then come from a fresh one
        os.environ.pop(_ROOM, None)
    return argv


def main(argv: Sequence[str] | None = None) -> int:
    # only as the process's own command line: a test (or any caller) running main() in its process keeps it
    argv = _make_room_for_command_lines(sys.argv[1:]) if argv is None else list(argv)
    # the full parser when no subcommand comes first (--help, --version, a typo: argparse lists every choice)
    only = argv[0] if argv and argv[0] in _command_names() else None
    parser = build_parser(only)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # argparse would blame the top-level command; name the subcommand's usage instead
        _chosen(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ValueError as exc:  # config validation errors: one clear line, no traceback
        print(f"morph-sim {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ConnectionError as exc:  # no endpoint there, or it refuses these credentials: one line
        print(f"morph-sim {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
