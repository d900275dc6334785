"""One process's fault machinery in one object, so a service wires faults with three calls (DESIGN §4, issue 5).

    rt = FaultRuntime(config.run_id, seed=config.seed, dt=config.dt, virtual=True, events=is_sim)
    rt.attach(bus)                      # fault layer (+ link meter) on the bus; sim-time stamps in virtual time
    await rt.start()                    # the ctl/faults controller (queryable + subscriber) on that bus
    ...
    rt.advance(boundary)                # at each phase boundary (vtime.boundaries): releases held messages,
                                        # heals expired faults, applies the schedule
    rt.metrics(t)                       # what this process received: link/* metric samples

In virtual time every process advances its own :class:`VirtualTime`: the sim at each boundary of its phase loop, an
agent on each ``Tick`` (``t·Δ``) and ``Resolve`` (``t·Δ + Δ/2``) it receives, before handling it. In wall time
(``virtual=False``) delayed messages wait on ``loop.call_later`` (real sleeps) and ``advance`` only applies the
schedule and heals.
"""

from __future__ import annotations

import time

from morph_sim.schemas.messages import MetricSample
from morph_sim.services.bus.base import Bus
from morph_sim.services.bus.faults import FaultLayer, install
from morph_sim.services.bus.linkstats import LinkMeter
from morph_sim.services.bus.vtime import VirtualTime
from morph_sim.services.faults.controller import CrashHook, FaultController
from morph_sim.services.faults.schedule import FaultSchedule


class FaultRuntime:
    def __init__(self, run: str, *, seed: int = 0, dt: float = 1.0, virtual: bool = True, events: bool = False,
                 schedule: FaultSchedule | None = None, on_crash: CrashHook | None = None):
        self.run = run
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

    def now(self) -> float:
        """Sim seconds: the last boundary reached (virtual), else wall seconds since start (paced runs)."""
        return self.vtime.now() if self.vtime is not None else time.monotonic() - self._t0

    def attach(self, bus: Bus) -> FaultLayer:
        """Install a fault layer with a link meter on ``bus`` (several buses in one process share the clock)."""
        meter = self.meters[bus.identity] = LinkMeter(f"morph/{self.run}")
        layer = FaultLayer(self.run, base_seed=self.seed, vtime=self.vtime, meter=meter,
                           clock=None if self.vtime is not None else self.now)
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
                                          events=self.events, on_crash=self.on_crash, schedule=self.schedule)
        await self.controller.start()
        self.controller.advance(self.now())  # commands scheduled at time 0
        return self.controller

    def advance(self, boundary: float) -> int:
        """Reach a phase boundary: apply the schedule, then release what is due (in virtual time)."""
        if self.controller is not None:
            self.controller.advance(boundary)
        if self.vtime is None:
            for layer in self.layers:
                layer.active()  # heals what expired
            return 0
        return self.vtime.advance(boundary)

    def metrics(self, t: int) -> list[MetricSample]:
        out: list[MetricSample] = []
        for receiver, meter in self.meters.items():
            out.extend(meter.metrics(t, self.now(), receiver))
        return out
