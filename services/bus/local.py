"""LocalBus: every participant in one process and one asyncio loop, with Zenoh's matching semantics.

A :class:`LocalNetwork` plays the role of the Zenoh network; each :class:`LocalBus` is one participant's session on
it. Delivery is deterministic: a publish snapshots the matching subscribers in declaration order and schedules one
delivery per subscriber with ``loop.call_soon`` (FIFO), so the same program always sees the same interleaving.
A session receives its own publications when it subscribes to them, as in Zenoh.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from schemas.keys import intersects, matches
from services.bus.base import Bus, LivelinessEvent, Query, Reply, Sample, Subscription


class LocalNetwork:
    """The shared in-process medium. Create one per run; open sessions with :meth:`session`."""

    def __init__(self) -> None:
        self.subscribers: list[tuple[LocalBus, Subscription[Sample]]] = []
        # key -> the subscribers it reaches, in declaration order; forgotten whenever a subscription comes or goes.
        # A run publishes on a few hundred keys against a hundred subscriptions: matching every put against every
        # subscription was most of an in-process run's bus time.
        self._routes: dict[str, list[tuple[LocalBus, Subscription[Sample]]]] = {}
        # the subscriptions that can match a key, found without matching every one: see :meth:`routes_of`
        self._shapes: _Shapes | None = None
        self.queryables: list[tuple[LocalBus, str, Callable[[Query], Awaitable[None] | None]]] = []
        self.tokens: dict[str, list[LocalBus]] = {}
        self.liveliness_subscribers: list[tuple[LocalBus, Subscription[LivelinessEvent]]] = []

    def session(self, identity: str) -> LocalBus:
        return LocalBus(self, identity)

    def subscriptions_changed(self) -> None:
        """A subscription came or went: every route is found afresh."""
        self._routes = {}
        self._shapes = None

    def routes_of(self, key: str) -> list[tuple[LocalBus, Subscription[Sample]]]:
        """The subscribers ``key`` reaches, in declaration order, kept per key.

        A key nobody published before is matched only against the subscriptions of its shape (:class:`_Shapes`):
        a fleet of a hundred robots has a thousand subscriptions and some thousands of keys between pairs of robots,
        each new to the table the first time that pair talks."""
        routes = self._routes
        targets = routes.get(key)
        if targets is None:
            if len(routes) >= 4096:  # keys nobody planned (a fuzzer's): the table stays bounded
                routes.clear()
            shapes = self._shapes
            if shapes is None:
                shapes = self._shapes = _Shapes(self.subscribers)
            targets = routes[key] = [entry for entry in shapes.candidates(key) if matches(entry[1].key_expr, key)]
        return targets

    def _notify_liveliness(self, key: str, alive: bool) -> None:
        loop = asyncio.get_running_loop()
        for _bus, sub in list(self.liveliness_subscribers):
            if matches(sub.key_expr, key):
                loop.call_soon(sub._push, LivelinessEvent(key, alive))


class _LocalQuery(Query):
    def __init__(self, key_expr: str, parameters: str, payload: bytes | None, sink: list[Reply]):
        super().__init__(key_expr, parameters, payload)
        self._sink = sink
        self.finished = False

    def _reply(self, key: str, payload: bytes) -> None:
        if not self.finished:  # a reply after the querier's timeout is dropped, as in Zenoh
            self._sink.append(Reply(key, payload=payload))

    def _reply_err(self, payload: bytes) -> None:
        if not self.finished:
            self._sink.append(Reply(self.key_expr, error=payload))


class LocalBus(Bus):
    """One session on a :class:`LocalNetwork`."""

    def __init__(self, network: LocalNetwork, identity: str):
        super().__init__(identity)
        self.network = network

    def _send(self, sample: Sample, droppable: bool) -> None:
        loop = asyncio.get_running_loop()
        targets = self.network.routes_of(sample.key)
        for bus, sub in targets:
            loop.call_soon(bus._ingress, sub, sample)

    def _declare_subscriber(self, key_expr: str, sub: Subscription[Sample]) -> Callable[[], None]:
        entry = (self, sub)
        network = self.network
        network.subscribers.append(entry)
        network.subscriptions_changed()

        def undeclare() -> None:
            _remove(network.subscribers, entry)
            network.subscriptions_changed()
        return undeclare

    def _has_subscribers(self, key: str) -> bool:
        return any(matches(sub.key_expr, key) for _bus, sub in self.network.subscribers)

    def _declare_queryable(self, key_expr: str, handler: Callable[[Query], Awaitable[None] | None]
                           ) -> Callable[[], None]:
        entry = (self, key_expr, handler)
        self.network.queryables.append(entry)
        return lambda: _remove(self.network.queryables, entry)

    async def _get(self, key_expr: str, parameters: str, payload: bytes | None, timeout: float) -> list[Reply]:
        loop = asyncio.get_running_loop()
        sinks: list[list[Reply]] = []
        queries: list[_LocalQuery] = []
        tasks: list[asyncio.Task] = []
        for bus, qkey, handler in list(self.network.queryables):
            if bus.closed or not intersects(qkey, key_expr):
                continue
            sink: list[Reply] = []
            query = _LocalQuery(key_expr, parameters, payload, sink)
            sinks.append(sink)
            queries.append(query)
            tasks.append(loop.create_task(bus._run_query_handler(handler, query)))
        if tasks:
            await asyncio.wait(tasks, timeout=timeout)
        for query in queries:
            query.finished = True
        for task in tasks:
            if not task.done():
                task.cancel()
        return [reply for sink in sinks for reply in sink]

    def _declare_token(self, key: str) -> Callable[[], None]:
        owners = self.network.tokens.setdefault(key, [])
        owners.append(self)
        if len(owners) == 1:
            self.network._notify_liveliness(key, True)

        def undeclare() -> None:
            owners = self.network.tokens.get(key, [])
            if self in owners:
                owners.remove(self)
            if not owners:
                self.network.tokens.pop(key, None)
                self.network._notify_liveliness(key, False)

        return undeclare

    def _declare_liveliness_subscriber(self, key_expr: str, sub: Subscription[LivelinessEvent], history: bool
                                       ) -> Callable[[], None]:
        entry = (self, sub)
        self.network.liveliness_subscribers.append(entry)
        if history:
            loop = asyncio.get_running_loop()
            for key in sorted(self.network.tokens):
                if matches(key_expr, key):
                    loop.call_soon(sub._push, LivelinessEvent(key, True))
        return lambda: _remove(self.network.liveliness_subscribers, entry)

    async def _liveliness_get(self, key_expr: str, timeout: float) -> set[str]:
        await asyncio.sleep(0)
        return {key for key in self.network.tokens if matches(key_expr, key)}

    async def _close_transport(self) -> None:
        # Entities were undeclared one by one by Bus.close(); drop anything left (e.g. declared behind our back).
        net = self.network
        net.subscribers[:] = [e for e in net.subscribers if e[0] is not self]
        net.subscriptions_changed()
        net.queryables[:] = [e for e in net.queryables if e[0] is not self]
        net.liveliness_subscribers[:] = [e for e in net.liveliness_subscribers if e[0] is not self]
        for key in [k for k, owners in net.tokens.items() if self in owners]:
            owners = net.tokens[key]
            while self in owners:
                owners.remove(self)
            if not owners:
                del net.tokens[key]
                net._notify_liveliness(key, False)


class _Shapes:
    """The subscriptions sorted by which concrete keys they can match, so that routing a key matches only those.

    An expression without ``**`` matches only keys of as many chunks as it has (``*`` stands for one chunk),
    and one whose last chunk has no wildcard only keys ending in that chunk. So every subscription lies in
    one of three places: by (chunks, last chunk), by chunks alone (a wildcard last chunk), or with ``**`` among the
    few that can match keys of any length. The candidates of a key are the union of its three places, in
    declaration order; :func:`matches` decides among them."""

    def __init__(self, subscribers: list[tuple[LocalBus, Subscription[Sample]]]):
        self.by_last: dict[tuple[int, str], list[tuple[int, tuple[LocalBus, Subscription[Sample]]]]] = {}
        self.by_length: dict[int, list[tuple[int, tuple[LocalBus, Subscription[Sample]]]]] = {}
        self.any_length: list[tuple[int, tuple[LocalBus, Subscription[Sample]]]] = []
        for order, entry in enumerate(subscribers):
            chunks = entry[1].key_expr.split("/")
            if "**" in chunks:
                self.any_length.append((order, entry))
            elif "*" in chunks[-1]:
                self.by_length.setdefault(len(chunks), []).append((order, entry))
            else:
                self.by_last.setdefault((len(chunks), chunks[-1]), []).append((order, entry))

    def candidates(self, key: str) -> list[tuple[LocalBus, Subscription[Sample]]]:
        length = key.count("/") + 1
        last = key[key.rfind("/") + 1:]
        found = [*self.by_last.get((length, last), ()), *self.by_length.get(length, ()), *self.any_length]
        found.sort(key=lambda item: item[0])
        return [entry for _, entry in found]


def _remove(items: list, entry: object) -> None:
    try:
        items.remove(entry)
    except ValueError:
        pass
