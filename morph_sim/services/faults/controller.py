"""The ``ctl/faults`` controller (DESIGN §4): every process mounts one over its fault layers.

* a queryable on ``morph/<run>/ctl/faults``: ``morph-sim faults set|list|reset`` sends a :class:`FaultCommand` as the
  query payload; each process applies it to its own layers (each keeps its own seeded per-link streams) and replies
  a :class:`FaultReply` naming itself, so the operator sees every process's answer;
* a subscriber on the same key: a put reaches every process the same way (no reply);
* a schedule (:mod:`.schedule`) applied locally at sim-time boundaries through :meth:`FaultController.advance`.

Crash faults are not the bus's business: they go to ``on_crash`` (the supervisor's hook) and are rejected with the
reason in a process that has none. ``reset`` always heals every network fault of the process, whatever else fails.

The process that owns the run record (the sim, ``events=True``) publishes each change as an ``Event`` on
``events/<source>`` with its tick and sim time — ``fault.set``, ``fault.reset``, ``fault.healed`` — so plots can
shade fault windows.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

from pydantic import ValidationError

from morph_sim.schemas.base import DecodeError
from morph_sim.schemas.codec import decode
from morph_sim.schemas.faults import FaultSpec
from morph_sim.schemas.keys import RunKeys
from morph_sim.schemas.messages import Event, FaultCommand, FaultReply
from morph_sim.services.bus.base import Bus, Query, Sample
from morph_sim.services.bus.faults import ActiveFault, FaultLayer
from morph_sim.services.faults.schedule import FaultSchedule

log = logging.getLogger("morph_sim.faults")

CrashHook = Callable[[FaultSpec], str | None]  # returns an error message, or None when accepted


def _network_part(spec: FaultSpec) -> bool:
    return any(x is not None for x in (spec.latency, spec.loss, spec.duplicate, spec.reorder, spec.partition))


class FaultController:
    """Applies fault commands to ``layers`` (all fault layers of this process)."""

    def __init__(self, bus: Bus, run: str, layers: list[FaultLayer], *, clock: Callable[[], float],
                 dt: float = 1.0, events: bool = False, on_crash: CrashHook | None = None,
                 schedule: FaultSchedule | None = None):
        self.bus = bus
        self.keys = RunKeys(run)
        self.layers = list(layers)
        self.clock = clock  # sim seconds
        self.dt = dt
        self.events = events
        self.on_crash = on_crash
        self.log: list[Event] = []  # every change this controller reported, in order
        self._timeline = schedule.timeline(dt) if schedule is not None else []
        self._next = 0
        if self.layers and events:
            first = self.layers[0]  # heals happen in every layer at the same sim time: report one of them
            chained = first.on_change

            def changed(what: str, fault: ActiveFault) -> None:
                if chained is not None:
                    chained(what, fault)
                if what == "healed":
                    self._event("fault.healed", fault.fault_id, fault.spec)
            first.on_change = changed

    async def start(self) -> None:
        await self.bus.declare_queryable(self.keys.faults, self._on_query)
        await self.bus.subscribe(self.keys.faults, self._on_put)

    # -- commands ------------------------------------------------------------------------------------------------------
    def handle(self, command: FaultCommand) -> FaultReply:
        """Apply one command to every layer of this process; never raises."""
        source = self.bus.identity
        try:
            if command.op == "reset":
                if command.fault_id is None:
                    healed = [fid for layer in self.layers for fid in layer.reset()]
                    for fid in dict.fromkeys(healed):
                        self._event("fault.reset", fid, None)
                    return FaultReply(ok=True, active=[], source=source)
                if not any(command.fault_id in {s.id for s in layer.active()} for layer in self.layers):
                    return FaultReply(ok=False, error=f"no active fault {command.fault_id!r}",
                                      active=self._active(), source=source)
                for layer in self.layers:
                    layer.reset(command.fault_id)
                self._event("fault.reset", command.fault_id, None)
            elif command.op == "set":
                spec = command.spec
                assert spec is not None  # FaultCommand guarantees it
                if spec.crash is not None:
                    if self.on_crash is None:
                        return FaultReply(ok=False, error="crash: this process has no supervisor to carry it out",
                                          active=self._active(), source=source)
                    error = self.on_crash(spec)
                    if error:
                        return FaultReply(ok=False, error=f"crash: {error}", active=self._active(), source=source)
                    if not _network_part(spec):
                        self._event("fault.crash", spec.id or "crash", spec)
                        return FaultReply(ok=True, active=self._active(), source=source)
                    spec = spec.model_copy(update={"crash": None})
                if spec.id is None:  # one id for the fault in every layer (and in the event log)
                    spec = spec.model_copy(update={"id": f"fault-{len(self.log) + 1}-{round(self.clock() * 1000)}"})
                for layer in self.layers:
                    layer.set(spec)
                self._event("fault.set", spec.id or "", spec)
        except (ValueError, ValidationError) as exc:
            return FaultReply(ok=False, error=str(exc), active=self._active(), source=source)
        return FaultReply(ok=True, active=self._active(), source=source)

    def _active(self) -> list[FaultSpec]:
        return self.layers[0].active() if self.layers else []

    def advance(self, now: float) -> list[FaultReply]:
        """Apply the scheduled commands due by sim time ``now`` (call at each tick start, or register on a
        VirtualTime's ``on_advance``)."""
        out = []
        while self._next < len(self._timeline) and self._timeline[self._next][0] <= now + 1e-9:
            at, command = self._timeline[self._next]
            self._next += 1
            reply = self.handle(command)
            if not reply.ok:
                log.warning("fault schedule at %.3f s: %s", at, reply.error)
            out.append(reply)
        return out

    # -- transport -----------------------------------------------------------------------------------------------------
    def _decode(self, payload: bytes | None) -> FaultCommand | str:
        if not payload:
            return FaultCommand(op="list")  # a bare query lists
        try:
            return decode(payload, FaultCommand)  # type: ignore[return-value]
        except (DecodeError, ValueError) as exc:
            return f"bad fault command: {exc}"

    def _on_query(self, query: Query) -> None:
        command = self._decode(query.payload)
        reply = (FaultReply(ok=False, error=command, active=self._active(), source=self.bus.identity)
                 if isinstance(command, str) else self.handle(command))
        query.reply(self.keys.faults, reply)

    def _on_put(self, sample: Sample) -> None:
        command = self._decode(sample.payload)
        if isinstance(command, str):
            log.warning("ctl/faults from %r: %s", sample.sender, command)
            return
        reply = self.handle(command)
        if not reply.ok:
            log.warning("ctl/faults %s from %r rejected: %s", command.op, sample.sender, reply.error)

    def _event(self, kind: str, fault_id: str, spec: FaultSpec | None) -> None:
        now = self.clock()
        details: dict = {"fault_id": fault_id}
        if spec is not None:
            details["spec"] = spec.model_dump(mode="json", exclude_none=True)
        event = Event(kind=kind, source=self.bus.identity, t=max(0, math.floor(now / self.dt + 1e-9)),
                      sim_time=now, wall_time=time.time(), details=details)
        self.log.append(event)
        if self.events and not self.bus.closed:
            try:
                self.bus.put(self.keys.event(self.bus.identity), event)
            except Exception:  # the record loses one event; the run goes on
                log.exception("could not publish %s", kind)
