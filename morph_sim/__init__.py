"""morph-sim: MORPH multi-robot task allocation in a TA-RWARE-style warehouse, run as services over Zenoh.

The Python API (:mod:`morph_sim.api`) is importable from here: ``morph_sim.run``, ``up``, ``episode``, ``sweep``,
``load`` and ``RunConfig``; it is loaded on first use, so ``import morph_sim`` stays cheap for the CLI.
"""

__version__ = "0.1.0"

_API = ("RunConfig", "Record", "Manifest", "Episode", "config", "run", "up", "episode", "sweep", "load")


def __getattr__(name: str):
    if name in _API:
        from morph_sim import api

        return getattr(api, name)
    raise AttributeError(f"module 'morph_sim' has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_API])
