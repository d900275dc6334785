"""Application-layer fault injection for the bus (docs/faults.md): loss (Bernoulli, Gilbert–Elliott), latency
(fixed, jitter, uniform/normal/pareto, correlation), duplicate, reorder and directional partitions, scoped by key
expression and agent ids, with optional auto-heal, and a seeded RNG per (fault, link) so a run is reproducible.

Pure core: :meth:`FaultLayer.fate` decides what happens to one message on one link and returns the delivery delays
(``[]`` = dropped, ``[d]`` = delivered after d seconds, ``[d1, d2]`` = duplicated). The thin shell
(:meth:`FaultLayer.on_deliver`, the bus's ingress seam) delivers at once or hands delayed copies to a scheduler:
``loop.call_later`` by default (wall time); a virtual-time run passes its own scheduler that releases messages at
the first phase boundary at or after their due sim time.

Faults are applied at ingress, where both ends of the link are known (the sender from the sample header, the
receiver is the bus that owns the layer), so each receiver keeps its own per-link random streams.
Semantics follow ``tc netem``:

* correlation c (percent): the uniform draw u is mixed with the previous one, u' = (1−c)·u + c·u_prev (the formula
  Chaos Mesh documents), then used for the decision or the inverse CDF;
* Gilbert–Elliott: per message, lose with probability 1−k in the good state and 1−h in the bad state, then move
  good→bad with p and bad→good with r (simple Gilbert: 1−h = 1, 1−k = 0, so a burst lasts 1/r messages on average);
* latency distributions with mean ``delay`` and spread ``jitter``: uniform on [delay−jitter, delay+jitter]; normal
  N(delay, jitter) truncated at 0; pareto with mean ``delay`` and standard deviation ``jitter`` (shape
  a = 1 + sqrt(1 + delay²/jitter²), scale delay·(a−1)/a);
* reorder P gap G: every G-th message of a link is a candidate, and with probability P it skips the delay.
"""

from __future__ import annotations

import asyncio
import itertools
import random
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from schemas.faults import FaultSpec, Loss
from schemas.keys import ONBOARD, RunKeys, matches, parse_agent_id
from schemas.messages import AirVerdicts, FaultCommand, FaultReply
from services.bus.base import Bus, Sample
from services.faults.air import VerdictBook, kind_of
from services.faults.distributions import latency_quantile
from services.faults.linkstats import LinkMeter
from services.faults.network import Fate
from services.faults.vtime import EPS as _VT_EPS, VirtualTime

if TYPE_CHECKING:
    from services.faults.network import HandoverEvent, NetworkModel

# A sample stamped later than this (seconds) carries a wall clock (time.time()), not a sim time: a process in wall time
# or a tool (the faults CLI, the supervisor). Sim times stay far below it (1e8 s is three years of robot time).
WALL_STAMP = 1e8
# Virtual time keeps healed fault windows this many steps, to judge stragglers sent while they were active.
HISTORY_STEPS = 64
# the most keys a table by key holds (the layer's kinds of key, a fault's scope matches): a run has a few dozen keys,
# and keys nobody planned (a fuzzer's) empty the table rather than grow it
KEY_TABLE_MAX = 4096


def is_wall_stamp(sent_at: float) -> bool:
    return sent_at > WALL_STAMP


# ---------------------------------------------------------------------------------------------------------------
# per (fault, link) state
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class _Link:
    rng: random.Random
    last: dict[str, float] = field(default_factory=dict)  # previous uniform draw per effect (correlation)
    bad: bool = False  # Gilbert–Elliott state
    count: int = 0  # messages seen (reorder gap)

    def uniform(self, effect: str, correlation_pct: float) -> float:
        u = self.rng.random()
        if correlation_pct > 0.0:
            c = correlation_pct / 100.0
            prev = self.last.get(effect, u)
            u = (1.0 - c) * u + c * prev
        self.last[effect] = u
        return u


@dataclass
class ActiveFault:
    spec: FaultSpec
    fault_id: str
    started: float
    expires: float | None
    serial: int = 0  # one per activation: a re-set fault gets fresh streams, its old window keeps its own

    def window_has(self, at: float) -> bool:
        """Was this fault active at sim time ``at`` (virtual time: faults are judged at a message's send time)?"""
        return self.started <= at + _VT_EPS and (self.expires is None or at < self.expires - _VT_EPS)

    # whether the scope's key expression matches a key, by key: every copy of every message asks (KEY_TABLE_MAX)
    _matched: dict[str, bool] = field(default_factory=dict, repr=False, compare=False)

    def applies(self, rel_key: str, sender: object, receiver: object) -> bool:
        scope = self.spec.scope
        matched = self._matched.get(rel_key)
        if matched is None:
            if len(self._matched) >= KEY_TABLE_MAX:
                self._matched.clear()
            matched = self._matched[rel_key] = matches(scope.key_expr, rel_key)
        if not matched:
            return False
        if scope.agents is not None and sender not in scope.agents and receiver not in scope.agents:
            return False
        return True


