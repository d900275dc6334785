"""Who takes part in a run, as the sim sees it: liveliness tokens, readiness probes, absences, and the monitor's window.

An agent takes part once its liveliness token is visible *and* it has answered a readiness probe (declarations
propagate asynchronously in Zenoh). An agent whose token disappears, or that stays silent past the lockstep phase
timeout, is absent until it answers a probe again; the sim never waits for an absent agent. In lockstep the sim runs
at most MONITOR_WINDOW ticks ahead of the rows the monitor has written.
"""

from __future__ import annotations

import asyncio
import logging
import time

from schemas import Event
from services.bus.base import LivelinessEvent, Sample

log = logging.getLogger("morph_sim.sim")

PROBE_INTERVAL = 0.25  # seconds between readiness probes
# A participant that appears is probed at once, after this many seconds in which others may appear too (a run's
# start brings every process within a few milliseconds: one probe for all of them, not one each).
NEWCOMER_GRACE = 0.02
MONITOR = "monitor"
AIR = "air"  # the shared air's process (a profile with rate-limited queues): tick 0 waits for it
# Lockstep: the sim runs at most this many ticks ahead of the rows the monitor has written (it reports them every
# PROGRESS_EVERY rows). The monitor takes in every message of the run and is not part of the tick's barrier; without
# this bound a monitor slower than the run builds an unbounded backlog (memory, a record that ends long after the
# run, live streams that lag by minutes). Larger than PROGRESS_EVERY plus the rows a monitor may hold back.
MONITOR_WINDOW = 200


class Presence:
    """Presence and readiness of a run's participants (a mixin of :class:`services.sim.service.SimService`)."""

    def present(self) -> set[int]:
        cut = self.intake.cut_off  # a robot cut off for flooding takes part no more, whatever it answers
        return {a for a in self.ready if isinstance(a, int) and a in self.alive and a not in cut}

    def _on_alive(self, event: LivelinessEvent) -> None:
        try:
            who = self.keys.alive_id(event.key)
        except ValueError as exc:
            self.intake.refuse(event.key, exc)
            return
        if isinstance(who, int) and not 0 <= who < self.n:
            self.intake.refuse(event.key, f"agent id {who} outside 0..{self.n - 1}")
            return
        if event.alive:
            self.alive.add(who)
            self._newcomer.set()
            if who == MONITOR:
                self._monitor_gone_at = None
                self._monitor_progress.set()
        else:
            self.alive.discard(who)
            if who == MONITOR:
                self._monitor_rows = None  # a restarted monitor starts at the live tick: no rows to wait for
                if self._running and self._stop is None:
                    self._monitor_gone_at = time.monotonic()
                self._monitor_progress.set()
            self.ready.discard(who)
            self._absent(who, "liveliness token gone")
        self._ready_changed.set()

    def _absent(self, who: int | str, why: str) -> None:
        if isinstance(who, int) and self._running and self._stop is None:
            self.result.absences += 1
            log.info("sim: agent %s absent (%s)", who, why)
            ph = self._phase
            if ph is not None:
                with ph.lock:
                    ph.answered(who)

    def _on_event(self, sample: Sample) -> None:
        msg = self.intake.decode(sample, Event)
        if msg is None:
            return
        if msg.kind == "record.progress":
            if self.keys.sender_of(sample.key) != MONITOR or msg.t is None:
                self.intake.refuse(sample.key, "record progress from another participant than the monitor")
                return
            self._monitor_rows = max(self._monitor_rows or 0, msg.t)
            self._monitor_progress.set()
            return
        if msg.kind != "ready.ack":
            return
        who = msg.source
        if self.keys.sender_of(sample.key) != who:
            self.intake.refuse(sample.key, f"ready ack of {who!r} on the key of another participant")
            return
        if who in self.alive and who not in self.ready:
            self.ready.add(who)
            self._ready_changed.set()

    async def _probe_loop(self) -> None:
        while True:
            if any(a not in self.ready and (isinstance(a, int) or a in (MONITOR, AIR)) for a in self.alive):
                self._probe_round += 1
                await self.bus.publish(self.keys.event("sim"), Event(
                    kind="ready.probe", source="sim", details={"round": self._probe_round}))
            self._newcomer.clear()
            try:
                await asyncio.wait_for(self._newcomer.wait(), PROBE_INTERVAL)
                await asyncio.sleep(NEWCOMER_GRACE)
            except asyncio.TimeoutError:
                pass

    def _everyone_ready(self) -> bool:
        need_monitor = self.wait_for_monitor and MONITOR not in self.ready
        need_air = self.shared_air and AIR not in self.ready
        return len(self.present()) >= self.n and not need_monitor and not need_air

    async def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.config.ready_timeout
        while not self._everyone_ready():
            if self._stop is not None:
                return
            left = deadline - time.monotonic()
            if left <= 0:
                missing = sorted(set(range(self.n)) - self.present())
                raise TimeoutError(
                    f"ready_timeout: {len(missing)} of {self.n} agents not ready after "
                    f"{self.config.ready_timeout:.0f} s (missing: {missing[:20]})"
                    + ("" if MONITOR in self.ready or not self.wait_for_monitor else "; monitor not ready")
                    + ("; air not ready" if self.shared_air and AIR not in self.ready else ""))
            self._ready_changed.clear()
            try:
                await asyncio.wait_for(self._ready_changed.wait(), min(left, PROBE_INTERVAL))
            except asyncio.TimeoutError:
                pass

    async def _keep_monitor_window(self, t: int) -> None:
        """Before tick ``t``: wait while the monitor's record is more than MONITOR_WINDOW ticks behind, and while a
        monitor that left mid-run is away (a supervisor restarts it; a run that went on at full speed could end
        before it is back, and close the endpoint on it: the record would then not even say what it lost). A monitor
        that makes no progress, or stays away, for a phase timeout is not waited for any more (until it reports or
        returns): the record then says what it lost, and the run goes on."""
        started, waited = time.monotonic(), False
        while self._stop is None and self._monitor_gone_at is not None:
            if time.monotonic() - self._monitor_gone_at > self.config.phase_timeout:
                log.warning("sim: the monitor left %.0f s ago and is not back; the run goes on without it",
                            self.config.phase_timeout)
                self._monitor_gone_at = None
                break
            await self._monitor_news(0.25)
            waited = True
        rows = self._monitor_rows
        if rows is not None and t - rows > MONITOR_WINDOW:
            progressed = time.monotonic()
            while self._stop is None and self._monitor_rows is not None and t - self._monitor_rows > MONITOR_WINDOW:
                if self._monitor_rows > rows:
                    rows, progressed = self._monitor_rows, time.monotonic()
                elif time.monotonic() - progressed > self.config.phase_timeout:
                    log.warning("sim: the monitor's record is stuck at row %d (tick %d); not waiting for it", rows, t)
                    self._monitor_rows = None
                    break
                await self._monitor_news(0.5)
                waited = True
        if waited:
            self.result.phase_seconds["monitor_wait"] = (
                self.result.phase_seconds.get("monitor_wait", 0.0) + time.monotonic() - started)

    async def _monitor_news(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for the monitor to report rows, leave or come back."""
        self._monitor_progress.clear()
        try:
            await asyncio.wait_for(self._monitor_progress.wait(), timeout)
        except asyncio.TimeoutError:
            pass
