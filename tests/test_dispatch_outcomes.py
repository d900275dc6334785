"""What became of the dispatch protocol's messages (on time, late but applied, expired, refused as stale, duplicate,
declined), per tick: the same numbers in the lab's episode, in a ``morph-sim run`` record and in the live streams of
a ``morph-sim up``, ending on the run's own totals (``run.finished``).

The robots count their side (requests expired, declined, duplicates, commitments expired) and report it on their
acks, the sim counts its side (commitments applied on time or late, refused) and reports it on its ticks; neither is
ever faulted, so the counts are exact under any fault schedule. The live streams of ``morph-sim up``:
tests/test_outcome_streams.py."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from morph_sim.lab.network import dispatch_faults
from morph_sim.lab.runner import EpisodeSpec, run_episode
from morph_sim.local import run_local
from schemas.faults import Duplicate, FaultSpec, Latency, Loss
from services.metrics import catalogue
from services.monitor.recorder import read_metrics
from services.runconfig import RunConfig

OUTCOME_COLUMNS = tuple(catalogue.outcome_values({}))
# late, not lost: 2.5 ticks of latency with jitter, bursty loss and duplicates on every dispatch message
LATE = FaultSpec(id="late", latency=Latency(delay=2.5, jitter=0.5, distribution="normal"), seed=1)
BURSTY = FaultSpec(id="bursty", loss=Loss(model="gilbert_elliott", percent=15, burst_length=3), seed=2)
TWICE = FaultSpec(id="twice", duplicate=Duplicate(percent=20), latency=Latency(delay=0.4, jitter=0.3), seed=3)


def schedule_toml(specs) -> str:
    """A ``--fault-schedule`` file setting ``specs`` at tick 0."""
    def value(v) -> str:
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        return json.dumps(v)

    out = []
    for spec in specs:
        out.append("[[at]]\ntick = 0\n[at.spec]")
        out += [f"{k} = {value(v)}" for k, v in spec.model_dump(exclude_none=True, exclude_defaults=True,
                                                                 mode="json").items()]
    return "\n".join(out) + "\n"


def _finished(record: Path) -> dict:
    events = [json.loads(x) for x in (record / "events.jsonl").read_text().splitlines() if x.strip()]
    return next(e for e in events if e["kind"] == "run.finished")["details"]


@pytest.mark.parametrize("scale,steps", [("tiny", 150), pytest.param("small", 300, marks=pytest.mark.slow),
                                         pytest.param("medium", 400, marks=pytest.mark.slow)])
def test_outcome_columns_of_the_lab_and_of_a_run_are_equal_tick_for_tick_under_late_lossy_duplicated_dispatch(
        tmp_path, scale, steps):
    specs = (*dispatch_faults(LATE), *dispatch_faults(BURSTY), *dispatch_faults(TWICE))
    seed = 7
    lab = run_episode(EpisodeSpec(scale=scale, condition="morph", seed=seed, steps=steps, faults=specs,
                                  fiedler_every=1000))
    (tmp_path / "faults.toml").write_text(schedule_toml(specs))
    config = RunConfig(run_id="oc", scale=scale, policy="morph", seed=seed, steps=steps, phase_timeout=10.0,
                       fault_schedule=tmp_path / "faults.toml", output_dir=tmp_path)
    run = asyncio.run(run_local(config))
    rows = read_metrics(tmp_path / "oc")
    assert len(rows) == steps
    np.testing.assert_array_equal([float(r["deliveries_total"]) for r in rows], lab.ticks["deliveries_total"])
    for name in OUTCOME_COLUMNS:
        np.testing.assert_array_equal([int(r[name]) for r in rows], lab.ticks[name].astype(int), err_msg=name)
    # every kind of outcome happened (the check can fail), and the record ends on the run's own totals
    last = rows[-1]
    for name in ("late_applied", "expired", "duplicates", "declined"):
        assert int(last[f"dispatch_{name}"]) > 0, name
    finished = _finished(tmp_path / "oc")["protocol"]
    assert run.sim.protocol == finished
    assert {name: int(last[name]) for name in OUTCOME_COLUMNS} == catalogue.outcome_values(finished)
    assert finished == {k.removeprefix("protocol_"): v for k, v in lab.summary.items() if k.startswith("protocol_")}


def test_zero_faults_every_commitment_is_on_time_and_nothing_expires(tmp_path):
    config = RunConfig(run_id="clean", scale="tiny", policy="full", seed=3, steps=80, output_dir=tmp_path)
    run = asyncio.run(run_local(config))
    rows = read_metrics(tmp_path / "clean")
    on_time = [int(r["dispatch_on_time"]) for r in rows]
    assert on_time == sorted(on_time) and on_time[-1] == run.sim.commits_applied > 0
    for name in ("late_applied", "expired", "commitment_expired", "refused_stale", "duplicates"):
        assert rows[-1][f"dispatch_{name}"] == "0", name


def test_forged_or_corrupt_outcome_counts_are_refused_naming_the_field():
    from schemas import Ack
    from schemas.base import DecodeError
    from schemas.codec import decode, encode_fields
    from schemas.tick import decode_tick, encode_tick_body, tick_fields
    from services.sim.wire import make_controller, world_fields

    ctl = make_controller(RunConfig(run_id="x", scale="tiny", steps=5))
    obs = ctl.begin_tick()
    for bad, field in (({"bogus": 1}, "outcomes.bogus"), ({"expired": -1}, "outcomes.expired"),
                       ({"expired": 1.5}, "outcomes.expired"), ([1, 2], "outcomes")):
        body = tick_fields(obs, 0.0, {**world_fields(ctl, obs), "outcomes": bad})
        try:
            decode_tick(encode_tick_body(body))
            raise AssertionError(f"tick with outcomes {bad!r} accepted")
        except DecodeError as exc:
            assert f"field '{field}" in str(exc), str(exc)
        try:
            decode(encode_fields(Ack, t=1, agent=0, phase=0, outcomes=bad), Ack)
            raise AssertionError(f"ack with outcomes {bad!r} accepted")
        except DecodeError as exc:
            assert f"field '{field}" in str(exc), str(exc)
    good = tick_fields(obs, 0.0, {**world_fields(ctl, obs), "outcomes": {"late_applied": 3}})
    assert decode_tick(encode_tick_body(good)).outcomes == {"late_applied": 3}
