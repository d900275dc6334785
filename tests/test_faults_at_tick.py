"""Runtime fault commands with ``at_tick`` (``morph-sim faults set --at-tick N``): every process applies the command at
the start of tick N instead of on arrival, so a run changed at run time is as reproducible as one with the same
command in a schedule file (virtual time)."""

from __future__ import annotations

import argparse
import asyncio

import pytest

from morph_sim.commands import faults as faults_cli
from morph_sim.local import run_local
from schemas import FaultSpec, Loss, RunKeys, Scope
from schemas.base import DecodeError
from schemas.codec import decode, encode_fields
from schemas.messages import FaultCommand
from services.bus import LocalNetwork
from services.faults.controller import FaultController
from services.faults.layer import FaultLayer
from services.faults.runtime import FaultRuntime
from services.faults.schedule import parse_schedule
from services.runconfig import RunConfig

AT = 40
SPEC = FaultSpec(id="late-loss", loss=Loss(model="gilbert_elliott", percent=35, burst_length=3),
                 scope=Scope(key_expr="agent/**"))
CONFIG = RunConfig(run_id="attick", scale="tiny", policy="full", seed=3, steps=100, phase_timeout=5.0)


async def _run(*, schedule: bool, runtime_command: bool):
    sched = parse_schedule({"at": [{"tick": AT, "spec": SPEC.model_dump(exclude_none=True)}]}) if schedule else None
    rt = FaultRuntime(CONFIG.run_id, seed=CONFIG.seed, dt=CONFIG.dt, events=True, schedule=sched)
    net = LocalNetwork()
    operator = net.session("operator")
    keys = RunKeys(CONFIG.run_id)
    sent = asyncio.Event()

    def on_tick(sample) -> None:  # the operator acts while the run goes on (at its first tick), long before AT
        if runtime_command and not sent.is_set():
            sent.set()
            operator.put(keys.faults, FaultCommand(op="set", spec=SPEC, at_tick=AT))

    await operator.subscribe(keys.tick, on_tick)
    try:
        run = await run_local(CONFIG, record=False, network=net, faults=rt)
    finally:
        await operator.close()
    return run, rt


async def test_a_runtime_command_at_a_tick_equals_the_same_command_in_a_schedule() -> None:
    clean, _ = await _run(schedule=False, runtime_command=False)
    scheduled, rt_s = await _run(schedule=True, runtime_command=False)
    live, rt_l = await _run(schedule=False, runtime_command=True)
    assert live.sim.per_tick_deliveries == scheduled.sim.per_tick_deliveries
    assert live.sim.commits_applied == scheduled.sim.commits_applied
    assert [(e.kind, e.t, e.details["fault_id"]) for e in rt_l.controller.log] == \
        [(e.kind, e.t, e.details["fault_id"]) for e in rt_s.controller.log] == [("fault.set", AT, "late-loss")]
    # the fault did act, and only from tick AT on
    assert (live.sim.per_tick_deliveries, live.sim.commits_applied) != (clean.sim.per_tick_deliveries,
                                                                       clean.sim.commits_applied)
    assert live.sim.per_tick_deliveries[:AT] == clean.sim.per_tick_deliveries[:AT]


async def test_a_tick_already_reached_is_refused_naming_at_tick() -> None:
    bus = LocalNetwork().session("sim")
    controller = FaultController(bus, "attick", [FaultLayer("attick")], clock=lambda: 12.0)
    controller.advance(12.0)
    reply = controller.handle(FaultCommand(op="set", spec=SPEC.model_copy(update={"crash": None}), at_tick=12))
    assert not reply.ok and reply.error.startswith("at_tick:")
    later = controller.handle(FaultCommand(op="reset", at_tick=13))
    assert later.ok
    await bus.close()


def test_at_tick_is_validated_on_the_wire_and_on_the_command_line() -> None:
    with pytest.raises(DecodeError) as err:
        decode(encode_fields(FaultCommand, op="list", at_tick=5), FaultCommand)
    assert err.value.field == "at_tick"
    with pytest.raises(DecodeError) as err:
        decode(encode_fields(FaultCommand, op="reset", at_tick=-1), FaultCommand)
    assert err.value.field == "at_tick"
    parser = argparse.ArgumentParser()
    faults_cli.add_arguments(parser)
    args = parser.parse_args(["set", "--run", "r1", "--loss", "20", "--at-tick", "300"])
    assert faults_cli.build_command(args).at_tick == 300
    with pytest.raises(ValueError, match="at_tick"):
        faults_cli.build_command(parser.parse_args(["set", "--run", "r1", "--loss", "20", "--at-tick", "-3"]))
    with pytest.raises(SystemExit):
        parser.parse_args(["list", "--run", "r1", "--at-tick", "3"])


@pytest.mark.slow  # ~40 s: a 4,000-tick `up` run plus the LocalBus run it is compared with (reduced: the test above)
def test_faults_set_at_tick_on_a_live_up_run_equals_the_scheduled_localbus_run(tmp_path, live_run):
    import json
    import subprocess
    import sys

    from services.monitor.recorder import read_metrics

    steps, at = 4000, 3000  # the CLI's answers must all come before tick `at`, with margin on a loaded machine
    flags = ["--scale", "tiny", "--policy", "full", "--seed", "9", "--steps", str(steps), "--run-id", "live"]
    up = live_run("live", *flags[2:-2], output_dir=tmp_path / "up")
    up.wait_for_rows(2, timeout=60)  # the run is under way
    spec = json.dumps(SPEC.model_dump(mode="json", exclude_none=True))
    cli = subprocess.run([sys.executable, "-m", "morph_sim.cli", "faults", "set", "--run", "live", "--endpoint",
                          up.endpoint, "--output-dir", str(up.output_dir),  # the operator's credentials of the run
                          "--spec", spec, "--at-tick", str(at), "--each"],
                         capture_output=True, text=True, timeout=60)
    replies = [json.loads(line) for line in cli.stdout.splitlines()]
    assert cli.returncode == 0 and len(replies) >= 9 and all(r["ok"] for r in replies), (cli.stdout, cli.stderr)
    assert up.wait(timeout=180) == 0, up.stderr()[-2000:]
    schedule = tmp_path / "at.toml"
    schedule.write_text(f"[[at]]\ntick = {at}\nspec = {json.dumps(SPEC.model_dump(mode='json', exclude_none=True))}\n"
                        .replace('": ', '" = ').replace('{"', '{ "'))
    local = subprocess.run([sys.executable, "-m", "morph_sim.cli", "run", *flags, "--fault-schedule", str(schedule),
                            "--output-dir", str(tmp_path / "local")], capture_output=True, text=True, timeout=180)
    assert local.returncode == 0, local.stderr[-2000:]
    live_rows, local_rows = read_metrics(tmp_path / "up" / "live"), read_metrics(tmp_path / "local" / "live")
    missing = sorted(set(range(steps)) - {int(r["t"]) for r in live_rows})
    assert len(local_rows) == steps and not missing, (missing[:10], missing[-10:], len(missing),
                                                      (tmp_path / "up" / "live" / "events.jsonl").read_text()[-3000:])
    assert live_rows == local_rows
