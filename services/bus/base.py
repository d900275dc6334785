"""The async Bus interface shared by :class:`LocalBus` and :class:`ZenohBus`.

A bus is one participant's session (one service, one agent). It offers pub/sub, queryables and get, and liveliness
tokens, all on the asyncio loop that opened it: handlers run on that loop, never on a transport thread — except
subscriptions declared ``inline=True`` (the lock-step hot path), whose plain handlers may run on the transport's
receive thread, serialized by one lock per bus (see :meth:`Bus.subscribe`).

Every published sample carries a small header (the publisher's identity, a per-(publisher, key) sequence number and
the publisher's send time), so receivers can attribute a message to its link (sender → receiver) and measure loss,
duplication and latency from the messages themselves.

Fault-layer seam. Every sample passes two hook points (on the loop; for inline subscriptions the ingress
hook runs on the receive thread, so a fault layer schedules delayed copies with ``call_soon_threadsafe``):

* egress — ``Interposer.on_publish(sample, send)`` runs in ``publish`` after the header is stamped and before the
  transport sends; it may call ``send`` zero times (drop), once, twice (duplicate) or later (delay);
* ingress — ``Interposer.on_deliver(sample, receiver, deliver)`` runs when a sample reaches this bus, before any
  handler sees it; ``receiver`` is this bus's identity, so a fault layer knows the link and can keep a seeded RNG per
  link, drop, delay (``loop.call_later`` in wall time, or until a virtual-time boundary), duplicate or reorder.

Install one with :meth:`Bus.set_interposer` (``services.faults.layer.FaultLayer`` implements it). Without
one, samples go straight through. The same seam exists on both buses, so a fault configuration behaves the same
in-process and over Zenoh. Queries, replies and liveliness do not pass the seam (they are control-plane traffic).
"""

from __future__ import annotations

import asyncio
import inspect
import itertools
import logging
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Generic, NamedTuple, Protocol, TypeVar

import msgpack

from schemas.base import DecodeError, Message
from schemas.codec import decode, to_payload
from schemas.keys import intersects, validate_key, validate_key_expr
from schemas.limits import max_payload_of_key

log = logging.getLogger("morph_sim.bus")

T = TypeVar("T")
M = TypeVar("M", bound=Message)


class Sample(NamedTuple):
    """One received (or about-to-be-sent) publication. (A NamedTuple: built once per message on the hot path.)"""

    key: str
    payload: bytes
    sender: str = ""
    seq: int = 0
    sent_at: float = 0.0  # publisher's time.time() when it published
    # virtual time: when a fault layer delivers it, sim seconds (send time + its latency, not rounded); -1 = unknown
    due: float = -1.0

    def decode(self, expect: type[M] | None = None) -> M | Message:
        """Decode the payload as a message (raises DecodeError naming the bad field)."""
        return decode(self.payload, expect)


@dataclass(frozen=True, slots=True)
class LivelinessEvent:
    key: str
    alive: bool


@dataclass(frozen=True, slots=True)
class Reply:
    """A reply to :meth:`Bus.get`: ``payload`` on success, ``error`` (bytes) if the queryable replied an error."""

    key: str
    payload: bytes | None = None
    error: bytes | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    def decode(self, expect: type[M] | None = None) -> M | Message:
        if self.payload is None:
            raise DecodeError("<payload>", f"error reply: {self.error!r}")
        return decode(self.payload, expect)


class Query(ABC):
    """A query received by a queryable. Reply with :meth:`reply` (any number of times) or :meth:`reply_err`."""

    def __init__(self, key_expr: str, parameters: str, payload: bytes | None):
        self.key_expr = key_expr
        self.parameters = parameters
        self.payload = payload

    @property
    def params(self) -> dict[str, str]:
        """``a=1;b=2`` (Zenoh's separator) or ``a=1&b=2`` parsed into a dict."""
        out: dict[str, str] = {}
        for part in self.parameters.replace("&", ";").split(";"):
            if part:
                name, _, value = part.partition("=")
                out[name] = value
        return out

    def reply(self, key: str, payload: Message | bytes) -> None:
        validate_key(key)
        if not intersects(key, self.key_expr):
            raise ValueError(f"reply key {key!r} does not match the query's key expression {self.key_expr!r}")
        self._reply(key, to_payload(payload))

    def reply_err(self, payload: bytes | str) -> None:
        self._reply_err(payload.encode() if isinstance(payload, str) else bytes(payload))

    @abstractmethod
    def _reply(self, key: str, payload: bytes) -> None: ...

    @abstractmethod
    def _reply_err(self, payload: bytes) -> None: ...


