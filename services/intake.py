"""What every service does with a message before it reads it: decode it, check that its author sent it under its own
key, and count what it refuses, with the reason.

The sim, each agent and the monitor open the same way, so the rules live here once: a message the bus refused on
arrival (oversized, undecodable envelope) and one a service refuses after decoding (a bad field, another author's
key) are counted together, and the first of them and then one in every thousand are logged (:class:`Rejects`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from schemas.keys import RunKeys
from services.rejects import Rejects


class Intake:
    """The opening of one service's receive path over ``bus`` (``owner`` names the service in log lines).

    ``on_refused(total)`` is called after every refusal, for a service that reports the count in its own result."""

    def __init__(self, bus, keys: RunKeys, log: logging.Logger, owner: str,
                 on_refused: Callable[[int], None] | None = None, flood=None,
                 on_flood: Callable[[int, int], None] | None = None):
        """``flood`` (a :class:`services.protocol.claims.FloodWatch`) counts each robot's refused messages, by the
        key they came on; ``on_flood(robot, refused)`` is called once when a robot crosses each threshold."""
        self.keys = keys
        self.rejects = Rejects(log, owner)
        self.on_refused = on_refused
        self.flood, self.on_flood = flood, on_flood
        #: robots whose messages are refused unread from now on (cut off for flooding)
        self.cut_off: set[int] = set()
        bus.reject_hook = self.refuse  # what the bus refuses on arrival counts here too
        bus.inbox_author = self._author  # each robot's share of what waits to be read

    @property
    def refused(self) -> int:
        return self.rejects.total

    def refuse(self, what: str, why: object) -> None:
        """Count (and maybe log) one refused message: ``what`` is its key, ``why`` the reason."""
        self.rejects.count(what, why)
        if self.on_refused is not None:
            self.on_refused(self.rejects.total)
        if self.flood is not None:
            author = self._author(what)
            crossed = self.flood.note(author)
            if crossed is not None and self.on_flood is not None:
                self.on_flood(author, crossed)

    def _author(self, key: str) -> int | str | None:
        try:
            return self.keys.sender_of(key)
        except ValueError:  # not a key of this run: nobody's
            return None

    def decode(self, sample, model: type, author: str | None = None, what: str = ""):
        """``sample`` decoded as ``model``, or None (counted) when it does not decode or, with ``author`` (the field
        that names who sent it), when that author is not the owner of the key it came on."""
        try:
            if self.cut_off and self._author(sample.key) in self.cut_off:
                raise ValueError("a robot cut off for flooding")
            msg = sample.decode(model)
            if author is not None:
                self.keys.check_author(sample.key, getattr(msg, author), what)
        except ValueError as exc:
            self.refuse(sample.key, exc)
            return None
        return msg
