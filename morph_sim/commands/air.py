"""``morph-sim air``: the shared air's own command (:mod:`services.air.command`), under the tool's CLI."""

from services.air.command import HELP, NAME, add_arguments, run

__all__ = ["HELP", "NAME", "add_arguments", "run"]