Handler = Callable[[Any], Awaitable[None] | None]


class Interposer(Protocol):
    """The fault-layer seam (see module docstring)."""

    def on_publish(self, sample: Sample, send: Callable[[Sample], None]) -> None: ...

    def on_deliver(self, sample: Sample, receiver: str, deliver: Callable[[Sample], None]) -> None: ...


_CLOSED = object()


class Subscription(Generic[T]):
    """A declared subscriber (samples) or liveliness subscriber (LivelinessEvent).

    With a handler, items are passed to it in arrival order: a plain function is called directly on the loop; a
    coroutine function is awaited by one worker task per subscription, so items are still handled one at a time
    in order. Without a handler the subscription is an async iterator (``async for sample in sub``), ending on close.
    """

    def __init__(self, bus: Bus, key_expr: str, handler: Handler | None, inline: bool = False):
        self.key_expr = key_expr
        self.received = 0
        self.inline = inline
        self._bus = bus
        self._handler = handler
        self._deliver_fn: Callable[[Any], None] = self._push
        self._is_async = handler is not None and inspect.iscoroutinefunction(handler)
        self._queue: deque[Any] = deque()
        self._wakeup: asyncio.Event | None = None
        self._worker: asyncio.Task | None = None
        self._closed = False
        self._undeclare: Callable[[], None] | None = None

    # called on the loop by the bus
    def _push(self, item: Any) -> None:
        if self._closed:
            return
        self.received += 1
        if self._handler is not None and not self._is_async:
            try:
                result = self._handler(item)
                if result is not None and inspect.isawaitable(result):  # a sync function returning an awaitable
                    self._bus.spawn(result, self.key_expr)
            except Exception:
                self._bus._handler_failed(self.key_expr)
            return
        self._queue.append(item)
        if self._wakeup is None:
            self._wakeup = asyncio.Event()
        self._wakeup.set()
        if self._is_async and self._worker is None:
            self._worker = asyncio.get_running_loop().create_task(self._work())

    async def _work(self) -> None:
        assert self._handler is not None
        while True:
            while self._queue:
                item = self._queue.popleft()
                if item is _CLOSED:
                    return
                try:
                    await self._handler(item)  # type: ignore[misc]
                except asyncio.CancelledError:
                    raise
                except Exception:
                    self._bus._handler_failed(self.key_expr)
            if self._closed:
                return
            assert self._wakeup is not None
            self._wakeup.clear()
            await self._wakeup.wait()

    def __aiter__(self) -> AsyncIterator[T]:
        if self._handler is not None:
            raise TypeError("a subscription with a handler is not iterable")
        return self

    async def __anext__(self) -> T:
        try:
            return await self._take()
        except EOFError:
            raise StopAsyncIteration from None

    async def _take(self) -> T:
        while True:
            if self._queue:
                item = self._queue[0]
                if item is _CLOSED:
                    raise EOFError(f"subscription {self.key_expr!r} is closed")
                return self._queue.popleft()
            if self._closed:
                raise EOFError(f"subscription {self.key_expr!r} is closed")
            if self._wakeup is None:
                self._wakeup = asyncio.Event()
            self._wakeup.clear()
            await self._wakeup.wait()

    async def next(self, timeout: float | None = None) -> T:
        """The next item (iterator mode); TimeoutError after ``timeout`` s, EOFError once closed."""
        if self._handler is not None:
            raise TypeError("a subscription with a handler has no next()")
        return await asyncio.wait_for(self._take(), timeout)

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._undeclare is not None:
            try:
                self._undeclare()
            except Exception:  # undeclare after session close is harmless
                log.debug("undeclare of %s failed", self.key_expr, exc_info=True)
        self._queue.append(_CLOSED)
        if self._wakeup is not None:
            self._wakeup.set()
        self._bus._forget(self)


