"""``morph-sim bench <target>``: performance measurements; targets live in :mod:`morph_sim.bench`."""

from __future__ import annotations

import argparse

from morph_sim import bench

NAME = "bench"
HELP = "measure performance (targets: " + ", ".join(m.NAME for m in bench.target_modules()) + ")"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench_target", metavar="TARGET", required=True)
    for module in bench.target_modules():
        target = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(target)
        target.set_defaults(_bench_run=module.run)


def run(args: argparse.Namespace) -> int:
    return int(args._bench_run(args) or 0)
