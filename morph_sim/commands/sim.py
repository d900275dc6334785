"""``morph-sim sim``: the sim service's own command (:mod:`services.sim.command`), under the tool's CLI."""

from services.sim.command import HELP, NAME, add_arguments, run

__all__ = ["HELP", "NAME", "add_arguments", "run"]
