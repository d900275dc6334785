"""``morph-sim schemas export DIR``: write the JSON Schema of every wire message."""

from __future__ import annotations

import argparse

NAME = "schemas"
HELP = "export the JSON Schema of every wire message (for non-Python clients)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="schemas_action", metavar="ACTION", required=True)
    exp = sub.add_parser("export", help="write one <kind>.json per message into DIR")
    exp.add_argument("dir", metavar="DIR", help="output directory (created if missing)")


def run(args: argparse.Namespace) -> int:
    from schemas.jsonschema import export
    from services.inputs import output_dir

    if args.schemas_action != "export":
        raise ValueError(f"schemas: unknown action {args.schemas_action!r}")
    paths = export(output_dir(args.dir, "dir"))
    for path in paths:
        print(path)
    return 0
