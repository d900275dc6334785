"""ZenohBus: the Bus interface over zenoh-python 1.10.2, with the settings measured in ``docs``/zenoh reference.

* Explicit endpoints: the sim (or the supervisor's endpoint) *listens* on ``tcp/127.0.0.1:<port>``, every other
  process *connects*. Multicast and gossip scouting are off, so nothing is discovered behind our back and agents do
  not mesh with each other.
* Peer mode, ``transport/unicast/lowlatency`` (which requires QoS off) and the one-thread Zenoh runtime
  (``ZENOH_RUNTIME``, set below before zenoh is imported unless the environment already chose one): the fastest
  configuration for a lock-step loop of small messages.
* Declared publishers, cached per key, with ``CongestionControl.BLOCK`` (control traffic; a dropped ack stalls a
  tick) or ``DROP`` for ``droppable`` telemetry. ``express`` only on sessions without ``lowlatency``: the
  lowlatency transport does not batch anyway, and an express message from a lowlatency session, routed through the
  endpoint to a subscriber whose session uses default transport settings (any user's client, e.g. the README's
  five-line subscriber), stops that subscriber's stream after a couple of samples (measured with zenoh 1.10.2;
  docs/decisions.md).
* There is no asyncio API in zenoh-python: every Zenoh callback (it runs on a Zenoh-owned Python thread) converts
  the sample to plain bytes there and appends it to one inbox; the loop is woken with ``call_soon_threadsafe`` only
  when the inbox goes from empty to non-empty, so a burst of replies costs one wake-up, not one per message.
* Sessions are always closed explicitly: ``close()`` undeclares everything and closes the session on a daemon thread
  bounded by ``CLOSE_TIMEOUT``; a safety net closes any still-open session at interpreter shutdown *before* Python
  joins threads (a callback subscriber's thread is non-daemon and would otherwise keep the process alive).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
import threading
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

# One app worker thread and everything handed over to it: measured +6–60 % ticks/s and half the context switches.
# Must be in the environment before the Zenoh runtime starts. An empty value makes zenoh panic, so it is removed.
RUNTIME_SINGLE_THREAD = (
    "(rx: (handover: app), tx: (handover: app), acc: (handover: app), net: (handover: app), "
    "app: (worker_threads: 1))"
)


# The process hosting the endpoint routes every other process's messages: on a lowlatency link a message arriving
# from one robot is sent on to the others from the receiving task itself, which waits until that send is written.
# With the sends on the same single thread as the receiving tasks, a fleet of 128 robots under load stalled the
# whole run for good: every receiving task (51 of them) waited on a send whose write no thread was left to drive,
# with nothing queued on any socket. Its sends get a runtime thread of their own; the rest stays on the one thread.
RUNTIME_ENDPOINT = "(rx: (handover: app), acc: (handover: app), net: (handover: app), app: (worker_threads: 1))"


def configure_runtime_env(env: dict[str, str] | os._Environ = os.environ) -> dict[str, str] | os._Environ:
    """Put the one-thread runtime into ``env`` (unless one is chosen already); fix an empty ``ZENOH_RUNTIME``."""
    if env.get("ZENOH_RUNTIME", None) == "":
        del env["ZENOH_RUNTIME"]
    env.setdefault("ZENOH_RUNTIME", RUNTIME_SINGLE_THREAD)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread per agent process is plenty
    return env


def use_endpoint_runtime(env: dict[str, str] | os._Environ = os.environ) -> None:
    """In the process that will host the endpoint, before its session opens (Zenoh reads the variable when its
    runtime starts, at the first session): :data:`RUNTIME_ENDPOINT` in place of our one-thread default. A runtime
    the user chose stays."""
    if env.get("ZENOH_RUNTIME") == RUNTIME_SINGLE_THREAD:
        env["ZENOH_RUNTIME"] = RUNTIME_ENDPOINT


configure_runtime_env()

import zenoh  # noqa: E402  (after the runtime environment is set)

from schemas.base import Message  # noqa: E402
from schemas.limits import MAX_MESSAGE_BYTES  # noqa: E402
from services.bus.base import (  # noqa: E402
    Bus,
    LivelinessEvent,
    Query,
    Reply,
    Sample,
    Subscription,
    is_bundle,
    pack_bundle,
    pack_header,
    unpack_bundle,
    unpack_header,
)
from services.bus.routes import Routes  # noqa: E402

log = logging.getLogger("morph_sim.bus.zenoh")

CLOSE_TIMEOUT = 3.0
DRAIN_BATCH = 256  # inbox items delivered per loop turn (see ZenohBus._drain)
#: samples of one robot that may wait in a session's inbox for the loop: a robot sends a few messages a tick and the
#: monitor may read a few hundred ticks behind; more waiting is a flood, refused on arrival (Bus.inbox_author)
INBOX_PER_ROBOT = 4096
DEFAULT_PORT = 7447


def endpoint(port: int, host: str = "127.0.0.1", proto: str = "tcp") -> str:
    """``tcp/127.0.0.1:7447``."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"port {port} is out of range 1-65535")
    return f"{proto}/{host}:{int(port)}"


