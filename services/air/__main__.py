"""``python -m services.air``: this service as its own process (the same as ``morph-sim air``)."""

import sys

from services.air import command
from services.process import command_main

if __name__ == "__main__":
    sys.exit(command_main(command))