class Declared:
    """A declared queryable or liveliness token; ``await close()`` undeclares it."""

    def __init__(self, bus: Bus, key_expr: str, undeclare: Callable[[], None]):
        self.key_expr = key_expr
        self._bus = bus
        self._undeclare = undeclare
        self._closed = False

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._undeclare()
        except Exception:
            log.debug("undeclare of %s failed", self.key_expr, exc_info=True)
        self._bus._forget(self)


@dataclass
class BusCounters:
    published: int = 0
    delivered: int = 0
    handler_errors: int = 0
    rejected: int = 0  # payloads that failed to decode (see Bus.decode)
    per_key_errors: dict[str, int] = field(default_factory=dict)
    per_key_rejects: dict[str, int] = field(default_factory=dict)


def pack_header(sender: str, seq: int, sent_at: float) -> bytes:
    return msgpack.packb((sender, seq, sent_at), use_bin_type=True)


def unpack_header(data: bytes | None) -> tuple[str, int, float]:
    """Header of a received sample; a missing or foreign header reads as ('', 0, 0.0) rather than failing."""
    if not data:
        return "", 0, 0.0
    try:
        sender, seq, sent_at = msgpack.unpackb(data, raw=False)
        return str(sender), int(seq), float(sent_at)
    except Exception:
        return "", 0, 0.0


_payload_bound = lru_cache(maxsize=4096)(max_payload_of_key)  # few distinct keys; checked on every arrival

#: At most this many samples travel in one bundle (the sim's tick start carries two: fleet broadcast, on-board state).
MAX_BUNDLE = 4
# A message payload is a msgpack map (an envelope); a bundle is a msgpack array of samples. Its first byte says which.
_ARRAY_FIRST_BYTES = frozenset([*range(0x90, 0xA0), 0xDC, 0xDD])


def is_bundle(payload: bytes) -> bool:
    """Whether a received payload is a bundle of samples (:func:`pack_bundle`) rather than one message."""
    return bool(payload) and payload[0] in _ARRAY_FIRST_BYTES


def pack_bundle(samples: list[Sample]) -> bytes:
    """Several samples of one publisher as one transport message: ``[[key, seq, sent_at, payload], …]``, the
    carrier's own sample (whose key and header the transport message has) last."""
    return msgpack.packb([(s.key, s.seq, s.sent_at, s.payload) for s in samples], use_bin_type=True)


