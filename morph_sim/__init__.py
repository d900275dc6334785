"""morph-sim: MORPH multi-robot task allocation in a TA-RWARE-style warehouse, run as services over Zenoh."""

__version__ = "0.1.0"
