"""The ``ctl/faults`` controller (docs/faults.md): every process mounts one over its fault layers.

* a queryable on ``morph/<run>/ctl/faults/<identity>``: ``morph-sim faults set|list|reset`` sends a
  :class:`FaultCommand` as the query payload to ``ctl/faults/*``; each process applies it to its own layers (each
  keeps its own seeded per-link streams) and replies a :class:`FaultReply` under its own key, so the operator sees
  every process's answer and knows whose it is (only that process may answer there);
* a subscriber on the same key: a put reaches every process the same way (no reply);
* a schedule (:mod:`.schedule`) applied locally at sim-time boundaries through :meth:`FaultController.advance`.

Only a process with a stake in a command answers it, so the operator's verdict is the verdict of the processes that
carry the fault out: crash faults are not the bus's business, they go to ``on_crash`` (the supervisor's planner) and
a process without that hook stays silent on them (it applies only the network part of a spec that has one); a process
without fault layers (the supervisor) stays silent on network faults. ``reset`` always heals every network fault of
the process, whatever else fails. A spec naming a robot outside the fleet (``fleet``) is refused, naming the field.

The process that owns the run record (the sim, ``events=True``) publishes each change as an ``Event`` on
``events/<source>`` with its tick and sim time — ``fault.set``, ``fault.reset``, ``fault.healed`` — so plots can
shade fault windows; the supervisor publishes ``fault.crash_planned`` when it accepts a crash spec (the crash itself
is its ``agent.crash`` event, at the tick it happened).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable

from pydantic import ValidationError

from schemas.base import DecodeError
from schemas.codec import decode
from schemas.errors import explain
from schemas.faults import FaultSpec
from schemas.keys import RunKeys
from schemas.messages import Event, FaultCommand, FaultReply
from services.bus.base import Bus, Query, Sample
from services.faults.layer import ActiveFault, FaultLayer
from services.faults.schedule import FaultSchedule

log = logging.getLogger("morph_sim.faults")

CrashHook = Callable[[FaultSpec], str | None]  # returns an error message, or None when accepted
#: the shared air's airtime faults: (spec, its start in sim seconds or None for now) -> an error message, or None
RateHook = Callable[[FaultSpec, float | None], str | None]
RateResetHook = Callable[[str | None, float | None], None]  # end one airtime fault (by id) or all, at a sim time
CrashResetHook = Callable[[str | None], None]  # forget one crash spec (by id) or all of them


def _network_part(spec: FaultSpec) -> bool:
    return any(x is not None for x in (spec.latency, spec.loss, spec.duplicate, spec.reorder, spec.partition))


class FaultController:
    """Applies fault commands to ``layers`` (all fault layers of this process)."""

    def __init__(self, bus: Bus, run: str, layers: list[FaultLayer], *, clock: Callable[[], float],
                 dt: float = 1.0, events: bool = False, on_crash: CrashHook | None = None,
                 schedule: FaultSchedule | None = None, lock=None, hold_events: bool = False,
                 on_crash_reset: CrashResetHook | None = None, fleet: int | None = None,
                 on_rate: RateHook | None = None, on_rate_reset: RateResetHook | None = None,
                 air_run: bool = False):
        self.bus = bus
        # airtime faults (FaultSpec.rate): the air carries them out (on_rate); the run record's owner (events) records
        # them, or refuses them in a run without an air (air_run False); any other process stays silent on them
        self.on_rate, self.on_rate_reset, self.air_run = on_rate, on_rate_reset, air_run
        self.rates: list[tuple[FaultSpec, float]] = []  # (airtime fault, its start) in force, as this process knows
        self.on_crash_reset = on_crash_reset
        self.fleet = fleet  # number of robots (ids 0..fleet-1), to refuse a spec naming one outside the run
        # ids of crash specs this process left to the supervisor: a reset of one of them is not this process's to judge
        self._crash_ids_elsewhere: set[str] = set()
        # the process's fault lock (FaultRuntime): commands arrive on the loop while transport threads decide fates
        self.lock = lock if lock is not None else contextlib.nullcontext()
        # hold_events: events of changes before the run starts are kept and published by publish_held() at tick 0,
        # once the monitor is known to listen (a fault scheduled at tick 0 is applied when the process starts)
        self._held_events: list[Event] | None = [] if events and hold_events else None
        self.crashes: list[FaultSpec] = []  # crash specs accepted (the supervisor lists them: it has no layers)
        self.keys = RunKeys(run)
        self.layers = list(layers)
        self.clock = clock  # sim seconds
        self.dt = dt
        self.events = events
        self.on_crash = on_crash
        self.log: list[Event] = []  # every change this controller reported, in order
        self._timeline = [self._named(i, c) for i, c in enumerate(schedule.timeline(dt))] if schedule else []
        self._next = 0
        self._reached = -math.inf  # the latest sim time whose scheduled commands were applied (advance)
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
        await self.bus.declare_queryable(self.keys.fault_answers(self.bus.identity), self._on_query)
        await self.bus.subscribe(self.keys.faults, self._on_put)

    # -- commands ------------------------------------------------------------------------------------------------------
    def handle(self, command: FaultCommand, at: float | None = None) -> FaultReply | None:
        """Apply one command to every layer of this process; never raises. ``at``: the sim time it takes effect
        (a scheduled command's own time, so every process starts the fault at the same instant); default now.
        A command with ``at_tick`` joins this process's timeline and is applied at that tick's start.
        None: the command is not this process's to judge (it gives no verdict)."""
        with self.lock:
            if not self._concerns(command):
                return None
            if command.at_tick is not None and at is None:
                return self._schedule(command)
            return self._handle(command, at)

    def _concerns(self, command: FaultCommand) -> bool:
        """Whether this process carries out (part of) ``command``, so that its answer is a verdict."""
        if command.op == "set" and command.spec is not None:
            spec = command.spec
            crash_here = spec.crash is not None and self.on_crash is not None
            network_here = _network_part(spec) and bool(self.layers)
            rate_here = spec.rate is not None and (self.on_rate is not None or (self.events and bool(self.layers)))
            if spec.crash is not None and not crash_here and spec.id is not None:
                self._crash_ids_elsewhere.add(spec.id)
            return crash_here or network_here or rate_here
        if command.op == "reset" and command.fault_id is not None:
            fid = command.fault_id
            if any(fid == s.id for s in self.crashes) or any(fid == s.id for s, _ in self.rates):
                return True
            if not self.layers:
                return False  # a network fault: the processes with layers answer
            held = any(fid in {s.id for s in layer.active()} for layer in self.layers)
            return held or fid not in self._crash_ids_elsewhere
        return True

    def _fleet_error(self, spec: FaultSpec) -> str | None:
        """The field naming a robot that is not in this run, if any."""
        if self.fleet is None:
            return None
        named = [("scope.agents", spec.scope.agents or [])]
        if spec.partition is not None:
            named += [("partition.from_agents", spec.partition.from_agents),
                      ("partition.to_agents", spec.partition.to_agents)]
        if spec.crash is not None and spec.crash.agent is not None:
            named.append(("crash.agent", [spec.crash.agent]))
        for field, refs in named:
            for ref in refs:
                if isinstance(ref, int) and not 0 <= ref < self.fleet:
                    return (f"{field}: agent {ref} is not in this run (robot ids 0..{self.fleet - 1}; "
                            f"or a service: sim, monitor)")
        return None

    def _schedule(self, command: FaultCommand) -> FaultReply:
        """Put a runtime command with ``at_tick`` into the timeline, as if it had been in the schedule file. Only a
        tick this process has not reached yet is accepted: one it has reached could no longer start at that tick's
        boundary here while it would elsewhere."""
        source = self.bus.identity
        at = command.at_tick * self.dt
        if at <= self._reached + 1e-9:
            reached = math.floor(self._reached / self.dt + 1e-9)
            return FaultReply(ok=False, error=f"at_tick: tick {command.at_tick} is not in this process's future (it "
                              f"has reached tick {reached}); give a later tick", active=self._active(), source=source)
        timed = command.model_copy(update={"at_tick": None})
        if timed.op == "set" and timed.spec is not None and timed.spec.id is None:
            # the same id in every process (hence the same seeded streams), whatever else each one has seen
            timed = timed.model_copy(update={"spec": timed.spec.model_copy(update={"id": f"tick{command.at_tick}"})})
        if timed.op == "set" and timed.spec is not None:
            error = self._fleet_error(timed.spec)
            if error:
                return FaultReply(ok=False, error=error, active=self._active(), source=source)
        index = len(self._timeline)
        while index > self._next and self._timeline[index - 1][0] > at + 1e-9:
            index -= 1  # after every command due at the same time: arrival order, like a schedule file's order
        self._timeline.insert(index, (at, timed))
        return FaultReply(ok=True, active=self._active(), source=source)

    def _handle(self, command: FaultCommand, at: float | None) -> FaultReply:
        source = self.bus.identity
        try:
            if command.op == "reset":
                if command.fault_id is None:
                    healed = [fid for layer in self.layers for fid in layer.reset(at=at)]
                    for fid in dict.fromkeys(healed):
                        self._event("fault.reset", fid, None, at)
                    for crash in self.crashes:
                        self._event("fault.reset", crash.id or "crash", None, at)
                    self.crashes.clear()
                    for rate, _ in self.rates:
                        self._event("fault.reset", rate.id or "rate", None, at)
                    self.rates.clear()
                    if self.on_rate_reset is not None:
                        self.on_rate_reset(None, at)
                    if self.on_crash_reset is not None:
                        self.on_crash_reset(None)
                    return FaultReply(ok=True, active=[], source=source)
                fid = command.fault_id
                crash_held = any(fid == s.id for s in self.crashes)
                layer_held = any(fid in {s.id for s in layer.active()} for layer in self.layers)
                rate_held = any(fid == s.id for s, _ in self._rates_in_force())
                if rate_held:
                    self.rates = [(s, t0) for s, t0 in self.rates if s.id != fid]
                    if self.on_rate_reset is not None:
                        self.on_rate_reset(fid, at)
                    if not crash_held and not layer_held:
                        self._event("fault.reset", fid, None, at)
                        return FaultReply(ok=True, active=self._active(), source=source)
                if not crash_held and not layer_held:
                    return FaultReply(ok=False, error=f"fault_id: no active fault {fid!r}",
                                      active=self._active(), source=source)
                if crash_held:
                    self.crashes = [s for s in self.crashes if s.id != fid]
                    if self.on_crash_reset is not None:
                        self.on_crash_reset(fid)
                for layer in self.layers:
                    layer.reset(fid, at=at)
                self._event("fault.reset", fid, None, at)
            elif command.op == "set":
                spec = command.spec
                assert spec is not None  # FaultCommand guarantees it
                error = self._fleet_error(spec)
                if error:
                    return FaultReply(ok=False, error=error, active=self._active(), source=source)
                if spec.crash is not None and self.on_crash is not None:
                    if spec.id is None:  # the planner and this list name it alike (reset --id, retirement)
                        spec = spec.model_copy(update={"id": f"crash-{len(self.log) + 1}"})
                    error = self.on_crash(spec)
                    if error:
                        return FaultReply(ok=False, error=error if error.startswith("crash") else f"crash: {error}",
                                          active=self._active(), source=source)
                    self.crashes.append(spec)
                    self._event("fault.crash_planned", spec.id or "crash", spec, at)
                if spec.rate is not None:
                    return self._set_rate(spec, at)
                if not _network_part(spec) or not self.layers:
                    return FaultReply(ok=True, active=self._active(), source=source)
                if spec.crash is not None:  # carried out by the supervisor; the network part is this process's
                    spec = spec.model_copy(update={"crash": None})
                if spec.id is None:  # one id for the fault in every layer (and in the event log)
                    when = self.clock() if at is None else at
                    spec = spec.model_copy(update={"id": f"fault-{len(self.log) + 1}-{round(when * 1000)}"})
                for layer in self.layers:
                    layer.set(spec, at=at)
                self._event("fault.set", spec.id or "", spec, at)
        except (ValueError, ValidationError) as exc:  # (a ValidationError is a ValueError: worded for the operator)
            error = explain(exc) if isinstance(exc, ValidationError) else str(exc)
            return FaultReply(ok=False, error=error, active=self._active(), source=source)
        return FaultReply(ok=True, active=self._active(), source=source)

    def _set_rate(self, spec: FaultSpec, at: float | None) -> FaultReply:
        """An airtime fault: the air applies it, the run record's owner records it (or refuses it: no air)."""
        source = self.bus.identity
        if self.on_rate is None and not self.air_run:
            return FaultReply(ok=False, error="rate: this run has no shared air (its network profile limits no access "
                              "point's airtime: --network congested or a profile with ap_rate)",
                              active=self._active(), source=source)
        when = self.clock() if at is None else at
        if spec.id is None:
            spec = spec.model_copy(update={"id": f"fault-{len(self.log) + len(self.rates) + 1}-{round(when * 1000)}"})
        if self.on_rate is not None:
            error = self.on_rate(spec, at)
            if error:
                return FaultReply(ok=False, error=error, active=self._active(), source=source)
        self.rates = [(s, t0) for s, t0 in self.rates if s.id != spec.id] + [(spec, when)]
        self._event("fault.set", spec.id or "", spec, at)
        return FaultReply(ok=True, active=self._active(), source=source)

    def _rates_in_force(self) -> list[tuple[FaultSpec, float]]:
        now = self.clock()
        return [(s, t0) for s, t0 in self.rates if s.duration is None or now < t0 + s.duration]

    def retire_crash(self, fault_id: str) -> None:
        """A one-shot crash was carried out: it is no longer an active fault (its record is the agent.crash event)."""
        with self.lock:
            self.crashes = [s for s in self.crashes if s.id != fault_id]

    def _active(self) -> list[FaultSpec]:
        # a process lists what it carries out: its network faults, and (the supervisor) its crash faults
        return ((self.layers[0].active() if self.layers else []) + list(self.crashes)
                + [s for s, _ in self._rates_in_force()])

    def advance(self, now: float) -> list[FaultReply]:
        """Apply the scheduled commands due by sim time ``now`` (call at each tick start, or register on a
        VirtualTime's ``on_advance``), each at its own time."""
        out = []
        with self.lock:
            self._reached = max(self._reached, now)
            while self._next < len(self._timeline) and self._timeline[self._next][0] <= now + 1e-9:
                reply = self._scheduled(self._next)
                self._next += 1
                if reply is not None:
                    out.append(reply)
        return out

    @staticmethod
    def _named(index: int, timed: tuple[float, FaultCommand]) -> tuple[float, FaultCommand]:
        at, command = timed
        if command.op == "set" and command.spec is not None and command.spec.id is None:
            # an id from the schedule itself (not from this process's log or clock): the same fault, hence the same
            # seeded streams, in every process
            command = command.model_copy(update={"spec": command.spec.model_copy(update={"id": f"at{index}"})})
        return at, command

    def _scheduled(self, index: int) -> FaultReply | None:
        at, command = self._timeline[index]
        if not self._concerns(command):
            return None
        reply = self._handle(command, at)
        if not reply.ok:
            log.warning("fault schedule at %.3f s: %s", at, reply.error)
        return reply

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
        if reply is not None:  # no verdict from a process the command does not concern
            query.reply(self.keys.fault_answers(self.bus.identity), reply)

    def _on_put(self, sample: Sample) -> None:
        command = self._decode(sample.payload)
        if isinstance(command, str):
            log.warning("ctl/faults from %r: %s", sample.sender, command)
            return
        reply = self.handle(command)
        if reply is not None and not reply.ok:
            log.warning("ctl/faults %s from %r rejected: %s", command.op, sample.sender, reply.error)

    def _event(self, kind: str, fault_id: str, spec: FaultSpec | None, at: float | None = None) -> None:
        now = self.clock() if at is None else at
        details: dict = {"fault_id": fault_id}
        if spec is not None:
            details["spec"] = spec.model_dump(mode="json", exclude_none=True)
        event = Event(kind=kind, source=self.bus.identity, t=max(0, math.floor(now / self.dt + 1e-9)),
                      sim_time=now, wall_time=time.time(), details=details)
        self.log.append(event)
        if self._held_events is not None:
            self._held_events.append(event)
        elif self.events:
            self._publish(event)

    def note(self, kind: str, at: float, **details) -> None:
        """An event of the network itself (a hand-over) in the run record, at sim time ``at``, if this controller
        reports events."""
        if not self.events:
            return
        event = Event(kind=kind, source=self.bus.identity, t=max(0, math.floor(at / self.dt + 1e-9)),
                      sim_time=at, wall_time=time.time(), details=details)
        self.log.append(event)
        if self._held_events is not None:
            self._held_events.append(event)
        else:
            self._publish(event)

    def publish_held(self) -> None:
        """The run has started (the monitor listens): publish the events kept so far, and the next ones at once."""
        held, self._held_events = self._held_events, None
        for event in held or ():
            self._publish(event)

    def _publish(self, event: Event) -> None:
        if self.bus.closed:
            return
        try:
            self.bus.put(self.keys.event(self.bus.identity), event)
        except Exception:  # the record loses one event; the run goes on
            log.exception("could not publish %s", event.kind)
