"""One process's fault machinery in one object, so a service wires faults with three calls (docs/faults.md).

    rt = FaultRuntime(config.run_id, seed=config.seed, dt=config.dt, virtual=True, events=is_sim)
    rt.attach(bus)                      # fault layer (+ link meter) on the bus; sim-time stamps in virtual time
    await rt.start()                    # the ctl/faults controller (queryable + subscriber) on that bus
    ...
    rt.advance(boundary)                # at each phase boundary (vtime.boundaries): releases held messages,
                                        # heals expired faults, applies the schedule
    rt.metrics(t)                       # what this process received: link/* metric samples

In virtual time every process advances its own :class:`VirtualTime`: the sim at each boundary of its phase loop, an
agent on each ``Tick`` (``t·Δ``) and ``Resolve`` (``t·Δ + Δ/2``) that *arrives*, before it is handled. In wall time
(``virtual=False``) delayed messages wait on ``loop.call_later`` (real sleeps) and ``advance`` only applies the
schedule and heals.

Across processes (docs/faults.md, "Virtual time across processes"): every layer judges a message by the faults active
at its send time and first brings the schedule up to that time (``_catch_up``), so a fault starts and heals at the same
sim instant in every process whatever the wall order of arrivals; and an agent whose Tick (or a picker whose Resolve)
is lost or held past its phase tells the phase owner at once with a *skip* (:meth:`skip`, a null message on
``agent/<id>/skip``, never faulted), which the owner counts as an answer that cannot come — so the sim never waits on
a wall timeout for it.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time

from schemas import Ack, RunKeys
from schemas.keys import parse_agent_id
from schemas.messages import MetricSample
from services.bus.base import Bus, Sample
from services.faults.controller import CrashHook, FaultController
from services.faults.layer import FaultLayer, install
from services.faults.linkstats import LinkMeter
from services.faults.schedule import FaultSchedule
from services.faults.vtime import VirtualTime

log = logging.getLogger("morph_sim.faults")

FAULT_TIMES = ("virtual", "wall")
#: whether the services count a network profile's delays or only its losses (FaultLayer.network_latency). They count
#: both: the fleet state is its own broadcast (``sim/fleet``) and a late one only leaves a robot with an older view,
#: while its decision point comes on board (docs/decisions.md, "What a robot knows on board and what it hears"), so
#: the lab and the services judge the radio alike. (While the Tick was also the barrier, any latency on it made the
#: agent skip the tick, and a profile's milliseconds of Wi-Fi latency would have silenced every robot.)
NETWORK_LATENCY = True


class FaultRuntime:
    def __init__(self, run: str, *, seed: int = 0, dt: float = 1.0, virtual: bool = True, events: bool = False,
                 schedule: FaultSchedule | None = None, on_crash: CrashHook | None = None,
                 phase_owner: bool | None = None, fleet: int | None = None,
                 network: tuple[str, str] | None = None):
        self.run = run
        self.fleet = fleet  # robots in the run: a fault naming another is refused
        # (profile name or file, scale): the run's Wi-Fi (services/faults/network.py), one model per process, fed by
        # the Ticks this process sees; every process's model follows the same trajectories with the same seed
        self.network_spec = network
        self.network = None
        self.air = False
        if network is not None:
            if not virtual:
                raise ValueError("network: a network profile needs virtual fault time")
            from services.faults.air import has_shared_capacity
            from services.faults.network import NetworkModel, load_profile
            from services.world.layout import LayoutConfig, layout_for

            profile = load_profile(network[0])
            # Shared capacity (rate-limited queues): the air process judges the radio and this process takes its
            # verdicts (services/faults/air.py); its own model still follows the robots (hand-overs, outages,
            # silence stops), and judges no queue: what it sees of the air's traffic is not all of it.
            self.air = has_shared_capacity(profile)
            if self.air:
                profile = profile.model_copy(update={"link_rate": None, "ap_rate": None, "ap_uplink_rate": None,
                                                     "ap_downlink_rate": None})
            self.network = NetworkModel(profile, layout_for(LayoutConfig.named(network[1])), seed=seed)
        # phase_owner: this process runs the phase loop (the sim): it receives the agents' skips. Default: the
        # process that owns the run record (events=True) is the sim.
        self.phase_owner = events if phase_owner is None else phase_owner
        # One lock per process around every fault decision, hold, release and command: transport threads (one per
        # subscription), the loop (ctl/faults) and the phase loop all reach the same layers and clock.
        self.lock = threading.RLock()
        self.keys = RunKeys(run)
        self.seed = seed
        self.dt = dt
        self.vtime = VirtualTime(dt=dt) if virtual else None
        self._t0 = time.monotonic()
        self.events = events
        self.schedule = schedule
        self.on_crash = on_crash
        self.layers: list[FaultLayer] = []
        self.meters: dict[str, LinkMeter] = {}
        self.controller: FaultController | None = None
        self._bus: Bus | None = None
        self._verdict_buses: list[tuple[FaultLayer, Bus]] = []
        self.likes: list[FaultRuntime] = []

    def now(self) -> float:
        """Sim seconds: the last boundary reached (virtual), else wall seconds since start (paced runs)."""
        return self.vtime.now() if self.vtime is not None else time.monotonic() - self._t0

    @classmethod
    def for_service(cls, config, role: str, *, schedule: FaultSchedule | None = None,
                    on_crash: CrashHook | None = None) -> FaultRuntime:
        """The runtime of one service of ``config``'s run (``role``: sim | agent), in the run's fault time."""
        if schedule is None and config.fault_schedule:
            from services.faults.schedule import load_schedule

            schedule = load_schedule(config.fault_schedule, config.n_agents)
        sim = role == "sim"
        return cls(config.run_id, seed=config.seed, dt=config.dt, virtual=config.fault_time == "virtual",
                   events=sim, schedule=schedule, on_crash=on_crash, fleet=config.n_agents,
                   network=None if config.network is None else (config.network, config.scale))

    def like(self) -> FaultRuntime:
        """A runtime for another process of the same run (same seed, Δ, time and schedule; no events). In-process
        runs (``run_local``) keep them in :attr:`likes`, so a run's totals can be read over all its processes."""
        made = FaultRuntime(self.run, seed=self.seed, dt=self.dt, virtual=self.vtime is not None,
                            schedule=self.schedule, fleet=self.fleet, network=self.network_spec)
        self.likes.append(made)
        return made

    def network_losses(self) -> dict[str, int]:
        """Messages the network profile lost, per cause, over this runtime and the ones made by :meth:`like`."""
        out: dict[str, int] = {}
        for rt in (self, *self.likes):
            if rt.network is not None:
                for cause, n in rt.network.stats.lost.items():
                    out[cause] = out.get(cause, 0) + n
        return out

    def attach(self, bus: Bus, *, meter: bool = True, receiver: int | str | None = None) -> FaultLayer:
        """Install a fault layer (with a link meter unless ``meter=False``) on ``bus`` (several buses in one process
        share the clock). ``receiver``: the agent id the layer's links end at, if not the bus identity."""
        link_meter = LinkMeter(f"morph/{self.run}", bus.identity) if meter else None
        if link_meter is not None:
            self.meters[bus.identity] = link_meter
        layer = FaultLayer(self.run, base_seed=self.seed, vtime=self.vtime, meter=link_meter,
                           clock=None if self.vtime is not None else self.now, per_key=True, lock=self.lock)
        layer.receiver = receiver
        try:  # wall time: delayed copies are handed to the loop from the transport's threads
            layer.loop = asyncio.get_running_loop()
        except RuntimeError:
            pass
        if self.vtime is not None:
            layer.before_fate = self._catch_up
        if self.network is not None:
            layer.network = self.network
            layer.network_latency = NETWORK_LATENCY
            if self.events and not any(x.network is self.network for x in self.layers):
                layer.on_handover = self._on_handover  # reported once per process: by the run record's owner
        if self.air:
            from services.faults.air import VerdictBook

            layer.air = VerdictBook()
            self._verdict_buses.append((layer, bus))
        install(bus, layer)
        self.layers.append(layer)
        if self._bus is None:
            self._bus = bus
        if self.controller is not None:
            self.controller.layers.append(layer)
        return layer

    async def start(self) -> FaultController:
        """Mount the ctl/faults controller on the first attached bus."""
        if self._bus is None:
            raise RuntimeError("attach a bus before start()")
        self.controller = FaultController(self._bus, self.run, self.layers, clock=self.now, dt=self.dt,
                                          events=self.events, on_crash=self.on_crash, schedule=self.schedule,
                                          lock=self.lock, hold_events=self.events, fleet=self.fleet,
                                          air_run=self.air)
        await self.controller.start()
        for layer, bus in self._verdict_buses:
            who = layer.receiver if layer.receiver is not None else parse_agent_id(bus.identity)
            await bus.subscribe(self.keys.air_verdicts(who), layer.on_verdicts, inline=True)
        if self.phase_owner:
            await self._bus.subscribe(self.keys.skips, self._on_skip, inline=True)
        self.controller.advance(self.now())  # commands scheduled at time 0
        return self.controller

    def advance(self, boundary: float) -> int:
        """Reach a phase boundary: apply the schedule, then release what is due (in virtual time)."""
        with self.lock:
            if self.controller is not None:
                self.controller.advance(boundary)
                self.controller.publish_held()  # the phase loop runs: the monitor listens
            if self.vtime is None:
                for layer in self.layers:
                    layer.active()  # heals what expired
                return 0
            return self.vtime.advance(boundary)

    def _on_handover(self, event) -> None:
        if self.controller is not None:
            self.controller.note("net.handover", event.time, robot=event.robot, from_ap=event.from_ap,
                                 to_ap=event.to_ap, outage=round(event.outage, 6))

    def _catch_up(self, sent_at: float) -> None:
        """A message sent at ``sent_at`` is about to be judged: apply the schedule up to then (each command at its
        own time), without releasing anything — that waits for this process's own boundary."""
        if self.controller is not None:
            self.controller.advance(sent_at)

    # -- skips: null messages of the phase protocol ---------------------------------------------------------------
    def skip(self, bus: Bus, agent: int, t: int, phase: int) -> None:
        """Tell the phase owner that ``agent`` will not answer ``phase`` of tick ``t`` (its Tick or Resolve was lost
        or held past the phase): it counts as an answer that arrived and was lost."""
        bus.put(self.keys.skip(agent), Ack(t=t, agent=agent, phase=phase))

    def _on_skip(self, sample: Sample) -> None:
        try:
            msg = sample.decode(Ack)
            self.keys.check_author(sample.key, msg.agent, "skip of agent")
        except ValueError as exc:
            log.warning("skip: rejected %s: %s", sample.key, exc)
            return
        lost = Sample(self.keys.ack(msg.agent), sample.payload, sample.sender, sample.seq, sample.sent_at)
        with self.lock:
            for layer in self.layers:
                if layer.on_fate is not None:
                    layer.on_fate(lost, [])

    def metrics(self, t: int) -> list[MetricSample]:
        out: list[MetricSample] = []
        for receiver, meter in self.meters.items():
            out.extend(meter.metrics(t, self.now(), receiver))
        return out