@dataclass
class FaultStats:
    seen: int = 0
    dropped: int = 0
    duplicated: int = 0
    delayed: int = 0
    partitioned: int = 0


class FaultLayer:
    """The fault layer of one receiver. Install with ``bus.set_interposer(FaultLayer(run, ...))``.

    ``clock`` gives the current time in the unit faults are expressed in (sim seconds for virtual time, wall seconds
    otherwise); it decides when a fault with a ``duration`` heals. ``schedule(delay, fn)`` runs ``fn`` after
    ``delay`` of that time; default: the running loop's ``call_later`` (wall time).

    Virtual time across processes (docs/faults.md): a message is judged by the faults active at its *send* time
    (``sample.sent_at``), not at the moment it happens to arrive, and ``before_fate(sent_at)`` lets the owner bring
    its schedule up to that time first; healed windows are kept (``HISTORY_STEPS``) for stragglers; ``events/**``
    (presence handshake, run record: wall-paced, before any boundary) is not faulted. ``per_key`` gives every
    (fault, sender, receiver, key) its own stream, so the order in which a receiver's subscriptions (separate
    transport threads) see two keys of one sender never shifts a stream. ``lock`` serializes the decision, the
    hook and the hold (one per process, shared with :meth:`VirtualTime.advance` by the FaultRuntime).
    """

    def __init__(self, run: str, *, base_seed: int = 0, clock: Callable[[], float] | None = None,
                 schedule: Callable[[float, Callable[[], None]], object] | None = None,
                 on_change: Callable[[str, ActiveFault], None] | None = None,
                 loop: asyncio.AbstractEventLoop | None = None, vtime: VirtualTime | None = None,
                 meter: LinkMeter | None = None, per_key: bool = False, lock: threading.RLock | None = None):
        self.keys = RunKeys(run)
        self.base_seed = int(base_seed)
        self.per_key = per_key
        # the receiver's agent id (an int for a robot) when its bus identity is a process name like "agent-3"
        self.receiver: int | str | None = None
        self.lock = lock or threading.RLock()
        self.before_fate: Callable[[float], None] | None = None
        self._history: list[ActiveFault] = []  # virtual time: healed/replaced windows, judged by send time
        self._serials = itertools.count(1)
        # virtual time: faults heal, messages wait and lateness is judged in sim seconds (see vtime.py)
        self.vtime = vtime
        self.clock = clock or (vtime.now if vtime is not None else time.monotonic)
        self.schedule = schedule
        self.meter = meter  # measures what this receiver actually got (linkstats.py)
        self._metered_fns: dict[tuple[Callable[[Sample], None], str], Callable[[Sample], None]] = {}
        # called with (sample, fate) the moment a sample physically arrives, before it is dropped or held: a lockstep
        # receiver counts arrivals here, so it never waits for a message the fault layer already decided to lose
        self.on_fate: Callable[[Sample, list[float]], None] | None = None
        if vtime is not None:
            vtime.on_advance(lambda _now: self._expire())  # auto-heal is logged at the boundary it happens
        self.on_change = on_change  # ("set" | "healed" | "reset", fault): for events in the run record
        self.loop = loop  # needed when deliveries arrive on a transport thread (inline subscriptions)
        self.stats = FaultStats()
        self._faults: dict[str, ActiveFault] = {}
        self._links: dict[tuple, _Link] = {}
        self._kinds: dict[str, tuple[str | None, bool | None]] = {}  # see _kind_of
        self._auto_ids = itertools.count(1)
        # the run's network profile (services/faults/network.py), judged before the fault specs in virtual time; it
        # learns where the robots are from every Tick of the sim this layer sees (sent or received)
        self.network: NetworkModel | None = None
        # whether the network's delays (legs' latency, queueing, a delayed hand-over) count, or only its losses: the
        # services' fault runtimes turn it off while their Tick is both the fleet broadcast and the tick's
        # synchronisation (any latency on it makes the agent skip the tick, so a profile's milliseconds of Wi-Fi
        # latency would silence every robot); the lab, whose fleet broadcast is its own message, counts them
        self.network_latency = True
        self.on_handover: Callable[[HandoverEvent], None] | None = None
        # the fleet broadcast reaches every robot physically whatever its fate: it says where the robots are
        self._tick_key = self.keys.fleet
        # a profile with shared capacity: the air process judges the radio (services/faults/air.py); this receiver
        # takes its verdicts and holds a radio message until its verdict is here
        self.air: VerdictBook | None = None
        self.air_refused = 0  # verdict messages refused: not from the air, or not decodable

    # -- control -----------------------------------------------------------------------------------------------
    def set(self, spec: FaultSpec, at: float | None = None) -> str:
        """Activate ``spec`` (replacing an active fault with the same id) from sim time ``at`` (default: now);
        returns its id."""
        if spec.crash is not None and all(x is None for x in (spec.latency, spec.loss, spec.duplicate, spec.reorder,
                                                                 spec.partition)):
            raise ValueError("crash faults are carried out by the supervisor, not by the bus fault layer")
        fault_id = spec.id or f"fault-{next(self._auto_ids)}"
        with self.lock:
            now = self.clock() if at is None else at
            fault = ActiveFault(spec, fault_id, now, None if spec.duration is None else now + spec.duration,
                                next(self._serials))
            old = self._faults.pop(fault_id, None)
            if old is not None:
                self._retire(old, now)
            self._faults[fault_id] = fault
        if self.on_change:
            self.on_change("set", fault)
        return fault_id

    def reset(self, fault_id: str | None = None, at: float | None = None) -> list[str]:
        """Heal one fault, or all of them (at sim time ``at``, default now); returns the ids removed. Always
        succeeds."""
        with self.lock:
            now = self.clock() if at is None else at
            ids = list(self._faults) if fault_id is None else [fault_id] if fault_id in self._faults else []
            removed = [self._faults.pop(fid) for fid in ids]
            for fault in removed:
                self._retire(fault, now)
        for fault in removed:
            if self.on_change:
                self.on_change("reset", fault)
        return ids

    def _retire(self, fault: ActiveFault, now: float) -> None:
        """A fault leaves the active set. Virtual time keeps its window (ending now) for messages sent during it;
        wall time forgets it and its streams."""
        if self.vtime is not None:
            fault.expires = now if fault.expires is None else min(fault.expires, now)
            self._history.append(fault)
            horizon = self.clock() - HISTORY_STEPS * self.vtime.dt
            old = [f for f in self._history if f.expires is not None and f.expires < horizon]
            if old:
                gone = {f.serial for f in old}
                self._history = [f for f in self._history if f.serial not in gone]
                self._links = {k: v for k, v in self._links.items() if k[0] not in gone}
        else:
            self._links = {k: v for k, v in self._links.items() if k[0] != fault.serial}

    def apply(self, command: FaultCommand) -> FaultReply:
        """Carry out a ``ctl/faults`` command; a rejected spec comes back as ``ok=False`` with the reason."""
        try:
            if command.op == "set":
                assert command.spec is not None  # FaultCommand's validator guarantees it
                self.set(command.spec)
            elif command.op == "reset":
                if command.fault_id is not None and command.fault_id not in self._faults:
                    return FaultReply(ok=False, error=f"no active fault {command.fault_id!r}", active=self.active())
                self.reset(command.fault_id)
        except ValueError as exc:
            return FaultReply(ok=False, error=str(exc), active=self.active())
        return FaultReply(ok=True, active=self.active())

    def active(self) -> list[FaultSpec]:
        with self.lock:
            self._expire()
            return [f.spec.model_copy(update={"id": f.fault_id}) for f in self._faults.values()]

    def _expire(self) -> None:
        now = self.clock()
        for fid, fault in list(self._faults.items()):
            if fault.expires is not None and now >= fault.expires - _VT_EPS * (self.vtime is not None):
                del self._faults[fid]
                self._retire(fault, now)
                if self.on_change:
                    self.on_change("healed", fault)

    # -- pure decision -----------------------------------------------------------------------------------------
    def _link(self, fault: ActiveFault, sender: object, receiver: object, rel: str) -> _Link:
        key = (fault.serial, sender, receiver, rel if self.per_key else None)
        link = self._links.get(key)
        if link is None:
            seed = fault.spec.seed if fault.spec.seed is not None else self.base_seed
            name = f"{seed}|{fault.fault_id}|{sender}|{receiver}" + (f"|{rel}" if self.per_key else "")
            link = self._links[key] = _Link(random.Random(name))
        return link

    def _kind_of(self, key: str) -> tuple[str | None, bool | None]:
        """What the layer does with messages on ``key``, kept per key (a few dozen keys carry every message of a
        run): (its key relative to the run, or None when it is never faulted; whether it is radio traffic, or None
        when it is faulted only in wall time)."""
        kinds = self._kinds
        if len(kinds) >= KEY_TABLE_MAX:
            kinds.clear()
        try:
            chunks = self.keys.relative(key)
        except ValueError:
            kind = None, None  # not this run's traffic: untouched
        else:
            rel = "/".join(chunks)
            if chunks[0] in ("ctl", "air"):
                # control traffic (fault reset, stop) is never faulted: `reset` always works; the air's verdicts and
                # announcements are the radio's own bookkeeping, not radio traffic
                kind = None, None
            elif chunks[0] == "events":
                kind = rel, None  # virtual time: the presence handshake runs before any boundary could release it
            elif len(chunks) == 3 and chunks[0] == "agent" and chunks[2] in ("skip", "ack"):
                kind = None, None  # acks and skips let the sim advance time (synchronisation): never faulted
            elif chunks[0] == "sim" and chunks[1:] == ["resolve"]:
                kind = None, None  # the picker's decision point is synchronisation too
            else:
                kind = rel, not matches(ONBOARD, rel)  # sensing is not radio
        kinds[key] = kind
        return kind

    def fate(self, key: str, sender: object, receiver: object, at: float | None = None, *,
             msg: object = None, size: int = 0, radio: Fate | None = None) -> list[float]:
        """Delivery delays for one message on link sender → receiver: [] dropped, [d] once, [d1, d2] duplicated.

        ``at`` (virtual time): the message's send time; the faults active then decide, healed ones included.
        ``msg`` (its identity, e.g. (sender, seq); the key is added) and ``size`` (bytes) feed the network model;
        ``radio``: the air's verdict on the message, which then stands for the network model's."""
        if self._faults:
            self._expire()
        self.stats.seen += 1
        if not self._faults and (at is None or not self._history) and self.network is None:
            return [0.0]
        rel, radio_traffic = self._kinds.get(key) or self._kind_of(key)
        if rel is None or (at is not None and radio_traffic is None):
            return [0.0]
        delay = 0.0
        if self.network is not None and at is not None and radio_traffic:
            # the radio legs first (the robots' Wi-Fi), then the fault specs on top, as netem on a real interface
            if radio is not None:  # the air's verdict, counted in this process's model as if it had judged it
                net = radio
                stats = self.network.stats
                stats.seen += 1
                if radio.delivered_at is None:
                    cause = radio.cause or "loss"
                    stats.lost[cause] = stats.lost.get(cause, 0) + 1
                else:
                    stats.delivered += 1
            else:
                net = self.network.fate(at, sender, receiver, (msg, rel), size=size)
            if net.delivered_at is None:
                self.stats.dropped += 1
                return []
            delay = net.delivered_at - at if self.network_latency else 0.0
        return self._apply(self._active_at(at), rel, sender, receiver, delay)

    def _active_at(self, at: float | None) -> list[ActiveFault]:
        """The faults that judge a message sent at ``at`` (None: the active ones, now), in the order they were set."""
        if at is None:
            return list(self._faults.values())
        if not self._history and not self._faults:
            return []
        return sorted((f for f in (*self._history, *self._faults.values()) if f.window_has(at)),
                      key=lambda f: f.serial)

    def _apply(self, faults: list[ActiveFault], rel: str, sender: object, receiver: object,
               delay: float) -> list[float]:
        """The fault specs' verdict on one message the radio let through with ``delay``: [] dropped, else one delay
        per copy."""
        copies = 1
        for fault in faults:
            if not fault.applies(rel, sender, receiver):
                continue
            spec = fault.spec
            if spec.partition is not None and spec.partition.cuts(sender, receiver):
                self.stats.partitioned += 1
                self.stats.dropped += 1
                return []
            link = self._link(fault, sender, receiver, rel)
            link.count += 1
            if spec.loss is not None and _lost(spec.loss, link):
                self.stats.dropped += 1
                return []
            if spec.latency is not None:
                skip = False
                if spec.reorder is not None and link.count % spec.reorder.gap == 0:
                    skip = link.uniform("reorder", spec.reorder.correlation) < spec.reorder.percent / 100.0
                if not skip:
                    u = link.uniform("latency", spec.latency.correlation)
                    delay += latency_quantile(spec.latency, u)
            if spec.duplicate is not None:
                if link.uniform("duplicate", spec.duplicate.correlation) < spec.duplicate.percent / 100.0:
                    copies = 2
        if delay > 0.0:
            self.stats.delayed += 1
        if copies == 2:
            self.stats.duplicated += 1
        return [delay] * copies

    def fate_copies(self, key: str, sender: object, receivers: Sequence[object], at: float, *, msg: object = None,
                    size: int = 0) -> list[list[float]]:
        """:meth:`fate` of one publication's copy to each of ``receivers`` (virtual time ``at``), in that order: the
        same verdicts and counts as one call per copy, with the key, the message's identity and the faults in force
        read once for every copy (a fleet broadcast has a copy per robot)."""
        if self._faults:
            self._expire()  # (the clock stands still while one publication is judged: once for every copy)
        rel, radio_traffic = self._kinds.get(key) or self._kind_of(key)
        if (at is None or rel is None or radio_traffic is None
                or (self.network is None and not self._faults and not self._history)):
            return [self.fate(key, sender, receiver, at, msg=msg, size=size) for receiver in receivers]
        # the radio's verdicts first, then the fault specs' on top, as fate() judges each copy: the network model
        # and the faults' link streams are apart, so judging every copy's radio legs first changes neither
        nets = (self.network.fate_copies(at, sender, receivers, (msg, rel), size=size)
                if self.network is not None and radio_traffic else None)
        faults = self._active_at(at)
        stats, latency = self.stats, self.network_latency
        out: list[list[float]] = []
        for i, receiver in enumerate(receivers):
            stats.seen += 1
            delay = 0.0
            if nets is not None:
                net = nets[i]
                if net.delivered_at is None:
                    stats.dropped += 1
                    out.append([])
                    continue
                delay = net.delivered_at - at if latency else 0.0
            out.append(self._apply(faults, rel, sender, receiver, delay))
        return out

    # -- the bus seam ------------------------------------------------------------------------------------------
    def on_publish(self, sample: Sample, send: Callable[[Sample], None]) -> None:
        if self.network is not None and sample.key == self._tick_key:
            with self.lock:
                self._observe_tick(sample)  # the sim's own Tick: its network model follows the robots too
        send(sample)  # faults are applied per link at the receiver

    def _observe_tick(self, sample: Sample) -> None:
        """Feed the robots' cells of a Tick of the sim to the network model (every process sees every Tick
        physically, whatever its fate, so every process's model follows the same trajectories)."""
        from schemas.tick import decode_tick

        assert self.network is not None and self.vtime is not None
        try:
            tick = decode_tick(sample.payload)
        except ValueError:
            return  # the handler rejects it
        cells = zip(tick.row("x").tolist(), tick.row("y").tolist())
        for event in self.network.observe_tick(tick.t, self.vtime.dt, list(cells)):
            if self.on_handover is not None:
                self.on_handover(event)

    def sent_at(self, sample: Sample) -> float:
        """A sample's send time in this layer's time: its stamp, or now for a wall-stamped sample in virtual time."""
        vt = self.vtime
        return sample.sent_at if vt is None or not is_wall_stamp(sample.sent_at) else vt.now()

    def delivers_now(self, sample: Sample, fate: list[float]) -> bool:
        """Will ``on_deliver`` hand this sample over at once (rather than drop it or hold it for later)?"""
        if not fate:
            return False
        delay = min(fate)
        vt = self.vtime
        return delay <= 0.0 or (vt is not None and self.sent_at(sample) + delay <= vt.now() + _VT_EPS)

    def on_deliver(self, sample: Sample, receiver: str, deliver: Callable[[Sample], None]) -> None:
        with self.lock:
            self._on_deliver(sample, receiver, deliver)

    def _sender(self, sample: Sample) -> object:
        # the link's sender off the key (every agent-sent key starts agent/<id>/, keys.py), whatever the publishing
        # process calls itself ("agent-3", a container's host name); else the publisher's identity
        try:
            who = self.keys.sender_of(sample.key)
        except ValueError:
            who = None
        if who is not None:
            return who
        return parse_agent_id(sample.sender) if sample.sender else ""

    def on_verdicts(self, sample: Sample) -> None:
        """The air's verdicts on messages to this receiver (``air/verdict/<receiver>``): each releases the message
        if it came first."""
        if self.air is None or sample.sender != "air":  # (the access control lets only the air publish there)
            self.air_refused += 1
            return
        try:
            msg = sample.decode(AirVerdicts)
        except ValueError:
            self.air_refused += 1
            return
        with self.lock:
            for pub, key, seq, at, cause in zip(msg.publishers, msg.keys, msg.seqs, msg.at, msg.causes):
                identity = ("sim" if pub < 0 else pub, key, seq)
                for parked, receiver, deliver in self.air.verdict(identity, Fate(at, cause)):
                    self._on_deliver(parked, receiver, deliver)

    def _on_deliver(self, sample: Sample, receiver: str, deliver: Callable[[Sample], None]) -> None:
        sender = self._sender(sample)
        rcv = self.receiver if self.receiver is not None else parse_agent_id(receiver)
        vt = self.vtime
        at = None
        radio = None
        if self.air is not None and vt is not None:
            rel = sample.key[len(self.keys.prefix) + 1:] if sample.key.startswith(self.keys.prefix + "/") else ""
            if rel and kind_of(rel) and (isinstance(rcv, int) or rcv == "sim"):
                identity = (sender, rel, sample.seq)
                radio = self.air.take(identity)
                if radio is None:  # the air has not judged it yet: it has not arrived
                    self.air.park(identity, (sample, receiver, deliver))
                    return
        if vt is not None:
            at = self.sent_at(sample)
            if self.before_fate is not None:
                self.before_fate(at)  # the schedule up to the send time: a fault starts at its time everywhere
        if self.network is not None and sample.key == self._tick_key and sample.sender == "sim":
            self._observe_tick(sample)  # only the sim's own Ticks say where the robots are (not a stray publisher's)
        fate = self.fate(sample.key, sender, rcv, at, msg=(sender, sample.seq), size=len(sample.payload), radio=radio)
        if self.on_fate is not None:
            self.on_fate(sample, fate)
        if self.meter is not None:
            deliver = self._metered(deliver, receiver)
        for copy, delay in enumerate(fate):
            if delay <= 0.0:  # no latency: within its own phase
                deliver(sample if at is None else Sample(sample.key, sample.payload, sample.sender, sample.seq,
                                                         sample.sent_at, at))
            elif vt is not None:
                # due at send time + latency, released at the first boundary at or after it; the tie order is the
                # message's identity, not its arrival order (deterministic across processes). The receiver orders
                # by ``due`` (continuous), the boundary is only when it gets to see it.
                # the default binds this copy's stamped sample now, as the callback runs later
                vt.hold(at + delay, lambda s=sample._replace(due=at + delay): deliver(s),  # noqa: B008
                        order=(sample.sender, sample.key, sample.seq, copy),
                        deadline=vt.deadline_of(at))
            elif self.schedule is not None:
                self.schedule(delay, lambda s=sample: deliver(s))
            else:
                loop = self.loop or asyncio.get_running_loop()
                loop.call_soon_threadsafe(loop.call_later, delay, deliver, sample)

    def _metered(self, deliver: Callable[[Sample], None], receiver: str) -> Callable[[Sample], None]:
        """``deliver`` with this layer's meter in front (one per subscription and receiver, made once)."""
        fn = self._metered_fns.get((deliver, receiver))
        if fn is None:
            fn = self._metered_fns[(deliver, receiver)] = self._metering(deliver)
        return fn

    def _metering(self, deliver: Callable[[Sample], None]) -> Callable[[Sample], None]:
        meter, vt = self.meter, self.vtime
        assert meter is not None

        def metered(sample: Sample) -> None:
            if vt is not None:
                now, late = vt.now(), vt.is_late(self.sent_at(sample))
            else:
                now, late = time.time(), False
            meter.record(sample.key, sample.sender, sample.seq, sample.sent_at, now, late=late)
            deliver(sample)
        return metered


def install(bus: Bus, layer: FaultLayer) -> FaultLayer:
    """Put ``layer`` on ``bus``'s ingress; in virtual time also stamp the bus's samples with sim time."""
    bus.set_interposer(layer)
    if layer.vtime is not None:
        bus.set_clock(layer.vtime.now)
    return layer


def _lost(loss: Loss, link: _Link) -> bool:
    if loss.model == "bernoulli":
        return link.uniform("loss", loss.correlation) < (loss.percent or 0.0) / 100.0
    p, r, one_minus_h, one_minus_k = loss.gilbert_elliott()
    u = link.rng.random()
    lost = u < (one_minus_h if link.bad else one_minus_k)
    v = link.rng.random()
    link.bad = (v >= r) if link.bad else (v < p)
    return lost
