"""Counting and logging rejected messages without letting a flood of garbage flood the log as well."""

from __future__ import annotations

import logging

LOG_FIRST = 10  # log the first rejects in full ...
LOG_EVERY = 1000  # ... then one line per this many


class Rejects:
    """``count(what, why)`` for every message a service refuses (undecodable, misaddressed, out of range)."""

    def __init__(self, log: logging.Logger, owner: str):
        self.log = log
        self.owner = owner
        self.total = 0
        self.by_key: dict[str, int] = {}

    def count(self, what: str, why: object) -> None:
        self.total += 1
        if len(self.by_key) < 4096 or what in self.by_key:  # bounded: keys of garbage can be garbage too
            self.by_key[what] = self.by_key.get(what, 0) + 1
        if self.total <= LOG_FIRST or self.total % LOG_EVERY == 0:
            self.log.warning("%s: rejected message #%d on %s: %s", self.owner, self.total, what, why)
