"""``morph-sim report RUN_DIR…``: a Markdown report with figures and a warehouse GIF from one or more run records."""

from __future__ import annotations

import argparse
import sys

NAME = "report"
HELP = "Markdown report (figures, warehouse GIF) of one or more run records"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dirs", nargs="+", help="run record directories (runs/<run-id>)")
    parser.add_argument("--out", default=None, help="report directory (default: <first RUN_DIR>/report)")
    parser.add_argument("--no-gif", action="store_true", help="skip the warehouse animation")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.inputs import output_dir
    from services.monitor.report import write_report

    out = output_dir(args.out if args.out else Path(args.run_dirs[0]) / "report", "out")
    cut: list[str] = []
    md = write_report([Path(d) for d in args.run_dirs], out, gif=not args.no_gif, notes=cut)
    if cut:  # the report is made from the lines before; said once, so nobody takes the record for whole
        print(f"morph-sim report: warning: left out the unfinished last line of {', '.join(cut)} (its writer "
              "stopped mid-line: a killed monitor or a full disk)", file=sys.stderr)
    print(md)
    return 0
