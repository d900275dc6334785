"""The air service: one process per run through whose judgement every radio message passes when the run's network
profile has shared capacity (rate-limited queues; services/faults/air.py, docs/faults.md).

It receives every radio message of the run (the sim's fleet broadcasts, its refusals, the robots' requests,
replies, commitments and policy messages) and the sim's announcements of what was published at each instant; once
an instant's part is whole it judges it with the run's network model in the medium's order and sends each receiver
the verdicts on its copies (``air/verdict/<receiver>``). Receivers hold a radio message until its verdict is there,
so no decision point acts before the air has judged what it waits for. Like the monitor it answers the sim's
readiness probe: tick 0 waits for it.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time

from schemas import AirPart, AirStats, AirVerdicts, Event, RunKeys, Stop
from schemas.keys import FLEET
from schemas.messages import AIR_CHUNK
from schemas.tick import decode_tick, observation_from_arrays
from services.bus.base import Bus, Sample
from services.faults.air import (
    SIM_PART,
    Ledger,
    Medium,
    Publication,
    Verdict,
    dispatch_size,
    fleet_size,
    kind_of,
    receivers_of,
)
from services.intake import Intake
from services.runconfig import RunConfig

log = logging.getLogger("morph_sim.air")

AIR = "air"
# A part the sim announced and that stays incomplete this long (wall seconds) is judged with what arrived: a robot
# that announced a message it never sent (or one lost to a crash) must not stall the fleet.
PART_TIMEOUT_FACTOR = 1.0
# A robot's message may be stamped up to this many ticks beyond the newest Tick the air saw (a robot acts on tick t
# once the Tick of t has gone out; one tick of slack for the order in which the two reach the air).
AHEAD_TICKS = 2
MAX_OPEN_ANNOUNCEMENTS = 8


class AirService:
    """The medium of one run over ``bus``. ``await run()`` returns when the run ends."""

    def __init__(self, config: RunConfig, bus: Bus):
        from services.faults.network import NetworkModel, load_profile
        from services.world.layout import LayoutConfig, layout_for

        self.config = config
        self.bus = bus
        self.keys = RunKeys(config.run_id)
        self.n = config.n_agents
        self.model = NetworkModel(load_profile(config.network), layout_for(LayoutConfig.named(config.scale)),
                                  seed=config.seed)
        self.ledger = Ledger(Medium(self.model))
        self.ledger.on_part = self._judged
        self.intake = Intake(bus, self.keys, log, AIR)
        # transport threads (one per subscription) share the ledger; the fault controller takes it too
        self.lock = threading.RLock()
        self._stop = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        self._waiting_since: float | None = None
        self._head: tuple[float, int] | None = None  # the oldest announced part not judged yet
        self.verdicts = 0
        self.parts = 0
        self._announcing: dict[tuple[float, int], dict] = {}  # parts announced in several messages, until the last
        self._newest_tick = -1  # the newest Tick seen: a publication stamped far beyond it is refused
        self.faults = None  # its fault controller (airtime faults), mounted by run()

    # -- airtime faults (faults set --rate, a fault schedule's rate specs) --------------------------------------------
    def _rate(self, spec, at: float | None) -> str | None:
        """(Under the lock.) Every access point's airtime becomes the spec's from sim time ``at`` (a scheduled or
        --at-tick command's own time: the same in every run) or, at once, from the newest tick."""
        if not self.model.has_ap_budget:
            return (f"rate: profile {self.config.network!r} gives its access points no airtime budget (ap_rate, "
                    "ap_uplink_rate, ap_downlink_rate) to change")
        start = at if at is not None else max(self._newest_tick, 0) * self.config.dt
        end = None if spec.duration is None else start + spec.duration
        self.model.set_airtime(spec.rate.rate, spec.rate.limit, start, end, spec.id)
        log.info("air: airtime %s B/s (queue %d) from %.3f s%s", spec.rate.rate, spec.rate.limit, start,
                 "" if end is None else f" to {end:.3f} s")
        return None

    def _rate_reset(self, fault_id: str | None, at: float | None) -> None:
        self.model.end_airtime(at if at is not None else max(self._newest_tick, 0) * self.config.dt, fault_id)

    # -- in ---------------------------------------------------------------------------------------------------------
    def _on_tick(self, sample: Sample) -> None:
        """The world record's Tick: where the robots are (from (t+1)·Δ on, as every process's model) and the fleet
        broadcast of tick t, which every robot receives over the radio."""
        if self.keys.sender_of(sample.key) != "sim":
            return
        try:
            arrays = decode_tick(sample.payload)
            obs = observation_from_arrays(arrays)
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return
        dt = self.config.dt
        pub = Publication(obs.t * dt, "sim", FLEET, obs.t, tuple(range(self.n)), fleet_size(obs, dt))
        if self.faults is not None:
            self.faults.advance(obs.t * dt)  # scheduled airtime faults due by this tick's start, at their own times
        with self.lock:
            self._newest_tick = max(self._newest_tick, obs.t)
            self.model.observe_tick(obs.t, dt, obs.cells.tolist())
            out = self.ledger.arrive(pub)
        self._send(out)

    def _on_radio(self, sample: Sample) -> None:
        try:
            rel = self.keys.local(sample.key)
            publisher = self.keys.sender_of(sample.key)
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return
        kind = kind_of(rel)
        if not kind or kind == "fleet" or publisher is None or publisher == AIR:
            return
        try:
            receivers = receivers_of(rel, publisher, self.n)
            if any(isinstance(r, int) and not 0 <= r < self.n for r in receivers) or (
                    isinstance(publisher, int) and not 0 <= publisher < self.n):
                raise ValueError(f"robot id outside 0..{self.n - 1}")
        except ValueError as exc:
            self.intake.refuse(sample.key, exc)
            return
        horizon = (self._newest_tick + AHEAD_TICKS) * self.config.dt
        if sample.sent_at > horizon:  # a forged stamp would keep it waiting for a part that never comes
            self.intake.refuse(sample.key, f"sent at {sample.sent_at:.3f} s, beyond the run's sim time "
                                           f"({horizon:.3f} s at most)")
            return
        size = len(sample.payload) if kind == "policy" else dispatch_size(kind)
        pub = Publication(sample.sent_at, publisher, rel, sample.seq, receivers, size)
        with self.lock:
            out = self.ledger.arrive(pub)
        self._send(out)

    def _on_part(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, AirPart)
        if msg is None:
            return
        if sample.sender != "sim":  # (only the sim's own session may publish there over a secured endpoint)
            self.intake.refuse(sample.key, "an air announcement not from the sim")
            return
        with self.lock:
            counts = self._announcing.setdefault((msg.sent_at, msg.part), {})
            for p, key, c in zip(msg.publishers, msg.keys, msg.counts):
                who = "sim" if p < 0 else p
                counts[(who, key)] = counts.get((who, key), 0) + c
            if msg.more:
                if len(self._announcing) > MAX_OPEN_ANNOUNCEMENTS:  # the sim finishes one part before the next
                    self._announcing.pop(next(iter(self._announcing)))
                return
            del self._announcing[(msg.sent_at, msg.part)]
            self.parts += 1
            out = self.ledger.announce(msg.sent_at, msg.part, counts)
        self._send(out)

    # -- out --------------------------------------------------------------------------------------------------------
    def _judged(self, sent_at: float, part: int) -> None:
        """(Under the lock.) The sim's part of tick t's instant is judged: everything sent before t·Δ and the
        sim's own sends at t·Δ are in the access points' counters, the same in every run of this configuration."""
        if part != SIM_PART:
            return
        t = round(sent_at / self.config.dt)
        self.bus.put(self.keys.air_stats, AirStats(
            t=t, sim_time=sent_at, ap_bytes=list(self.model.ap_bytes), ap_queue=self.model.ap_queue_depths(sent_at),
            ap_drops=list(self.model.ap_drops)))

    def _send(self, verdicts: list[Verdict]) -> None:
        with self.lock:
            # since when the oldest announced part has waited (a part that stays incomplete is forced; other
            # traffic meanwhile does not reset its clock)
            head = (self.ledger.parts[0].sent_at, self.ledger.parts[0].part) if self.ledger.parts else None
            if head != self._head:
                self._head, self._waiting_since = head, (time.monotonic() if head is not None else None)
        if not verdicts:
            return
        by_receiver: dict[int | str, list[Verdict]] = {}
        for v in verdicts:
            by_receiver.setdefault(v.receiver, []).append(v)
        for receiver, all_of in by_receiver.items():
            for i in range(0, len(all_of), AIR_CHUNK):  # a flooded receiver's verdicts in messages of bounded size
                vs = all_of[i:i + AIR_CHUNK]
                self.bus.put(self.keys.air_verdicts(receiver), AirVerdicts(
                    publishers=[-1 if v.publisher == "sim" else v.publisher for v in vs], keys=[v.key for v in vs],
                    seqs=[v.seq for v in vs], at=[v.at for v in vs], causes=[v.cause for v in vs]))
        self.verdicts += len(verdicts)

    def _on_event(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, Event)
        if msg is None or msg.source != "sim" or self.keys.sender_of(sample.key) != "sim":
            return  # (a robot's event naming the sim as its source is not the sim's)
        if msg.kind == "ready.probe":
            self.bus.put(self.keys.event(AIR), Event(kind="ready.ack", source=AIR,
                                                     details={"round": msg.details.get("round", 0)}))
        elif msg.kind == "run.finished":
            self._stop.set()

    def _on_stop(self, sample: Sample) -> None:
        if self.intake.decode(sample, Stop) is not None:
            self._stop.set()

    def stop(self, why: str = "") -> None:
        self._loop.call_soon_threadsafe(self._stop.set)

    async def _watch_stalls(self) -> None:
        """A part the sim announced that stays incomplete past the phase timeout is judged with what arrived."""
        limit = self.config.phase_timeout * PART_TIMEOUT_FACTOR
        while not self._stop.is_set():
            await asyncio.sleep(min(1.0, limit / 4))
            with self.lock:
                since = self._waiting_since
                stuck = since is not None and time.monotonic() - since > limit and self.ledger.parts
                if stuck:
                    missing = self.ledger.waiting_for()
                    log.warning("air: part at %.3f s still misses %s after %.0f s; judged without them",
                                self.ledger.parts[0].sent_at, missing, limit)
                    out = self.ledger.force()
                else:
                    continue
            self._send(out)  # (also starts the next part's clock)

    async def run(self) -> dict:
        k, bus = self.keys, self.bus
        from services.faults.controller import FaultController

        schedule = None
        if self.config.fault_schedule:
            from services.faults.schedule import load_schedule

            schedule = load_schedule(self.config.fault_schedule, self.n)
        self.faults = FaultController(bus, self.config.run_id, [], clock=lambda: max(self._newest_tick, 0) *
                                      self.config.dt, dt=self.config.dt, on_rate=self._rate,
                                      on_rate_reset=self._rate_reset, schedule=schedule, lock=self.lock,
                                      fleet=self.n, air_run=True)
        await self.faults.start()
        self.faults.advance(0.0)  # airtime faults scheduled at time 0
        await bus.subscribe(k.tick, self._on_tick, inline=True)
        for expr in (k.requests, k.replies, k.commits, k._k("agent", "*", "policy", "*"),
                     k._k("sim", "refusal", "*")):
            await bus.subscribe(expr, self._on_radio, inline=True)
        await bus.subscribe(k.air_parts, self._on_part, inline=True)
        await bus.subscribe(k.events, self._on_event)
        await bus.subscribe(k.stop, self._on_stop)
        token = await bus.declare_token(k.alive(AIR))
        watcher = asyncio.get_running_loop().create_task(self._watch_stalls())
        try:
            await self._stop.wait()
        finally:
            watcher.cancel()
        await token.close()
        return {"verdicts": self.verdicts, "parts": self.parts, "judged": self.ledger.judged,
                "strays": self.ledger.strays, "rejected": self.intake.refused,
                "lost": dict(self.model.stats.lost), "ap_drops": list(self.model.ap_drops),
                "messages": self.ledger.medium.messages, "bytes": self.ledger.medium.bytes}
