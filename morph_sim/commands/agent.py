"""``morph-sim agent``: the agent service's own command (:mod:`services.agent.command`), under the tool's CLI."""

from services.agent.command import HELP, NAME, add_arguments, run

__all__ = ["HELP", "NAME", "add_arguments", "run"]
