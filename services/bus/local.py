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
from services.bus.routes import Routes


class LocalNetwork:
    """The shared in-process medium. Create one per run; open sessions with :meth:`session`."""

    def __init__(self) -> None:
        # the sample subscriptions in declaration order, and per key the ones it reaches
        self.routes: Routes[tuple[LocalBus, Subscription[Sample]]] = Routes(lambda entry: entry[1].key_expr)
        self.queryables: list[tuple[LocalBus, str, Callable[[Query], Awaitable[None] | None]]] = []
        self.tokens: dict[str, list[LocalBus]] = {}
        self.liveliness_subscribers: list[tuple[LocalBus, Subscription[LivelinessEvent]]] = []

    def session(self, identity: str) -> LocalBus:
        return LocalBus(self, identity)

    @property
    def subscribers(self) -> list[tuple[LocalBus, Subscription[Sample]]]:
        """The sample subscriptions of every session, in declaration order."""
        return self.routes.entries

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
        targets = self.network.routes.reach(sample.key)
        for bus, sub in targets:
            loop.call_soon(bus._ingress, sub, sample)

    def _declare_subscriber(self, key_expr: str, sub: Subscription[Sample]) -> Callable[[], None]:
        entry = (self, sub)
        routes = self.network.routes
        routes.add(entry)
        return lambda: routes.remove(entry)

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
        net.routes.changed()
        net.queryables[:] = [e for e in net.queryables if e[0] is not self]
        net.liveliness_subscribers[:] = [e for e in net.liveliness_subscribers if e[0] is not self]
        for key in [k for k, owners in net.tokens.items() if self in owners]:
            owners = net.tokens[key]
            while self in owners:
                owners.remove(self)
            if not owners:
                del net.tokens[key]
                net._notify_liveliness(key, False)


def _remove(items: list, entry: object) -> None:
    try:
        items.remove(entry)
    except ValueError:
        pass
