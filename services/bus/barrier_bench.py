"""Micro-benchmark of the raw lock-step barrier over Zenoh: a clock publishes a tick, N agent OS processes reply,
the clock publishes the next tick when the N-th reply is in. No warehouse, no plasticity: the ceiling that the
distributed run (``morph-sim bench distributed``) is compared with.

Modes:

* ``raw`` — plain zenoh-python with the recommended settings (peer, explicit endpoint, one-thread runtime,
  lowlatency, declared BLOCK publishers, plain callbacks; the clock publishes the next tick from the callback that
  receives the N-th reply). This is "the raw Zenoh barrier rate".
* ``bus`` — the same loop through :class:`ZenohBus` with every message bridged into asyncio on both sides, to show
  what the asyncio bridge costs.
* ``inline`` — through :class:`ZenohBus` with ``inline=True`` subscriptions: handlers run on the receive thread and
  the clock publishes the next tick from the handler of the N-th reply, as in ``raw``.

Usage: ``python -m services.bus.barrier_bench --n 18 --ticks 2000`` (prints one line per mode), or call
:func:`run_barrier`.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass

import msgpack

from services.bus import zenoh_bus
from services.bus.zenoh_bus import endpoint, free_port, zenoh_config

zenoh = zenoh_bus.zenoh
from schemas.keys import RunKeys  # noqa: E402

TICK_PAD = b"\0" * 120  # a tick payload of ~150 B, like the measurements in the Zenoh reference
PROBE = -1  # probe ticks before t = 0 complete the readiness handshake
STOP = -2


@dataclass
class BarrierResult:
    mode: str
    n_agents: int
    ticks: int
    seconds: float
    ticks_per_s: float
    p50_ms: float
    p99_ms: float
    startup_s: float
    phases: int = 1

    def line(self) -> str:
        ph = "" if self.phases == 1 else f", {self.phases} phases per tick"
        return (f"barrier[{self.mode}{ph}] N={self.n_agents}: {self.ticks_per_s:.0f} ticks/s over {self.ticks} ticks "
                f"(tick latency p50 {self.p50_ms:.2f} ms, p99 {self.p99_ms:.2f} ms; startup {self.startup_s:.1f} s)")


def _tick_payload(t: int, phase: int = 0) -> bytes:
    return msgpack.packb({"t": t, "p": phase, "pad": TICK_PAD})


def _reply_payload(t: int, agent: int, phase: int = 0) -> bytes:
    return msgpack.packb({"t": t, "p": phase, "agent": agent, "requests_sent": [], "seq": t + 1})


# ---------------------------------------------------------------------------------------------------------------
# agent side (runs in a child process)
# ---------------------------------------------------------------------------------------------------------------
def _agent_raw(run: str, connect: str, agent: int, timeout: float) -> None:
    keys = RunKeys(run)
    session = zenoh.open(zenoh_config(connect=connect, connect_timeout=10.0))
    done = threading.Event()
    pub = session.declare_publisher(keys.ack(agent), express=True, congestion_control=zenoh.CongestionControl.BLOCK)

    def on_tick(sample) -> None:  # tick (phase 0) and resolve (phase 1) alike
        msg = msgpack.unpackb(sample.payload.to_bytes())
        if msg["t"] == STOP:
            done.set()
            return
        pub.put(_reply_payload(msg["t"], agent, msg["p"]))

    session.declare_subscriber(f"{keys.prefix}/sim/*", on_tick)
    session.liveliness().declare_token(keys.alive(agent))
    try:
        done.wait(timeout)
    finally:
        session.close()


async def _agent_bus(run: str, connect: str, agent: int, timeout: float, inline: bool = False) -> None:
    from services.bus.zenoh_bus import ZenohBus

    keys = RunKeys(run)
    bus = await ZenohBus.open(str(agent), connect=connect, connect_timeout=10.0)
    done = asyncio.Event()
    ack_key = keys.ack(agent)

    loop = asyncio.get_running_loop()

    def on_tick(sample) -> None:
        t = msgpack.unpackb(sample.payload)["t"]
        if t == STOP:
            loop.call_soon_threadsafe(done.set)
            return
        bus.put(ack_key, _reply_payload(t, agent))

    try:
        await bus.subscribe(keys.tick, on_tick, inline=inline)
        await bus.declare_token(keys.alive(agent))
        await asyncio.wait_for(done.wait(), timeout)
    finally:
        await bus.close()


# ---------------------------------------------------------------------------------------------------------------
# clock side
# ---------------------------------------------------------------------------------------------------------------
def _spawn_agents(run: str, ep: str, n: int, mode: str, timeout: float) -> list[subprocess.Popen]:
    env = zenoh_bus.configure_runtime_env(dict(os.environ))
    return [subprocess.Popen([sys.executable, "-m", "services.bus.barrier_bench", "agent", "--run", run,
                              "--connect", ep, "--id", str(i), "--mode", mode, "--timeout", str(timeout)], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            for i in range(n)]


def _reap(procs: list[subprocess.Popen], grace: float) -> None:
    deadline = time.monotonic() + grace
    for proc in procs:
        try:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    for proc in procs:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()


class _RawClock:
    """Callback-chained clock: the N-th reply's callback publishes the next tick (no thread hop)."""

    def __init__(self, session, keys: RunKeys, n: int, total: int, warmup: int, phases: int = 1):
        self.n, self.total, self.warmup, self.phases = n, total, warmup, phases
        self.phase = 0
        self.measure_start = 0.0
        self.measure_end = 0.0
        self.pub = session.declare_publisher(keys.tick, express=True,
                                             congestion_control=zenoh.CongestionControl.BLOCK)
        self.pub_resolve = session.declare_publisher(keys.resolve, express=True,
                                                     congestion_control=zenoh.CongestionControl.BLOCK)
        self.t = PROBE
        self.seen: set[int] = set()
        self.count = 0
        self.started = 0.0
        self.latencies: list[float] = []
        self.ready = threading.Event()
        self.done = threading.Event()
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(keys.acks, self.on_reply)

    def publish(self, t: int) -> None:
        self.started = time.perf_counter()
        self.pub.put(_tick_payload(t))

    def publish_phase(self, t: int, phase: int) -> None:
        self.pub_resolve.put(_tick_payload(t, phase))

    def on_reply(self, sample) -> None:
        reply = msgpack.unpackb(sample.payload.to_bytes())
        with self.lock:  # one callback thread per subscriber, but keep the state change atomic anyway
            if reply["t"] == PROBE:
                self.seen.add(reply["agent"])
                if len(self.seen) == self.n:
                    self.ready.set()
                return
            if reply["t"] != self.t or reply["p"] != self.phase:
                return
            self.count += 1
            if self.count < self.n:
                return
            if self.phase + 1 < self.phases:  # two-phase tick (docs/services.md): resolve after the tick's acks
                self.count = 0
                self.phase += 1
                self.publish_phase(self.t, self.phase)
                return
            self.phase = 0
            now = time.perf_counter()
            self.latencies.append(now - self.started)
            self.count = 0
            self.t += 1
            if self.t == self.warmup:
                self.measure_start = now
            if self.t < self.total:
                self.publish(self.t)
            else:
                self.measure_end = now
                self.done.set()

    def start(self) -> None:
        with self.lock:
            self.measure_start = time.perf_counter()
            self.t = 0
            self.count = 0
            self.phase = 0
            self.publish(0)


