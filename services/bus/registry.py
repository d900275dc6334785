"""The robot-id registry over a bus: the sim serves it, an agent started without ``--id`` claims an id from it.

The allocation rules are pure code in :mod:`services.protocol.registry`; this module only moves the
:class:`RegistrationRequest` and :class:`RegistrationReply` messages and follows the agents' liveliness tokens.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections.abc import Callable

from schemas.codec import decode
from schemas.keys import RunKeys
from schemas.messages import PolicyAnnouncement, RegistrationReply, RegistrationRequest
from services.protocol.registry import (
    DEFAULT_HOLD,
    INVALID,
    RETRYABLE,
    IdAllocator,
    Refusal,
    RegistrationError,
    reason_code,
)

log = logging.getLogger("morph_sim.registry")


class Registry:
    """The sim side: serves ``morph/<run>/registry`` on a Bus and follows the agents' liveliness tokens."""

    def __init__(self, bus, keys: RunKeys, n_agvs: int, n_pickers: int, *, hold: float = DEFAULT_HOLD,
                 clock: Callable[[], float] = time.monotonic, policy: PolicyAnnouncement | None = None):
        self.bus = bus
        self.policy = policy
        self.keys = keys
        self.allocator = IdAllocator(n_agvs, n_pickers, hold)
        self.alive: set[int] = set()
        self.clock = clock
        self.grants: list[tuple[str, int]] = []  # (instance, id) in grant order, for logs and tests
        self._entities: list = []

    async def start(self) -> Registry:
        # Liveliness first (with history): the first query must already know which ids are live.
        self._entities.append(await self.bus.subscribe_liveliness(self.keys.alive_all, self._on_liveliness,
                                                                  history=True))
        self._entities.append(await self.bus.declare_queryable(self.keys.registry, self._on_query))
        if self.policy is not None:
            self._entities.append(await self.bus.declare_queryable(self.keys.registry_policy, self._on_policy_query))
        return self

    def _on_policy_query(self, query) -> None:
        query.reply(self.keys.registry_policy, self.policy)

    async def close(self) -> None:
        for entity in reversed(self._entities):
            await entity.close()
        self._entities.clear()

    def _on_liveliness(self, event) -> None:
        try:
            agent = self.keys.alive_id(event.key)
        except ValueError:
            return
        if not isinstance(agent, int) or not 0 <= agent < self.allocator.n_agents:
            return  # a service token (alive/sim, alive/monitor) or a stray id
        if event.alive:
            self.alive.add(agent)
            self.allocator.seen_alive(agent)
        else:
            self.alive.discard(agent)

    def _on_query(self, query) -> None:
        n_agvs, n_pickers = self.allocator.n_agvs, self.allocator.n_pickers
        try:
            if query.payload is None:
                raise Refusal(INVALID, "the query carries no RegistrationRequest payload")
            request = decode(query.payload, RegistrationRequest)
            grant = self.allocator.allocate(request.instance, self.alive, self.clock(), want_id=request.want_id,
                                            want_role=request.want_role)
        except Refusal as refusal:
            reply = RegistrationReply(ok=False, reason=str(refusal), n_agvs=n_agvs, n_pickers=n_pickers)
        except ValueError as exc:  # a payload that does not decode: name the field, keep serving
            reply = RegistrationReply(ok=False, reason=f"{INVALID}: {exc}", n_agvs=n_agvs, n_pickers=n_pickers)
        else:
            self.grants.append((request.instance, grant.agent_id))
            log.info("registry: %s -> robot %d (%s%s)", request.instance, grant.agent_id, grant.role,
                     ", returning" if grant.returning else "")
            reply = RegistrationReply(ok=True, agent_id=grant.agent_id, role=grant.role, n_agvs=n_agvs,
                                      n_pickers=n_pickers)
        query.reply(self.keys.registry, reply)


async def mount_registry(bus, keys: RunKeys, n_agvs: int, n_pickers: int, *, hold: float = DEFAULT_HOLD,
                         clock: Callable[[], float] = time.monotonic,
                         policy: PolicyAnnouncement | None = None) -> Registry:
    """Serve the registration queryable of ``keys.run`` on ``bus`` (the sim calls this before readiness), and the
    announcement of the run's ``policy``."""
    return await Registry(bus, keys, n_agvs, n_pickers, hold=hold, clock=clock, policy=policy).start()


async def fetch_policy(bus, keys: RunKeys, *, timeout: float = 60.0, query_timeout: float = 2.0
                       ) -> PolicyAnnouncement:
    """The run's policy as its sim announces it; retries until ``timeout`` seconds, then RegistrationError."""
    deadline = time.monotonic() + timeout
    delay, last = 0.1, "no answer (is the sim running and reachable?)"
    while True:
        remaining = deadline - time.monotonic()
        for reply in await bus.get(keys.registry_policy, timeout=max(0.05, min(query_timeout, remaining))):
            if not reply.ok:
                last = f"error {reply.error!r}"
                continue
            try:
                return reply.decode(PolicyAnnouncement)
            except ValueError as exc:
                last = f"undecodable announcement: {exc}"
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise RegistrationError(f"policy: the run's policy on {keys.registry_policy}: {last}")
        await asyncio.sleep(min(delay, remaining))
        delay = min(delay * 2, 1.0)


def default_instance(environ: dict[str, str] | os._Environ = os.environ, pid: int | None = None) -> str:
    """The name an agent registers under: ``MORPH_INSTANCE``, else ``<host name>-<pid>``.

    The pid is part of it because processes on one host share the host name, and two claims under one name are one
    instance to the allocator: both would get its id. A restarted agent (a new pid, or a new container) still gets
    its robot back in a running run, where every other id is held and the departed one is the only id free."""
    return environ.get("MORPH_INSTANCE") or f"{socket.gethostname()}-{os.getpid() if pid is None else pid}"


async def claim_id(bus, keys: RunKeys, instance: str | None = None, *, want_id: int | None = None,
                   want_role: str | None = None, timeout: float = 60.0, query_timeout: float = 2.0
                   ) -> RegistrationReply:
    """Ask the sim's registry for a robot id; retry ``busy``/``full``/no answer until ``timeout`` seconds.

    Returns the granted :class:`RegistrationReply` (``agent_id``, ``role``, fleet size). Raises RegistrationError
    naming the last reason when the deadline passes or the request is invalid.
    """
    instance = instance or default_instance()
    request = RegistrationRequest(instance=instance, want_id=want_id, want_role=want_role)
    deadline = time.monotonic() + timeout
    delay, last = 0.1, "no reply from the registry (is the sim running and reachable?)"
    while True:
        remaining = deadline - time.monotonic()
        replies = await bus.get(keys.registry, payload=request, timeout=max(0.05, min(query_timeout, remaining)))
        for reply in replies:
            if not reply.ok:
                last = f"registry error: {reply.error!r}"
                continue
            try:
                answer = reply.decode(RegistrationReply)
            except ValueError as exc:  # not from our registry (or a newer one): ignore it, keep asking
                last = f"undecodable registry reply: {exc}"
                continue
            if answer.ok:
                return answer
            last = answer.reason or "refused without a reason"
            if reason_code(last) not in RETRYABLE:
                raise RegistrationError(f"registration of instance {instance!r} on {keys.registry}: {last}")
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise RegistrationError(
                f"registration of instance {instance!r} on {keys.registry} timed out after {timeout:.0f} s: {last}")
        await asyncio.sleep(min(delay, remaining))
        delay = min(delay * 2, 2.0)
