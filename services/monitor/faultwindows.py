"""Fault windows from the run's events: when each fault was set and when it healed or was reset.

One tracker for every reader: the monitor feeds it live (Prometheus ``morph_faults_active``, which Grafana turns into
shaded regions) and the report feeds it the recorded events (shaded windows in the figures). Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

KINDS = ("fault.set", "fault.healed", "fault.reset")


class FaultWindows:
    """Feed events in order with :meth:`add`; ``open`` holds the faults in force, ``closed`` the finished windows."""

    def __init__(self, events: Iterable[Mapping[str, Any]] = ()):
        self.open: dict[str, tuple[float, str]] = {}  # fault id -> (start tick, label)
        self.closed: list[tuple[float, float, str]] = []
        for e in events:
            self.add(e)

    def add(self, event: Mapping[str, Any]) -> None:
        kind, t = event.get("kind", ""), event.get("t")
        if kind not in KINDS or t is None:
            return
        details = event.get("details") or {}
        fid = str(details.get("fault_id") or details.get("id") or kind)
        if kind == "fault.set":
            # every process of a run applies (and reports) the same command: the first report opens the window
            self.open.setdefault(fid, (float(t), fid))
        elif fid in self.open:
            start, label = self.open.pop(fid)
            self.closed.append((start, float(t), label))
        elif kind == "fault.reset" and fid == kind:  # a reset without an id heals everything (a reset of a fault
            # that opened no window here, e.g. a crash plan cancelled by the supervisor, closes nothing)
            for start, label in self.open.values():
                self.closed.append((start, float(t), label))
            self.open.clear()

    @property
    def active(self) -> int:
        return len(self.open)

    def windows(self, end: float) -> list[tuple[float, float, str]]:
        """(start tick, end tick, label) of every window; those still open end at ``end``."""
        return self.closed + [(start, end, label) for start, label in self.open.values()]
