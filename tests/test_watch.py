"""``morph-sim watch``: the view renders from a scripted state, and follows a live run joining late."""

from __future__ import annotations

import asyncio
import io

from rich.console import Console

from morph_sim.commands.watch import WatchState, find_run, sparkline, watch
from morph_sim.local import run_local
from schemas import AgentState, Event, MetricSample
from services.bus.local import LocalNetwork
from services.runconfig import RunConfig


def _text(renderable) -> str:
    console = Console(file=io.StringIO(), width=120, color_system=None)
    console.print(renderable)
    return console.file.getvalue()


def test_the_view_renders_a_scripted_state():
    st = WatchState("r1", steps=200)
    for t, total in enumerate((0, 1, 1, 3, 6)):
        st.on_metric(MetricSample(name="deliveries_total", t=t, sim_time=float(t), value=float(total)))
    st.on_metric(MetricSample(name="links", t=4, sim_time=4.0, value=7.0))
    st.on_metric(MetricSample(name="messages_total", t=4, sim_time=4.0, value=99.0, labels={"ack": "60"}))
    st.on_metric(MetricSample(name="latency_seconds", t=4, sim_time=4.0, values=[0.001, 0.002, 0.004]))
    st.on_state(AgentState(agent=0, role="agv", t=4, w_row=[0.0, 0.5], a_row=[False, True], theta_row=[0.0, 0.0],
                           age_row=[0, 3], h=0.25, eta=0.5))
    st.on_event(Event(kind="fault.start", source="faults"))
    st.missions = [2, 1]
    st.n_agvs = 1
    out = _text(st.renderable())
    assert "tick 5 / 200 (2 %)" in out
    assert "▁▂▂▅█" in out  # the cumulative deliveries 0 1 1 3 6
    assert "delivering" in out and "picking" in out and "agv" in out and "picker" in out
    assert "0.250" in out and "99" in out and "fault.start" in out and "1.0 ms / 2.0 ms / 4.0 ms" in out
    assert sparkline([]) == "" and sparkline([1, 1]) == "▁▁"


async def test_watch_joins_a_live_run_late_and_follows_it_to_the_end(tmp_path):
    config = RunConfig(run_id="watched", scale="tiny", steps=150, policy="morph", output_dir=tmp_path)
    net = LocalNetwork()
    run = asyncio.create_task(run_local(config, network=net))
    while True:  # join late: once the monitor has finalised some rows
        await asyncio.sleep(0.02)
        assert not run.done()
        if (net_bus := net.session("probe")) and await net_bus.get("morph/watched/state/metrics/links", timeout=0.5):
            await net_bus.close()
            break
        await net_bus.close()
    bus = net.session("watch")
    assert await find_run(bus) == "watched"
    out = io.StringIO()
    state = await asyncio.wait_for(
        watch(bus, "watched", steps=150, console=Console(file=out, width=120, color_system=None), refresh=20),
        timeout=60)
    result = await run
    await bus.close()
    assert state.finished
    assert state.metrics["deliveries_total"].value == result.monitor.deliveries_total
    assert len(state.agents) == config.n_agents and len(state.missions) == config.n_agents
    assert "finished" in _text(state.renderable()) and "cumulative deliveries" in out.getvalue()


def test_the_watch_command_follows_a_live_up_run(shared_default_up):
    """``morph-sim watch`` without ``--run`` joins the shared default ``up`` run (tests/conftest.py) mid-run, once its
    record has rows, finds the run by itself and follows it for ``--duration 3``."""
    import re

    from conftest import LATE_JOIN_ROWS

    shared = shared_default_up.finished()
    late = shared.observer("late-watch")
    run = shared.run.run_id
    assert late.returncode == 0, late.err[-2000:]
    assert run in late.out and "cumulative deliveries" in late.out and "picker" in late.out
    m = re.search(rf"run {run}: tick (\d+), deliveries (\S+)", late.out)
    assert m and int(m.group(1)) > LATE_JOIN_ROWS, late.out[-600:]
