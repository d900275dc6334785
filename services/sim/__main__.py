"""``python -m services.sim``: this service as its own process (the same as ``morph-sim sim``)."""

import sys

from services.process import command_main
from services.sim import command

if __name__ == "__main__":
    sys.exit(command_main(command))