def _percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _run_raw(run: str, n: int, ticks: int, warmup: int, port: int, timeout: float, phases: int = 1
             ) -> BarrierResult:
    keys = RunKeys(run)
    ep = endpoint(port)
    t0 = time.monotonic()
    session = zenoh.open(zenoh_config(listen=ep))
    procs: list[subprocess.Popen] = []
    try:
        clock = _RawClock(session, keys, n, warmup + ticks, warmup, phases)
        procs = _spawn_agents(run, ep, n, "raw", timeout)
        deadline = time.monotonic() + timeout
        while not clock.ready.is_set():  # probe until every agent has answered (declarations are asynchronous)
            if time.monotonic() > deadline:
                raise TimeoutError(f"only {len(clock.seen)} of {n} agents answered the probe in {timeout} s")
            for proc in procs:
                if proc.poll() is not None:
                    raise RuntimeError(f"agent process {proc.pid} exited early: {proc.stderr.read().decode()[-500:]}")
            clock.publish(PROBE)
            clock.ready.wait(0.25)
        startup = time.monotonic() - t0
        clock.start()
        if not clock.done.wait(timeout):
            raise TimeoutError(f"barrier stalled at tick {clock.t} (count {clock.count}/{n})")
        lat = clock.latencies[warmup:]
        seconds = max(clock.measure_end - clock.measure_start, 1e-9)  # wall time of the measured ticks
        clock.pub.put(_tick_payload(STOP))
        time.sleep(0.05)
        return BarrierResult("raw", n, ticks, seconds, ticks / seconds, 1000 * _percentile(lat, 0.5),
                             1000 * _percentile(lat, 0.99), startup, phases)
    finally:
        try:
            session.close()
        finally:
            _reap(procs, 5.0)


