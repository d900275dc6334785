"""``python -m services.agent``: this service as its own process (the same as ``morph-sim agent``)."""

import sys

from services.agent import command
from services.process import command_main

if __name__ == "__main__":
    sys.exit(command_main(command))