LISTEN_PORTS_FROM = 10000  # the lowest port free_port offers


def ephemeral_ports() -> tuple[int, int]:
    """The kernel's range of ports for the local end of outgoing connections (Linux; the IANA range elsewhere)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            low, high = (int(x) for x in f.read().split())
        return low, high
    except (OSError, ValueError):
        return 49152, 65535


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (for tests and single-machine runs), below the kernel's ephemeral range:
    a port the kernel picks (bind to 0) comes from that range, which every outgoing connection of this machine also
    draws from, so between this call and the listen a Zenoh client's connection could take it."""
    import random

    low, _ = ephemeral_ports()
    for _ in range(64):
        port = random.randrange(LISTEN_PORTS_FROM, low) if low > LISTEN_PORTS_FROM + 1 else 0
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return s.getsockname()[1]
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # no luck below the range: let the kernel choose
        s.bind((host, 0))
        return s.getsockname()[1]


def _as_list(value: str | Iterable[str] | None) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    return list(value)


def zenoh_config(*, listen: str | Iterable[str] | None = None, connect: str | Iterable[str] | None = None,
                 mode: str = "peer", lowlatency: bool = True, connect_timeout: float = 10.0,
                 base: zenoh.Config | None = None) -> zenoh.Config:
    """The project's Zenoh configuration: explicit endpoints, scouting off, low-latency unicast.

    ``connect_timeout`` bounds how long opening a session waits for its connect endpoints (then it fails with a
    clear error instead of hanging). ``base`` is a deployment's own config (e.g. user/password for an ACL router,
    read from ``ZENOH_CONFIG``); these settings are written on top of it.
    """
    listen_l, connect_l = _as_list(listen), _as_list(connect)
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode {mode!r} must be peer, client or router")
    if not listen_l and not connect_l:
        raise ValueError("zenoh endpoint: give listen (the process that hosts the endpoint) or connect (the others)")
    cfg = zenoh.Config() if base is None else base
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    # With scouting off there is nobody to wait for; Zenoh's default (500 ms) held every router's open that long,
    # and the sim's endpoint is one: every run started half a second later.
    cfg.insert_json5("scouting/delay", "0")
    cfg.insert_json5("listen/endpoints", json.dumps(listen_l))
    if connect_l:
        cfg.insert_json5("connect/endpoints", json.dumps(connect_l))
        ms = int(connect_timeout * 1000)
        cfg.insert_json5("connect/timeout_ms", json.dumps({"router": ms, "peer": ms, "client": ms}))
        cfg.insert_json5("connect/exit_on_failure", json.dumps({"router": True, "peer": True, "client": True}))
    if lowlatency:
        cfg.insert_json5("transport/unicast/lowlatency", "true")
        cfg.insert_json5("transport/unicast/qos/enabled", "false")
    if listen_l:
        # The process hosting the endpoint refuses oversized messages on arrival, before it reassembles or forwards
        # them: a lowlatency link cannot carry a message that does not fit one batch, and forwarding one closes the
        # link of every subscriber (services/credentials.py explains the bound).
        from services.credentials import MAX_MESSAGE_BYTES, size_limits

        cfg.insert_json5("low_pass_filter", json.dumps(size_limits()))
        cfg.insert_json5("transport/link/rx/max_message_size", json.dumps(2 * MAX_MESSAGE_BYTES))
        # Connections that never finish their handshake (silent or half-open sockets) each hold a pending slot until
        # the accept timeout; with Zenoh's defaults (100 slots, 10 s) 150 silent sockets kept every new session —
        # the operator's stop, a restarted agent — waiting 10 s. More slots, freed sooner: a handshake takes
        # milliseconds, so 5 s leaves a slow or busy client room, and starving the endpoint would take more than
        # 200 new silent sockets a second.
        cfg.insert_json5("transport/unicast/accept_timeout", json.dumps(ACCEPT_TIMEOUT_MS))
        cfg.insert_json5("transport/unicast/accept_pending", json.dumps(accept_pending()))
    return cfg


