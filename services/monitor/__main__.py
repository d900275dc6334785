"""``python -m services.monitor``: this service as its own process (the same as ``morph-sim monitor``)."""

import sys

from services.monitor import command
from services.process import command_main

if __name__ == "__main__":
    sys.exit(command_main(command))
