"""Which of a bus's subscriptions a published key reaches, in declaration order: one table per bus, kept per key.

The in-process network routes every sample through it; a Zenoh session routes the samples of a bundle through it
(Zenoh routes everything else itself). A key the table has not seen is matched only against the subscriptions of its
shape (:class:`_Shapes`): a fleet of a hundred robots has a thousand subscriptions on the in-process network, and
some thousands of keys between pairs of robots, each new to the table the first time that pair talks.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

from schemas.keys import matches

#: the most keys a table holds: keys nobody planned (a fuzzer's) empty it rather than grow it
ROUTES_MAX = 4096

E = TypeVar("E")


class Routes(Generic[E]):
    """The subscriptions ``entries`` (declaration order; ``key_expr`` gives an entry's key expression) and, per key,
    the ones it reaches. :meth:`reach` may run on a transport thread while :meth:`add` and :meth:`remove` run on the
    loop: a change replaces the tables rather than clearing them, so a lookup under way finishes on the old ones."""

    def __init__(self, key_expr: Callable[[E], str]):
        self.entries: list[E] = []
        self._key_expr = key_expr
        self._table: dict[str, list[E]] = {}
        self._shapes: _Shapes[E] | None = None

    def add(self, entry: E) -> None:
        self.entries.append(entry)
        self.changed()

    def remove(self, entry: E) -> bool:
        """Forget ``entry``; False if it was not there."""
        try:
            self.entries.remove(entry)
        except ValueError:
            return False
        self.changed()
        return True

    def changed(self) -> None:
        """The entries changed: every route is found afresh. The shapes go first, so that a lookup that takes the new
        table also takes shapes of the new entries."""
        self._shapes = None
        self._table = {}

    def reach(self, key: str) -> list[E]:
        """The entries whose key expression matches the concrete ``key``, in declaration order."""
        table = self._table
        found = table.get(key)
        if found is None:
            if len(table) >= ROUTES_MAX:
                table.clear()
            shapes = self._shapes
            if shapes is None:
                shapes = self._shapes = _Shapes(self.entries, self._key_expr)
            key_expr = self._key_expr
            found = table[key] = [entry for entry in shapes.candidates(key) if matches(key_expr(entry), key)]
        return found


class _Shapes(Generic[E]):
    """The entries sorted by which concrete keys they can match, so that routing a key matches only those.

    An expression without ``**`` matches only keys of as many chunks as it has (``*`` stands for one chunk), and one
    whose last chunk has no wildcard only keys ending in that chunk. So every entry lies in one of three places: by
    (chunks, last chunk), by chunks alone (a wildcard last chunk), or with ``**`` among the few that can match keys of
    any length. The candidates of a key are the union of its three places, in declaration order; :func:`matches`
    decides among them."""

    def __init__(self, entries: list[E], key_expr: Callable[[E], str]):
        self.by_last: dict[tuple[int, str], list[tuple[int, E]]] = {}
        self.by_length: dict[int, list[tuple[int, E]]] = {}
        self.any_length: list[tuple[int, E]] = []
        for order, entry in enumerate(list(entries)):
            chunks = key_expr(entry).split("/")
            if "**" in chunks:
                self.any_length.append((order, entry))
            elif "*" in chunks[-1]:
                self.by_length.setdefault(len(chunks), []).append((order, entry))
            else:
                self.by_last.setdefault((len(chunks), chunks[-1]), []).append((order, entry))

    def candidates(self, key: str) -> list[E]:
        length = key.count("/") + 1
        last = key[key.rfind("/") + 1:]
        found = [*self.by_last.get((length, last), ()), *self.by_length.get(length, ()), *self.any_length]
        found.sort(key=lambda item: item[0])
        return [entry for _, entry in found]
