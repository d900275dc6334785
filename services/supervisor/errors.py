"""How a run of ``morph-sim up`` fails: each error's message is the one line ``up`` prints after ``error:``."""

from __future__ import annotations


class StartError(RuntimeError):
    """A process of the run could not start (message names it and shows its log tail)."""


class RunFailed(StartError):
    """The run ended but its record is not the truth (incomplete, or the monitor failed): the message says why."""


class RunStalled(StartError):
    """The run stopped advancing: no new tick for ``stall_timeout`` seconds although every phase has a deadline.

    A stall inside Zenoh — a router blocked on a full socket while forwarding (zenoh 1.10.2, lowlatency transport;
    we met it when the monitor handled samples on its receive thread, docs/services.md) — is out of reach of every
    phase deadline of ours. A user gets a clear failure and a record up to the stall instead of a silent hang."""