def unpack_bundle(carrier: Sample) -> list[Sample]:
    """The samples a bundle carried, each with its own key and header; ValueError naming what is wrong.

    A bundle speaks only for its publisher: every sample in it must lie in the carrier key's own key space (the
    same ``morph/<run>/<head>``, and for ``agent/<id>/…`` keys the same id), and the last one is the carrier's own
    sample (its key and sequence number), so a bundle cannot smuggle another author's messages past a check made
    on the carrier's key.
    """
    try:
        entries = msgpack.unpackb(carrier.payload, raw=False, use_list=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise ValueError(f"bundle: not msgpack: {type(exc).__name__}") from None
    if not isinstance(entries, tuple) or not 1 <= len(entries) <= MAX_BUNDLE:
        raise ValueError(f"bundle: expected 1..{MAX_BUNDLE} samples")
    chunks = carrier.key.split("/")
    space = "/".join(chunks[:4] if len(chunks) > 3 and chunks[2] == "agent" else chunks[:3]) + "/"
    out: list[Sample] = []
    for i, entry in enumerate(entries):
        if not (isinstance(entry, tuple) and len(entry) == 4 and isinstance(entry[0], str)
                and type(entry[1]) is int and isinstance(entry[2], (int, float)) and isinstance(entry[3], bytes)):
            raise ValueError(f"bundle[{i}]: expected [key, seq, sent_at, payload]")
        key, seq, sent_at, payload = entry
        if not key.startswith(space):
            raise ValueError(f"bundle[{i}].key: {key!r} is outside the carrier's key space {space!r}")
        validate_key(key)
        out.append(Sample(key, payload, carrier.sender, seq, float(sent_at)))
    last = out[-1]
    if last.key != carrier.key or last.seq != carrier.seq:
        raise ValueError("bundle: its last sample is not the carrier's own (key and sequence number)")
    return out


class Bus(ABC):
    """One participant's session on the run's bus. Use ``async with`` or call :meth:`close`."""

    #: this session hosts the endpoint others connect to: closing it drops what it still queues for them
    hosts_endpoint: bool = False
    #: what this session publishes leaves from a send queue after the call returns (a network transport): closing
    #: the session right after a publication can lose it
    flushes_late: bool = False

    def __init__(self, identity: str):
        self.identity = str(identity)
        self.counters = BusCounters()
        self._seq: dict[str, itertools.count] = {}
        self._entities: list[Subscription | Declared] = []
        self._tasks: set[asyncio.Task] = set()
        self._interposer: Interposer | None = None
        self._closed = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clock: Callable[[], float] = time.time
        # The owning service's reject counter (``hook(key, reason)``): refusals made here, before any handler sees
        # the message, are counted with the service's own rejects.
        self.reject_hook: Callable[[str, str], None] | None = None
        # The owning service's reading of a key's author (a robot id, or None for anything else): where samples wait
        # for the loop (ZenohBus's inbox), each robot gets a bounded share, so one robot's flood cannot fill memory.
        self.inbox_author: Callable[[str], object] | None = None

    # -- lifecycle ------------------------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    async def __aenter__(self) -> Bus:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        """Undeclare everything and close the session. Idempotent and bounded in time."""
        if self._closed:
            return
        self._closed = True
        for entity in list(reversed(self._entities)):
            await entity.close()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=1.0)
        await self._close_transport()

    def decode(self, sample: Sample, expect: type[M]) -> M | None:
        """Decode a received sample as ``expect``; a malformed or wrong-version payload is counted, logged (first few
        per key, then every 100th) and returned as None, so a service carries on."""
        try:
            return decode(sample.payload, expect)
        except DecodeError as exc:
            self.counters.rejected += 1
            count = self.counters.per_key_rejects.get(sample.key, 0) + 1
            self.counters.per_key_rejects[sample.key] = count
            if count <= 5 or count % 100 == 0:
                log.warning("bus %s: rejected payload #%d on %s from %r: %s", self.identity, count, sample.key,
                            sample.sender, exc)
            return None

    def _refuse(self, sample: Sample, why: str) -> None:
        self.counters.rejected += 1
        self.counters.per_key_rejects[sample.key] = self.counters.per_key_rejects.get(sample.key, 0) + 1
        hook = self.reject_hook
        if hook is not None:
            hook(sample.key, why)
        elif self.counters.rejected <= 5 or self.counters.rejected % 100 == 0:
            log.warning("bus %s: rejected #%d on %s from %r: %s", self.identity, self.counters.rejected, sample.key,
                        sample.sender, why)

    def set_clock(self, clock: Callable[[], float] | None) -> None:
        """The clock that stamps ``sent_at`` on published samples: ``time.time`` (default, wall time) or a virtual-time
        run's sim clock (``VirtualTime.now``), so that latency is measured and applied in sim seconds."""
        self._clock = clock or time.time

    def set_interposer(self, interposer: Interposer | None) -> None:
        """Install (or remove, with None) the fault layer for this bus's egress and ingress."""
        self._interposer = interposer

    # -- pub/sub --------------------------------------------------------------------------------------------------
    async def publish(self, key: str, payload: Message | bytes, *, droppable: bool = False) -> None:
        """Publish ``payload`` (a message, encoded here, or raw bytes) on the concrete ``key``.

        Control traffic blocks under congestion (a dropped ack would stall a tick); ``droppable=True`` is for
        telemetry that may be dropped when a subscriber is slow.
        """
        self.put(key, payload, droppable=droppable)

    def put(self, key: str, payload: Message | bytes, *, droppable: bool = False) -> None:
        """:meth:`publish` without the coroutine: usable from a plain (sync) handler on the loop."""
        self._egress(self._stamp(key, payload), lambda s: self._send(s, droppable))

    def put_together(self, shared: tuple[str, Message | bytes], own: list[tuple[str, Message | bytes]]) -> None:
        """Publish ``shared`` once and each of ``own`` on its key, for receivers that each take one of the ``own``
        samples and the shared one (the sim's tick start: every robot's on-board state beside the fleet broadcast).

        Every sample gets its own header and passes the egress seam on its own, so to a receiver and its fault layer
        this is the same as separate puts. A transport may carry the shared sample inside each own one instead of
        sending it alone: :class:`~services.bus.zenoh_bus.ZenohBus` does (one message per robot and tick instead of
        two, and each received message costs a thread wake-up); over it, a subscriber of the shared key that takes
        none of the own keys does not get the shared sample.
        """
        self.put(*shared)
        for key, payload in own:
            self.put(key, payload)

    def _egress(self, sample: Sample, send: Callable[[Sample], None]) -> None:
        """``sample`` through the egress seam (the fault layer decides when ``send`` runs), or straight to ``send``."""
        if self._interposer is not None:
            self._interposer.on_publish(sample, send)
        else:
            send(sample)

    def _stamp(self, key: str, payload: Message | bytes) -> Sample:
        """A sample of this bus on ``key``, with its header (publisher, next sequence number of the key, clock)."""
        self._check_open()
        counter = self._seq.get(key)
        if counter is None:  # a key not published on before: checked once (setdefault is atomic: inline handlers on
            # another thread may publish too)
            validate_key(key)
            counter = self._seq.setdefault(key, itertools.count())
        self.counters.published += 1
        return Sample(key, to_payload(payload), self.identity, next(counter), self._clock())

    async def subscribe(self, key_expr: str, handler: Callable[[Sample], Awaitable[None] | None] | None = None,
                        *, inline: bool = False) -> Subscription[Sample]:
        """Subscribe to samples on ``key_expr`` (``*``/``**`` wildcards allowed).

        ``inline=True`` is the lock-step hot path (the fastest pattern measured over Zenoh, docs/services.md): the handler, a plain
        function, may run on the transport's receive thread instead of the loop, skipping one thread hop and loop
        wake-up per message. All inline handlers of one bus are serialized by one lock (they never run
        concurrently with each other), but they may run concurrently with coroutines on the loop: hand results to
        the loop with ``loop.call_soon_threadsafe``. ``put`` may be called from an inline handler. On LocalBus an
        inline handler runs on the loop like any plain handler.
        """
        self._check_open()
        validate_key_expr(key_expr)
        if inline and (handler is None or inspect.iscoroutinefunction(handler)):
            raise TypeError("an inline subscription needs a plain (non-async) handler function")
        sub: Subscription[Sample] = Subscription(self, key_expr, handler, inline)
        sub._deliver_fn = self._make_deliver(sub)
        sub._undeclare = self._declare_subscriber(key_expr, sub)
        self._entities.append(sub)
        return sub

    async def wait_for_subscribers(self, key: str, *, timeout: float = 5.0) -> None:
        """Wait until some subscriber matches ``key`` (declarations propagate asynchronously: a put made before the
        publisher knows of a subscriber is silently not delivered). TimeoutError names the key."""
        self._check_open()
        validate_key(key)
        deadline = time.monotonic() + timeout
        while not self._has_subscribers(key):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no subscriber for {key!r} after {timeout:.1f} s")
            await asyncio.sleep(0.005)

    # -- query/reply ----------------------------------------------------------------------------------------------
    async def declare_queryable(self, key_expr: str, handler: Callable[[Query], Awaitable[None] | None]) -> Declared:
        """Answer gets on ``key_expr``; ``handler(query)`` replies with ``query.reply(key, payload)``."""
        self._check_open()
        validate_key_expr(key_expr)
        declared = Declared(self, key_expr, lambda: None)
        declared._undeclare = self._declare_queryable(key_expr, handler)
        self._entities.append(declared)
        return declared

    async def get(self, selector: str, *, payload: Message | bytes | None = None, timeout: float = 2.0
                  ) -> list[Reply]:
        """Query every matching queryable; returns the replies received within ``timeout`` seconds."""
        self._check_open()
        key_expr, _, parameters = selector.partition("?")
        validate_key_expr(key_expr)
        data = None if payload is None else to_payload(payload)
        return await self._get(key_expr, parameters, data, timeout)

    # -- liveliness -----------------------------------------------------------------------------------------------
    async def declare_token(self, key: str) -> Declared:
        """Declare a liveliness token; it disappears when undeclared or when this session ends (even by a crash)."""
        self._check_open()
        validate_key(key)
        declared = Declared(self, key, lambda: None)
        declared._undeclare = self._declare_token(key)
        self._entities.append(declared)
        return declared

    async def subscribe_liveliness(self, key_expr: str,
                                   handler: Callable[[LivelinessEvent], Awaitable[None] | None] | None = None,
                                   *, history: bool = True) -> Subscription[LivelinessEvent]:
        """Liveliness changes on ``key_expr``; with ``history`` the tokens already present come first as alive."""
        self._check_open()
        validate_key_expr(key_expr)
        sub: Subscription[LivelinessEvent] = Subscription(self, key_expr, handler)
        sub._undeclare = self._declare_liveliness_subscriber(key_expr, sub, history)
        self._entities.append(sub)
        return sub

    async def alive(self, key_expr: str, *, timeout: float = 1.0) -> set[str]:
        """Keys of the liveliness tokens currently present on ``key_expr``."""
        self._check_open()
        validate_key_expr(key_expr)
        return await self._liveliness_get(key_expr, timeout)

    # -- transport hooks ------------------------------------------------------------------------------------------
    @abstractmethod
    def _send(self, sample: Sample, droppable: bool) -> None: ...

    @abstractmethod
    def _declare_subscriber(self, key_expr: str, sub: Subscription[Sample]) -> Callable[[], None]: ...

    @abstractmethod
    def _has_subscribers(self, key: str) -> bool: ...

    @abstractmethod
    def _declare_queryable(self, key_expr: str, handler: Callable[[Query], Awaitable[None] | None]
                           ) -> Callable[[], None]: ...

    @abstractmethod
    async def _get(self, key_expr: str, parameters: str, payload: bytes | None, timeout: float) -> list[Reply]: ...

    @abstractmethod
    def _declare_token(self, key: str) -> Callable[[], None]: ...

    @abstractmethod
    def _declare_liveliness_subscriber(self, key_expr: str, sub: Subscription[LivelinessEvent], history: bool
                                       ) -> Callable[[], None]: ...

    @abstractmethod
    async def _liveliness_get(self, key_expr: str, timeout: float) -> set[str]: ...

    @abstractmethod
    async def _close_transport(self) -> None: ...

    # -- shared plumbing ------------------------------------------------------------------------------------------
    def _ingress(self, sub: Subscription[Sample], sample: Sample) -> None:
        """A sample reached this bus for ``sub``: pass it through the fault seam to the handler."""
        if self._closed:
            return
        size = len(sample.payload)
        if size > _payload_bound(sample.key):  # before anything unpacks it (schemas/limits.py)
            self._refuse(sample, f"payload of {size} bytes exceeds the {_payload_bound(sample.key)}-byte bound of "
                                 "its kind")
            return
        if self._interposer is not None:
            self._interposer.on_deliver(sample, self.identity, sub._deliver_fn)
        else:
            sub._deliver_fn(sample)

    def _make_deliver(self, sub: Subscription[Sample]) -> Callable[[Sample], None]:
        """The function that hands one sample to ``sub`` (transports may wrap it, e.g. with a lock)."""
        def deliver(sample: Sample) -> None:
            if not self._closed:
                self.counters.delivered += 1
                sub._push(sample)
        return deliver

    def spawn(self, awaitable: Awaitable[Any], what: str) -> asyncio.Task:
        """Run ``awaitable`` on the loop in the background of this session: cancelled when the session closes, its
        failure counted and logged as a failed handler of ``what`` (the bus carries on)."""
        async def run() -> None:
            try:
                await awaitable
            except asyncio.CancelledError:
                raise
            except Exception:
                self._handler_failed(what)

        task = asyncio.get_running_loop().create_task(run())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _handler_failed(self, key_expr: str) -> None:
        self.counters.handler_errors += 1
        self.counters.per_key_errors[key_expr] = self.counters.per_key_errors.get(key_expr, 0) + 1
        log.exception("bus %s: handler for %s failed (the bus carries on)", self.identity, key_expr)

    async def _run_query_handler(self, handler: Callable[[Query], Awaitable[None] | None], query: Query) -> None:
        try:
            result = handler(query)
            if inspect.isawaitable(result):
                await result
        except asyncio.CancelledError:
            raise
        except Exception:
            self._handler_failed(query.key_expr)
            try:
                query.reply_err("queryable handler failed")
            except Exception:
                pass

    def _forget(self, entity: Subscription | Declared) -> None:
        try:
            self._entities.remove(entity)
        except ValueError:
            pass

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"bus {self.identity!r} is closed")
