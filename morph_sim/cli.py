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


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
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