async def _run_bus(run: str, n: int, ticks: int, warmup: int, port: int, timeout: float, inline: bool = False
                   ) -> BarrierResult:
    from services.bus.zenoh_bus import ZenohBus

    keys = RunKeys(run)
    ep = endpoint(port)
    t0 = time.monotonic()
    bus = await ZenohBus.open("sim", listen=ep)
    loop = asyncio.get_running_loop()
    procs: list[subprocess.Popen] = []
    total = warmup + ticks
    state = {"t": PROBE, "count": 0, "started": 0.0, "measure_start": 0.0, "measure_end": 0.0}
    seen: set[int] = set()
    latencies: list[float] = []
    ready = asyncio.Event()  # every agent answered a probe
    complete = asyncio.Event()  # bridged: this tick is complete; inline: the run is complete

    def publish(t: int) -> None:
        state["started"] = time.perf_counter()
        bus.put(keys.tick, _tick_payload(t))

    def on_reply(sample) -> None:
        reply = msgpack.unpackb(sample.payload)
        if reply["t"] == PROBE:
            if len(seen) < n:
                seen.add(reply["agent"])
                if len(seen) == n:
                    loop.call_soon_threadsafe(ready.set)
            return
        if reply["t"] != state["t"]:
            return
        state["count"] += 1
        if state["count"] < n:
            return
        now = time.perf_counter()
        latencies.append(now - state["started"])
        if not inline:  # bridged: wake the main task once per tick; it publishes the next tick
            complete.set()
            return
        state["count"] = 0
        state["t"] += 1
        if state["t"] == warmup:
            state["measure_start"] = now
        if state["t"] < total:
            publish(state["t"])
        else:
            state["measure_end"] = now
            loop.call_soon_threadsafe(complete.set)

    try:
        await bus.subscribe(keys.acks, on_reply, inline=inline)
        procs = _spawn_agents(run, ep, n, "inline" if inline else "bus", timeout)
        deadline = time.monotonic() + timeout
        while not ready.is_set():
            if time.monotonic() > deadline:
                raise TimeoutError(f"only {len(seen)} of {n} agents answered the probe in {timeout} s")
            bus.put(keys.tick, _tick_payload(PROBE))
            try:
                await asyncio.wait_for(ready.wait(), 0.25)
            except asyncio.TimeoutError:
                pass
        startup = time.monotonic() - t0
        if inline:
            state["t"], state["count"] = 0, 0
            state["measure_start"] = time.perf_counter()
            publish(0)
            await asyncio.wait_for(complete.wait(), timeout)
            seconds = state["measure_end"] - state["measure_start"]
        else:
            begin = 0.0
            for t in range(total):
                if t == warmup:
                    begin = time.perf_counter()
                complete.clear()
                state["t"], state["count"] = t, 0
                publish(t)
                await asyncio.wait_for(complete.wait(), timeout)
            seconds = time.perf_counter() - begin
        bus.put(keys.tick, _tick_payload(STOP))
        await asyncio.sleep(0.05)
        lat = latencies[warmup:]
        return BarrierResult("inline" if inline else "bus", n, ticks, seconds, ticks / max(seconds, 1e-9),
                             1000 * _percentile(lat, 0.5), 1000 * _percentile(lat, 0.99), startup, 1)
    finally:
        await bus.close()
        await asyncio.to_thread(_reap, procs, 5.0)


def run_barrier(n_agents: int, ticks: int = 2000, warmup: int = 100, *, mode: str = "raw", port: int | None = None,
                timeout: float = 120.0, run: str = "barrier", phases: int = 1) -> BarrierResult:
    """Measure the lock-step barrier rate with ``n_agents`` agent OS processes. Every child is reaped (killed by
    pid if needed) before this returns.

    ``phases=2`` (raw mode) makes every tick two barriers, tick then resolve, as in the tick protocol (docs/services.md).
    """
    if n_agents < 1:
        raise ValueError(f"n_agents must be >= 1, got {n_agents}")
    if ticks < 1 or warmup < 0:
        raise ValueError("ticks must be >= 1 and warmup >= 0")
    if phases not in (1, 2) or (phases == 2 and mode != "raw"):
        raise ValueError(f"phases must be 1, or 2 with mode 'raw'; got phases={phases}, mode={mode!r}")
    port = port or free_port()
    if mode == "raw":
        return _run_raw(run, n_agents, ticks, warmup, port, timeout, phases)
    if mode in ("bus", "inline"):
        return asyncio.run(_run_bus(run, n_agents, ticks, warmup, port, timeout, inline=mode == "inline"))
    raise ValueError(f"mode {mode!r} must be 'raw', 'bus' or 'inline'")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="barrier_bench", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="role")
    agent = sub.add_parser("agent", help="(internal) one agent process")
    agent.add_argument("--run", required=True)
    agent.add_argument("--connect", required=True)
    agent.add_argument("--id", type=int, required=True)
    agent.add_argument("--mode", choices=["raw", "bus", "inline"], default="raw")
    agent.add_argument("--timeout", type=float, default=120.0)
    parser.add_argument("--n", type=int, nargs="+", default=[18, 24])
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--mode", choices=["raw", "bus", "inline", "all"], default="all")
    parser.add_argument("--phases", type=int, choices=[1, 2], default=1,
                        help="barriers per tick (2 = tick + resolve, raw mode only)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per result")
    args = parser.parse_args(argv)
    if args.role == "agent":
        if args.mode == "raw":
            _agent_raw(args.run, args.connect, args.id, args.timeout)
        else:
            asyncio.run(_agent_bus(args.run, args.connect, args.id, args.timeout, inline=args.mode == "inline"))
        return 0
    modes = ["raw", "bus", "inline"] if args.mode == "all" else [args.mode]
    for n in args.n:
        for mode in modes:
            result = run_barrier(n, args.ticks, args.warmup, mode=mode,
                                 phases=args.phases if mode == "raw" else 1)
            if args.json:
                import json
                print(json.dumps(asdict(result)), flush=True)
            else:
                print(result.line(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