ACCEPT_TIMEOUT_MS = 5000
ACCEPT_PENDING = 1024


def accept_pending() -> int:
    """Handshakes the endpoint keeps pending: :data:`ACCEPT_PENDING`, or fewer where the process may open few files
    (each pending socket is a descriptor, and the endpoint's own sessions and records need some)."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (ImportError, OSError, ValueError):
        return ACCEPT_PENDING
    if soft == resource.RLIM_INFINITY:
        return ACCEPT_PENDING
    return max(16, min(ACCEPT_PENDING, soft // 2))


# Sessions still open at interpreter shutdown are closed before Python joins non-daemon threads.
_OPEN_SESSIONS: set[Any] = set()
_OPEN_LOCK = threading.Lock()


def _close_leftover_sessions() -> None:
    with _OPEN_LOCK:
        sessions = list(_OPEN_SESSIONS)
        _OPEN_SESSIONS.clear()
    for session in sessions:
        _close_session_bounded(session, CLOSE_TIMEOUT)


def _close_session_bounded(session: Any, timeout: float) -> threading.Event:
    done = threading.Event()

    def run() -> None:
        try:
            session.close()
        except Exception:
            log.debug("session close failed", exc_info=True)
        finally:
            done.set()

    threading.Thread(target=run, name="zenoh-close", daemon=True).start()
    done.wait(timeout)
    return done


_register_atexit = getattr(threading, "_register_atexit", None)
if _register_atexit is not None:  # CPython >= 3.9: runs before non-daemon threads are joined
    _register_atexit(_close_leftover_sessions)


async def _in_daemon_thread(fn: Callable[[], Any], timeout: float) -> tuple[bool, Any, BaseException | None]:
    """Run blocking ``fn`` on a daemon thread (so it can never hold up interpreter exit); wait at most ``timeout``.

    Returns (finished, result, error).
    """
    loop = asyncio.get_running_loop()
    fut: asyncio.Future = loop.create_future()

    def settle(value: tuple[Any, BaseException | None]) -> None:
        if not fut.done():
            fut.set_result(value)

    def run() -> None:
        try:
            value: tuple[Any, BaseException | None] = (fn(), None)
        except BaseException as exc:  # zenoh raises ZError; keep whatever it was
            value = (None, exc)
        try:
            loop.call_soon_threadsafe(settle, value)
        except RuntimeError:  # loop already closed
            pass

    threading.Thread(target=run, name="zenoh-blocking", daemon=True).start()
    try:
        result, error = await asyncio.wait_for(asyncio.shield(fut), timeout)
    except asyncio.TimeoutError:
        return False, None, None
    return True, result, error


class _ZenohQuery(Query):
    def __init__(self, zquery: Any):
        payload = zquery.payload
        super().__init__(str(zquery.key_expr), str(zquery.parameters),
                         None if payload is None else payload.to_bytes())
        self._zquery = zquery

    def _reply(self, key: str, payload: bytes) -> None:
        self._zquery.reply(key, payload)

    def _reply_err(self, payload: bytes) -> None:
        self._zquery.reply_err(payload)


class ZenohBus(Bus):
    """A Bus over one Zenoh session. Open with :meth:`open` (listen or connect)."""

    flushes_late = True

    def __init__(self, identity: str, session: Any, loop: asyncio.AbstractEventLoop, *, express: bool = False):
        super().__init__(identity)
        self.session = session
        self._loop = loop
        self._express = express
        self._inbox: deque[tuple[Callable[..., None], tuple]] = deque()
        self._waiting: dict[int, int] = {}  # robot -> its samples in the inbox (see _post_sample)
        self._waiting_lock = threading.Lock()
        self._drain_pending = False
        self._publishers: dict[tuple[str, bool], Any] = {}
        # Serializes inline handlers across subscriptions (each Zenoh callback subscriber has its own thread).
        # Re-entrant: an inline handler may trigger a nested delivery (e.g. a fault layer delivering at once).
        self._inline_lock = threading.RLock()
        self._pub_lock = threading.Lock()
        # the sample subscriptions of this session, and per key the ones it reaches: where a bundle's samples go
        self._routes: Routes[Subscription[Sample]] = Routes(lambda sub: sub.key_expr)
        with _OPEN_LOCK:
            _OPEN_SESSIONS.add(session)

    @classmethod
    async def open(cls, identity: str, *, listen: str | Iterable[str] | None = None,
                   connect: str | Iterable[str] | None = None, mode: str = "peer", lowlatency: bool = True,
                   connect_timeout: float = 10.0, config: Any = None) -> ZenohBus:
        """Open a session: ``listen=endpoint(port)`` for the process hosting the endpoint, ``connect=`` otherwise.

        Raises ConnectionError (naming the endpoint) if the session cannot be opened within ``connect_timeout``.
        """
        cfg = config if config is not None else zenoh_config(
            listen=listen, connect=connect, mode=mode, lowlatency=lowlatency, connect_timeout=connect_timeout)
        if listen is not None:
            use_endpoint_runtime()
        loop = asyncio.get_running_loop()
        # zenoh.open blocks while it connects: keep it off the loop and off the exit path.
        finished, session, error = await _in_daemon_thread(lambda: zenoh.open(cfg), connect_timeout + 5.0)
        where = f"listen={_as_list(listen)}, connect={_as_list(connect)}"
        if not finished:
            raise ConnectionError(f"zenoh session did not open within {connect_timeout + 5.0:.0f} s ({where})")
        if error is not None:
            if connect is not None and "Unable to connect" in str(error):
                raise ConnectionError(f"cannot reach the Zenoh endpoint {', '.join(_as_list(connect))}: nothing "
                                      f"answered within {connect_timeout:.0f} s (is the run up?)") from None
            raise ConnectionError(f"cannot open zenoh session ({where}): {error}") from None
        lowlatency_on = json.loads(cfg.get_json("transport/unicast/lowlatency")) is True
        bus = cls(identity, session, loop, express=not lowlatency_on)
        bus.hosts_endpoint = bool(_as_list(listen))
        return bus

    # -- bridge: Zenoh threads -> the asyncio loop -------------------------------------------------------------------
    def _post(self, fn: Callable[..., None], *args: Any) -> None:
        """Called on a Zenoh callback thread: queue ``fn(*args)`` for the loop, waking it once per burst."""
        self._inbox.append((fn, args))
        if not self._drain_pending:
            self._drain_pending = True
            try:
                self._loop.call_soon_threadsafe(self._drain)
            except RuntimeError:  # loop closed: the process is shutting down
                pass

    def _post_sample(self, sub: Subscription[Sample], sample: Sample) -> None:
        """Called on a Zenoh callback thread: queue ``sample`` for ``sub`` on the loop, within its robot's share of
        the inbox (:data:`INBOX_PER_ROBOT`; a sample over it is refused and counted)."""
        author_of = self.inbox_author
        robot = None
        if author_of is not None:
            try:
                robot = author_of(sample.key)
            except ValueError:
                robot = None
        if type(robot) is not int:
            self._post(self._ingress, sub, sample)
            return
        with self._waiting_lock:
            waiting = self._waiting.get(robot, 0)
            if waiting < INBOX_PER_ROBOT:
                self._waiting[robot] = waiting + 1
        if waiting >= INBOX_PER_ROBOT:
            self._refuse(sample, f"robot {robot} has {INBOX_PER_ROBOT} messages waiting to be read: over its share")
            return
        self._post(self._ingress_counted, sub, sample, robot)

    def _ingress_counted(self, sub: Subscription[Sample], sample: Sample, robot: int) -> None:
        with self._waiting_lock:
            left = self._waiting.get(robot, 1) - 1
            if left > 0:
                self._waiting[robot] = left
            else:
                self._waiting.pop(robot, None)
        self._ingress(sub, sample)

    def _drain(self) -> None:
        """Deliver what is in the inbox now, at most ``DRAIN_BATCH`` items, then give the loop a turn.

        Samples keep arriving while we deliver: a drain that ran until the inbox was empty never returned under a
        steady stream (the monitor takes in every message of the run), so nothing else on the loop ran — no task,
        no timer, no query answer — and the monitor's metric publications waited for the end of the run.
        """
        inbox = self._inbox
        for _ in range(min(len(inbox), DRAIN_BATCH)):
            fn, args = inbox.popleft()
            try:
                fn(*args)
            except Exception:
                log.exception("bus %s: delivery failed", self.identity)
        if inbox:
            self._loop.call_soon(self._drain)  # behind whatever became ready meanwhile; stays pending
        else:
            self._drain_pending = False
            if inbox:  # appended between the check and the flag: nobody else will schedule it
                self._drain_pending = True
                self._loop.call_soon(self._drain)

    # -- transport hooks -------------------------------------------------------------------------------------------
    def _publisher(self, key: str, droppable: bool) -> Any:
        pub = self._publishers.get((key, droppable))
        if pub is None:
            with self._pub_lock:  # the loop and inline handlers may both publish on a new key
                pub = self._publishers.get((key, droppable))
                if pub is None:
                    pub = self.session.declare_publisher(
                        key, express=self._express, reliability=zenoh.Reliability.RELIABLE,
                        congestion_control=(zenoh.CongestionControl.DROP if droppable
                                            else zenoh.CongestionControl.BLOCK))
                    self._publishers[(key, droppable)] = pub
        return pub

    def _has_subscribers(self, key: str) -> bool:
        return bool(self._publisher(key, False).matching_status.matching)

    def _send(self, sample: Sample, droppable: bool) -> None:
        self._put(sample, sample.payload, droppable)

    def _put(self, sample: Sample, payload: bytes, droppable: bool) -> None:
        """One Zenoh message on ``sample``'s key with its header: its payload, or a bundle carrying it."""
        if self._closed:
            return
        pub = self._publishers.get((sample.key, droppable)) or self._publisher(sample.key, droppable)
        pub.put(payload, attachment=pack_header(sample.sender, sample.seq, sample.sent_at))

    def put_together(self, shared: tuple[str, Message | bytes], own: list[tuple[str, Message | bytes]]) -> None:
        """The shared sample rides inside each own one: one Zenoh message per receiver (see :meth:`Bus.put_together`).

        Each sample still passes the egress seam on its own; a copy that the seam sends later than now (a delay at
        the publisher) goes out alone on its key."""
        riders: list[Sample] = []
        building = True

        def carry(sample: Sample) -> None:
            if building:
                riders.append(sample)
            else:
                self._send(sample, False)

        self._egress(self._stamp(*shared), carry)
        building = False
        for key, payload in own:
            self._egress(self._stamp(key, payload), self._send_with(riders))

    def _send_with(self, riders: list[Sample]) -> Callable[[Sample], None]:
        def send(sample: Sample) -> None:
            self._put(sample, pack_bundle([*riders, sample]), False)
        return send

    def _make_deliver(self, sub: Subscription[Sample]) -> Callable[[Sample], None]:
        deliver = super()._make_deliver(sub)
        if not sub.inline:
            return deliver
        lock = self._inline_lock

        def deliver_locked(sample: Sample) -> None:  # any thread (receive thread, or the loop after a delay)
            with lock:
                deliver(sample)
        return deliver_locked

    def _declare_subscriber(self, key_expr: str, sub: Subscription[Sample]) -> Callable[[], None]:
        post_sample, ingress, put_kind = self._post_sample, self._ingress, zenoh.SampleKind.PUT
        inline = sub.inline

        def on_sample(zs: Any) -> None:  # Zenoh thread
            if zs.kind != put_kind:
                return
            att = zs.attachment
            sender, seq, sent_at = unpack_header(None if att is None else att.to_bytes())
            sample = Sample(str(zs.key_expr), zs.payload.to_bytes(), sender, seq, sent_at)
            if is_bundle(sample.payload):
                self._unbundle(sub, sample)
            elif inline:
                ingress(sub, sample)  # straight to the handler on this thread (deliver_locked serializes)
            else:
                post_sample(sub, sample)

        zsub = self.session.declare_subscriber(key_expr, on_sample)
        self._routes.add(sub)

        def undeclare() -> None:
            self._routes.remove(sub)
            zsub.undeclare()
        return undeclare

    def _unbundle(self, sub: Subscription[Sample], carrier: Sample) -> None:
        """A bundle arrived for ``sub`` (Zenoh thread): each sample in it goes to every subscription of this session
        its own key reaches, as if it had come alone. Zenoh hands the carrier to each subscription that matches its
        key; the first of them in declaration order unpacks it, the others leave it."""
        takers = self._routes.reach(carrier.key)
        if not takers or takers[0] is not sub or self._closed:
            return
        if len(carrier.payload) > MAX_MESSAGE_BYTES:
            self._refuse(carrier, f"bundle of {len(carrier.payload)} bytes exceeds the transport's "
                                  f"{MAX_MESSAGE_BYTES}-byte bound")
            return
        try:
            samples = unpack_bundle(carrier)
        except ValueError as exc:
            self._refuse(carrier, str(exc))
            return
        ingress, post_sample = self._ingress, self._post_sample
        for sample in samples:
            for target in self._routes.reach(sample.key):
                if target.inline:
                    ingress(target, sample)
                else:
                    post_sample(target, sample)

    def _declare_queryable(self, key_expr: str, handler: Callable[[Query], Awaitable[None] | None]
                           ) -> Callable[[], None]:
        def on_query(zquery: Any) -> None:  # Zenoh thread
            # straight to the loop, not behind the inbox: a querier (a restarting agent restoring its state) waits for
            # the answer, which must not queue behind the samples of a busy subscription (the monitor's)
            try:
                self._loop.call_soon_threadsafe(self._start_query, handler, zquery)
            except RuntimeError:  # loop closed: the process is shutting down
                pass

        zq = self.session.declare_queryable(key_expr, on_query)
        return zq.undeclare

    def _start_query(self, handler: Callable[[Query], Awaitable[None] | None], zquery: Any) -> None:
        async def run() -> None:
            try:
                await self._run_query_handler(handler, _ZenohQuery(zquery))
            finally:
                try:
                    zquery.drop()  # finalises the query so the querier is not left waiting for its timeout
                except Exception:
                    pass

        self.spawn(run(), "queryable")

    async def _get(self, key_expr: str, parameters: str, payload: bytes | None, timeout: float) -> list[Reply]:
        replies: list[Reply] = []
        finished = self._loop.create_future()

        def on_reply(zr: Any) -> None:  # Zenoh thread
            ok = zr.ok
            if ok is not None:
                reply = Reply(str(ok.key_expr), payload=ok.payload.to_bytes())
            else:
                reply = Reply(key_expr, error=zr.err.payload.to_bytes())
            self._post(replies.append, reply)

        def on_done() -> None:  # Zenoh thread, after the last reply
            self._post(lambda: finished.done() or finished.set_result(None))

        selector = f"{key_expr}?{parameters}" if parameters else key_expr
        kwargs: dict[str, Any] = {"target": zenoh.QueryTarget.ALL, "consolidation": zenoh.ConsolidationMode.NONE,
                                  "timeout": timeout}
        if payload is not None:
            kwargs["payload"] = payload
        self.session.get(selector, zenoh.handlers.Callback(on_reply, on_done), **kwargs)
        try:
            await asyncio.wait_for(asyncio.shield(finished), timeout + 1.0)
        except asyncio.TimeoutError:
            pass
        return list(replies)

    def _declare_token(self, key: str) -> Callable[[], None]:
        token = self.session.liveliness().declare_token(key)
        return token.undeclare

    def _declare_liveliness_subscriber(self, key_expr: str, sub: Subscription[LivelinessEvent], history: bool
                                       ) -> Callable[[], None]:
        put_kind = zenoh.SampleKind.PUT

        def on_change(zs: Any) -> None:  # Zenoh thread
            self._post(sub._push, LivelinessEvent(str(zs.key_expr), zs.kind == put_kind))

        zsub = self.session.liveliness().declare_subscriber(key_expr, on_change, history=history)
        return zsub.undeclare

    async def _liveliness_get(self, key_expr: str, timeout: float) -> set[str]:
        keys: set[str] = set()
        finished = self._loop.create_future()

        def on_reply(zr: Any) -> None:
            ok = zr.ok
            if ok is not None:
                self._post(keys.add, str(ok.key_expr))

        def on_done() -> None:
            self._post(lambda: finished.done() or finished.set_result(None))

        self.session.liveliness().get(key_expr, zenoh.handlers.Callback(on_reply, on_done), timeout=timeout)
        try:
            await asyncio.wait_for(asyncio.shield(finished), timeout + 1.0)
        except asyncio.TimeoutError:
            pass
        return set(keys)

    async def _close_transport(self) -> None:
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except Exception:
                pass
        self._publishers.clear()
        session = self.session
        with _OPEN_LOCK:
            _OPEN_SESSIONS.discard(session)
        finished, _, _ = await _in_daemon_thread(session.close, CLOSE_TIMEOUT)
        if not finished:
            log.warning("bus %s: zenoh session did not close within %.1f s; continuing", self.identity, CLOSE_TIMEOUT)
        self._inbox.clear()


async def open_endpoint_bus(identity: str, port_or_endpoint: int | str, *, host: bool,
                            connect_timeout: float = 10.0, lowlatency: bool = True) -> ZenohBus:
    """Open a session on the run's embedded endpoint: ``host=True`` for the process that listens on it (the sim,
    or the supervisor), ``host=False`` for every process that connects (agents, monitor, CLI tools).

    ``port_or_endpoint`` is a port on 127.0.0.1 or a full endpoint such as ``tcp/10.0.0.5:7447``.
    """
    ep = endpoint(port_or_endpoint) if isinstance(port_or_endpoint, int) else port_or_endpoint
    if host:
        return await ZenohBus.open(identity, listen=ep, lowlatency=lowlatency)
    return await ZenohBus.open(identity, connect=ep, connect_timeout=connect_timeout, lowlatency=lowlatency)

