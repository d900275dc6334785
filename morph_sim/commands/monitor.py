"""``morph-sim monitor``: the monitor service's own command (:mod:`services.monitor.command`), under the tool's CLI."""

from services.monitor.command import HELP, NAME, add_arguments, run

__all__ = ["HELP", "NAME", "add_arguments", "run"]
