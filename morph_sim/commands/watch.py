"""``morph-sim watch``: a live terminal view of an ongoing run (rich), joining late from the monitor's latest state.

On start the view asks the monitor (``get morph/<run>/state/**``) for the latest metric samples and agent states, so
a late joiner sees the run as it is, then follows the metric streams, agent states, ticks and events.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from dataclasses import dataclass, field

from services.metrics.catalogue import DISPATCH_OUTCOMES

NAME = "watch"
HELP = "live terminal view of an ongoing run: progress, deliveries, links, agents, counters"
SPARK = "▁▂▃▄▅▆▇█"
MISSIONS = {0: "-", 1: "picking", 2: "delivering", 3: "returning"}
HISTORY = 120  # points of the deliveries sparkline
FINAL_WAIT = 30.0  # seconds to wait, after the sim's end of run, for the monitor's final numbers


def sparkline(values: list[float], width: int = 60) -> str:
    if not values:
        return ""
    values = values[-width:]
    lo, hi = min(values), max(values)
    span = (hi - lo) or 1.0
    return "".join(SPARK[min(len(SPARK) - 1, int((v - lo) / span * (len(SPARK) - 1) + 0.5))] for v in values)


@dataclass
class WatchState:
    """What the view shows; fed by messages (pure bookkeeping, no I/O)."""

    run_id: str
    steps: int | None = None
    metrics: dict = field(default_factory=dict)  # name -> MetricSample
    agents: dict = field(default_factory=dict)  # id -> AgentState
    missions: list[int] = field(default_factory=list)
    n_agvs: int | None = None
    deliveries: list[float] = field(default_factory=list)  # cumulative deliveries, one point per sample
    faults: dict[str, int] = field(default_factory=dict)
    events: int = 0
    finished: bool = False
    last_t: int = -1

    def on_metric(self, m) -> None:
        old = self.metrics.get(m.name)
        if old is not None and m.t < old.t:
            return
        self.metrics[m.name] = m
        self.last_t = max(self.last_t, m.t)
        if m.name == "deliveries_total" and m.value is not None:
            self.deliveries.append(m.value)
            del self.deliveries[:-HISTORY]

    def on_state(self, s) -> None:
        old = self.agents.get(s.agent)
        if old is None or s.t >= old.t:
            self.agents[s.agent] = s

    def on_tick(self, tick) -> None:
        self.missions = list(tick.mission)
        self.n_agvs = sum(tick.is_agv)
        self.last_t = max(self.last_t, tick.t - 1)

    def on_event(self, event) -> None:
        self.events += 1
        if event.kind.startswith(("fault", "agent.crash", "agent.restart", "monitor.")):
            self.faults[event.kind] = self.faults.get(event.kind, 0) + 1
        if event.kind == "run.finished":
            self.finished = True

    def value(self, name: str, fmt: str = "{:.0f}") -> str:
        m = self.metrics.get(name)
        if m is None:
            return "–"
        if m.value is None:
            return " / ".join(f"{v * 1000:.1f} ms" for v in (m.values or []))
        return fmt.format(m.value)

    def renderable(self):
        from rich.console import Group
        from rich.panel import Panel
        from rich.table import Table

        t = self.last_t
        progress = f"tick {t + 1}" + (f" / {self.steps} ({100 * (t + 1) / self.steps:.0f} %)" if self.steps else "")
        if self.finished:
            progress += "  [bold green]finished[/]"
        head = Table.grid(padding=(0, 2))
        head.add_row("run", f"[bold]{self.run_id}[/]", "progress", progress)
        head.add_row("deliveries", self.value("deliveries_total"), "rate", self.value("delivery_rate", "{:.3f}/s"))
        head.add_row("links", self.value("links"), "λ₂", self.value("lambda2", "{:.3f}"))
        head.add_row("η", self.value("eta", "{:.3f}"), "agents alive", self.value("agents_alive"))
        clock = (self.metrics["latency_seconds"].labels.get("clock", "wall") if "latency_seconds" in self.metrics
                 else "wall")
        head.add_row("dispatch delay", self.value("dispatch_delay", "{:.1f} s"),
                     f"latency p50/p90/p99 ({clock} time)", self.value("latency_seconds"))
        curve = Panel(sparkline(self.deliveries) or "(waiting for metrics)", title="cumulative deliveries")
        counters = Table(title="counters", show_header=True)
        counters.add_column("what")
        counters.add_column("count", justify="right")
        msgs = self.metrics.get("messages_total")
        counters.add_row("messages", self.value("messages_total"))
        for kind, count in sorted((msgs.labels if msgs else {}).items()):
            counters.add_row(f"  {kind}", count)
        counters.add_row("drops", self.value("drops_total"))
        counters.add_row("dispatch", "")  # what became of the protocol's messages (services/metrics/catalogue.py)
        for name in DISPATCH_OUTCOMES:
            counters.add_row(f"  {name.replace('_', ' ')}", self.value(f"dispatch_{name}"))
        for kind, count in sorted(self.faults.items()):
            counters.add_row(kind, str(count))
        agents = Table(title="agents", show_header=True)
        for col in ("id", "role", "mission", "degree", "h", "η", "t"):
            agents.add_column(col, justify="right" if col not in ("role", "mission") else "left")
        ids = sorted(set(self.agents) | set(range(len(self.missions))))
        for i in ids:
            st = self.agents.get(i)
            role = st.role if st is not None else ("agv" if self.n_agvs is not None and i < self.n_agvs else "picker")
            mission = MISSIONS.get(self.missions[i], "?") if i < len(self.missions) else "–"
            agents.add_row(str(i), str(getattr(role, "value", role)), mission,
                           str(sum(st.a_row)) if st else "–", f"{st.h:.3f}" if st else "–",
                           f"{st.eta:.3f}" if st else "–", str(st.t) if st else "–")
        return Group(Panel(head, title="morph-sim watch"), curve, counters, agents)


async def watch(bus, run_id: str | None, *, steps: int | None = None, duration: float | None = None,
                console=None, refresh: float = 4.0, follow_ticks: bool = True) -> WatchState:
    """Follow the run on ``bus`` until it finishes (or ``duration`` seconds); draw with rich ``Live`` on ``console``."""
    from rich.live import Live

    from schemas import AgentState, Event, MetricSample, Tick
    from schemas.keys import RunKeys

    if run_id is None:
        run_id = await find_run(bus)
    else:
        await check_run(bus, run_id)
    keys = RunKeys(run_id)
    state = WatchState(run_id, steps)
    # join late: the latest values first
    for reply in await bus.get(keys.latest_all, timeout=2.0):
        if not reply.ok:
            continue
        try:
            msg = reply.decode()
        except ValueError:
            continue
        if isinstance(msg, MetricSample):
            state.on_metric(msg)
        elif isinstance(msg, AgentState):
            state.on_state(msg)

    def handler(kind, fn):
        def on(sample):
            msg = bus.decode(sample, kind)
            if msg is not None:
                fn(msg)
        return on

    subs = [await bus.subscribe(keys.metrics, handler(MetricSample, state.on_metric)),
            await bus.subscribe(keys.agent_states, handler(AgentState, state.on_state)),
            await bus.subscribe(keys.events, handler(Event, state.on_event))]
    if follow_ticks:
        subs.append(await bus.subscribe(keys.tick, handler(Tick, state.on_tick)))
    # The sim's run.finished comes before the monitor's last rows and final publication: the view ends when the
    # monitor has left (its token goes after its last publication), so that it ends on the record's numbers.
    monitor_here = asyncio.Event()
    monitor_gone = asyncio.Event()

    def on_monitor(change) -> None:
        (monitor_here if change.alive else monitor_gone).set()

    subs.append(await bus.subscribe_liveliness(keys.alive("monitor"), on_monitor))
    start = time.monotonic()
    finished_at = None
    try:
        with Live(state.renderable(), console=console, refresh_per_second=refresh, transient=False) as live:
            while duration is None or time.monotonic() - start < duration:
                if state.finished:
                    finished_at = finished_at or time.monotonic()
                    if monitor_gone.is_set() or not monitor_here.is_set() \
                            or time.monotonic() - finished_at > FINAL_WAIT:
                        break
                await asyncio.sleep(1.0 / refresh)
                live.update(state.renderable())
            await asyncio.sleep(0.2)  # what the monitor published just before leaving
            live.update(state.renderable())
    finally:
        for sub in subs:
            await sub.close()
    return state


async def find_run(bus, timeout: float = 5.0) -> str:
    """The run id of the monitor alive on this bus (its liveliness token ``morph/<run>/alive/monitor``)."""
    deadline = time.monotonic() + timeout
    while True:
        runs = sorted({key.split("/")[1] for key in await bus.alive("morph/*/alive/monitor", timeout=1.0)})
        if len(runs) == 1:
            return runs[0]
        if len(runs) > 1:
            raise ValueError(f"run: several runs on this endpoint ({', '.join(runs)}); pass --run ID")
        if time.monotonic() > deadline:
            raise ValueError("run: no monitor is alive on this endpoint; pass --run ID of a running run")
        await asyncio.sleep(0.2)


async def check_run(bus, run_id: str, timeout: float = 5.0) -> None:
    """ValueError unless a process of run ``run_id`` (its sim or monitor) is alive on this bus."""
    deadline = time.monotonic() + timeout
    while True:
        if await bus.alive(f"morph/{run_id}/alive/*", timeout=1.0):
            return
        if time.monotonic() > deadline:
            runs = sorted({key.split("/")[1] for key in await bus.alive("morph/*/alive/monitor", timeout=1.0)})
            here = f"runs here: {', '.join(runs)}" if runs else "no run is alive on this endpoint"
            raise ValueError(f"run: no process of run {run_id!r} is alive on this endpoint ({here})")
        await asyncio.sleep(0.2)


def finished_record(output_dir, run_id: str) -> str | None:
    """The last line for run ``run_id`` if its record under ``output_dir`` has its ``summary.json`` (the monitor writes
    it once the run has ended, and a run id is never used twice), else None."""
    import json
    from pathlib import Path

    record = Path(output_dir) / run_id
    try:
        summary = json.loads((record / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict):
        return None
    return (f"run {run_id}: tick {summary.get('steps', '?')}, deliveries {summary.get('deliveries_total', '?')} "
            f"(finished: its record {record} has its summary; nothing to watch)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run", default=None, help="run id (default: the run whose monitor answers)")
    parser.add_argument("--steps", type=int, default=None, help="total ticks, for the progress (default: unknown)")
    parser.add_argument("--duration", type=float, default=None, help="stop watching after this many seconds")
    from services.process import add_operator_arguments

    add_operator_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from schemas.keys import validate_run_id
    from services.inputs import finite
    from services.process import open_operator_bus, operator_endpoint

    if args.run is not None:
        validate_run_id(args.run)
    if args.duration is not None:
        finite(args.duration, "duration", above=0)
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"steps: must be >= 1, got {args.steps}")
    endpoint = operator_endpoint(args, args.run)  # checks it, and the other operator options
    if args.run is not None:
        ended = finished_record(args.output_dir, args.run)
        if ended is not None:  # nothing of the run is left to join: say so now instead of waiting for it
            print(ended)
            return 0

    async def main() -> WatchState:
        bus = await open_operator_bus("watch", endpoint, args, args.run)
        try:
            return await watch(bus, args.run, steps=args.steps, duration=args.duration)
        finally:
            await bus.close()

    state = asyncio.run(main())
    import sys

    if not sys.stdout.isatty():
        print()  # the view's last frame ends without a newline when it is not drawn on a terminal
    print(f"run {state.run_id}: tick {state.last_t + 1}, deliveries {state.value('deliveries_total')}"
          f"{' (finished)' if state.finished else ''}")
    return 0
