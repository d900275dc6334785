"""Benchmark targets for ``morph-sim bench <target>``.

Each module here defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``; the ``bench``
command discovers them, so a new target (e.g. ``distributed``) is added by adding a module. Keep this package's
import light: benchmark child processes import it and their memory is measured.
"""

from __future__ import annotations

import importlib
import pkgutil


def target_modules():
    """Benchmark target modules, sorted by name."""
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield importlib.import_module(f"{__name__}.{info.name}")
