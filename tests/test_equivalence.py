"""A zero-fault distributed run (``morph-sim up``: one OS process per agent over Zenoh) equals the
LocalBus run (``morph-sim run``) with the same seed — per-tick deliveries, links and W snapshots, tick for tick.

The default suite keeps one configuration of each kind at Tiny; the full matrix and the larger scales are marked
slow.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from morph_sim.local import run_local
from services.monitor.recorder import read_metrics, read_snapshots
from services.runconfig import RunConfig

POLICIES = [("full", "reference"), ("tsg", "reference"), ("proximity", "reference"), ("morph", "reference"),
            ("morph", "paper")]


def check_equal(live_run, tmp_path: Path, scale: str, policy: str, preset: str, steps: int = 200, seed: int = 42
                ) -> None:
    up = live_run("eq", "--policy", policy, "--preset", preset, "--steps", str(steps), "--seed", str(seed),
                  "--state-every", "10", "--snapshot-every", "50", scale=scale, listen=False, output_dir=tmp_path / "up")
    assert up.wait(timeout=300) == 0, up.stderr()[-3000:]
    check_record_equal(up.record, tmp_path, scale, policy, preset, steps, seed)


def check_record_equal(up: Path, tmp_path: Path, scale: str, policy: str, preset: str, steps: int, seed: int
                       ) -> None:
    """The record of a finished ``up`` run (directory ``up``) equals the LocalBus run of the same configuration."""
    config = RunConfig(run_id=up.name, scale=scale, policy=policy, preset=preset, steps=steps, seed=seed,
                       state_every=10, snapshot_every=50, output_dir=tmp_path / "local")
    asyncio.run(run_local(config))
    local = config.record_dir
    up_rows, local_rows = read_metrics(up), read_metrics(local)
    assert len(up_rows) == len(local_rows) == steps
    for name in ("deliveries", "links", "lambda2", "requests", "commits", "acks", "eta"):
        assert [r[name] for r in up_rows] == [r[name] for r in local_rows], name
    assert (up / "metrics.csv").read_bytes() == (local / "metrics.csv").read_bytes()
    up_snaps, local_snaps = read_snapshots(up), read_snapshots(local)
    assert sorted(up_snaps) == sorted(local_snaps) == list(range(0, steps + 1, 50))
    for t in local_snaps:
        np.testing.assert_array_equal(up_snaps[t]["W"], local_snaps[t]["W"], err_msg=f"W at tick {t}")
        np.testing.assert_array_equal(up_snaps[t]["A"], local_snaps[t]["A"], err_msg=f"A at tick {t}")


def test_up_equals_local_tiny_morph(recorded_run, tmp_path):
    """The shared recorded run (tests/conftest.py) is a tiny MORPH run of this kind; a recorder that followed it
    changes nothing."""
    assert recorded_run.code == 0, recorded_run.up.stderr()[-3000:]
    check_record_equal(recorded_run.up.record, tmp_path, "tiny", "morph", "reference", recorded_run.steps,
                       recorded_run.seed)


@pytest.mark.slow
@pytest.mark.parametrize("scale", ["tiny", "small"])
@pytest.mark.parametrize("policy,preset", POLICIES)
def test_up_equals_local(live_run, tmp_path, scale, policy, preset):
    check_equal(live_run, tmp_path, scale, policy, preset)


@pytest.mark.slow
@pytest.mark.parametrize("policy,preset", [("morph", "reference"), ("morph", "paper")])
def test_up_equals_local_medium(live_run, tmp_path, policy, preset):
    check_equal(live_run, tmp_path, "medium", policy, preset, steps=400)


# ---------------------------------------------------------------------------------------------------------------
# Under faults: latency of 2.5 ticks with jitter and bursty (Gilbert–Elliott) loss on the dispatch messages, and loss
# on the fleet broadcast. The lab (in-process event network), `morph-sim run` (LocalBus) and `morph-sim up` (one OS
# process per robot over Zenoh) must give the same run.
# ---------------------------------------------------------------------------------------------------------------
def faulted_specs():
    from morph_sim.lab.network import dispatch_faults, fleet_faults
    from schemas.faults import FaultSpec, Latency, Loss

    return (*dispatch_faults(FaultSpec(id="late", seed=11, latency=Latency(delay=2.5, jitter=0.6))),
            *dispatch_faults(FaultSpec(id="bursty", seed=12, loss=Loss(model="gilbert_elliott", percent=15,
                                                                        burst_length=3))),
            *fleet_faults(FaultSpec(id="fleet", seed=13, loss=Loss(percent=20))))


def schedule_toml(specs) -> str:
    """A fault schedule file that sets every spec at tick 0."""
    import json

    def value(v) -> str:
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        return json.dumps(v)

    return "\n".join("[[at]]\ntick = 0\n[at.spec]\n" + "\n".join(
        f"{k} = {value(v)}" for k, v in spec.model_dump(mode="json", exclude_none=True).items()) + "\n"
        for spec in specs)


def check_faulted(live_run, tmp_path: Path, scale: str, steps: int, policy: str = "morph", preset: str = "reference",
                  seed: int = 7) -> None:
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    specs = faulted_specs()
    sched = tmp_path / "faults.toml"
    sched.write_text(schedule_toml(specs))
    up = live_run("eqf", "--policy", policy, "--preset", preset, "--steps", str(steps), "--seed", str(seed),
                  "--phase-timeout", "20", "--fault-schedule", str(sched), scale=scale, listen=False,
                  output_dir=tmp_path / "up")
    lab = run_episode(EpisodeSpec(scale=scale, condition=policy, preset=preset, seed=seed, steps=steps,
                                  fiedler_every=1, faults=specs))
    config = RunConfig(run_id="eqf", scale=scale, policy=policy, preset=preset, steps=steps, seed=seed,
                       phase_timeout=20.0, fault_schedule=sched, output_dir=tmp_path / "local")
    run = asyncio.run(run_local(config))
    assert up.wait(timeout=600) == 0, up.stderr()[-3000:]
    up, local = tmp_path / "up" / "eqf", tmp_path / "local" / "eqf"
    assert (up / "metrics.csv").read_bytes() == (local / "metrics.csv").read_bytes()
    rows = run.monitor.rows  # the values metrics.csv was written from, unrounded
    assert len(rows) == len(read_metrics(local)) == steps

    def col(name):
        return np.array([np.nan if r[name] is None else float(r[name]) for r in rows])

    np.testing.assert_array_equal(col("deliveries_total"), lab.ticks["deliveries_total"])
    np.testing.assert_array_equal(col("requests"), lab.ticks["requests"])
    np.testing.assert_array_equal(col("links"), lab.ticks["links"])
    np.testing.assert_array_equal(col("view_age_mean"), lab.ticks["view_age_mean"])
    np.testing.assert_array_equal(col("view_age_max"), lab.ticks["view_age_max"])
    np.testing.assert_array_equal(run.monitor.snapshots[steps][0], lab.final_weights)
    assert run.sim.protocol["late_applied"] == lab.summary["protocol_late_applied"] > 0
    assert run.sim.protocol["refused_stale"] == lab.summary["protocol_refused_stale"]
    # the faults acted: fleet views went stale, commitments came late, and deliveries still happened
    assert col("view_age_max").max() >= 2.0 and lab.summary["deliveries"] > 0


# 100 ticks by default (late commitments, stale views and deliveries all happen by then; check_faulted asserts it),
# the 150 they were with -m slow
@pytest.mark.parametrize("steps", [100, pytest.param(150, marks=pytest.mark.slow)])
def test_lab_run_and_up_agree_under_late_bursty_dispatch_and_a_lossy_fleet_broadcast_tiny(live_run, tmp_path, steps):
    check_faulted(live_run, tmp_path, "tiny", steps=steps)


# Small with -m slow: its twin at Tiny above (the same check_faulted, 100 ticks) stays in the default suite; Small adds
# a larger fleet and warehouse, not another assertion.
@pytest.mark.slow
@pytest.mark.parametrize("steps", [100, 150])
def test_lab_run_and_up_agree_under_late_bursty_dispatch_and_a_lossy_fleet_broadcast_small(live_run, tmp_path, steps):
    check_faulted(live_run, tmp_path, "small", steps=steps)


@pytest.mark.slow
def test_lab_run_and_up_agree_under_late_bursty_dispatch_and_a_lossy_fleet_broadcast_medium(live_run, tmp_path):
    check_faulted(live_run, tmp_path, "medium", steps=300)



# ---------------------------------------------------------------------------------------------------------------
# Arrival order. Over Zenoh each subscription of a session has its own callback thread, so a sample on one key can
# reach its handler after a later one on another key of the same sender; the in-process bus always delivers in send
# order. A decision point must not depend on it: these runs carry some keys behind the rest and must not change.
# ---------------------------------------------------------------------------------------------------------------
def lagging_network(pattern: str, lag: float):
    """A LocalNetwork whose transport carries the samples of keys matching ``pattern`` ``lag`` wall seconds behind
    every other sample."""
    from schemas.keys import matches
    from services.bus.local import LocalBus, LocalNetwork

    class LaggingBus(LocalBus):
        def _send(self, sample, droppable):
            if not matches(pattern, sample.key):
                return super()._send(sample, droppable)
            loop = asyncio.get_running_loop()
            for bus, sub in [(b, s) for b, s in self.network.subscribers if matches(s.key_expr, sample.key)]:
                loop.call_later(lag, bus._ingress, sub, sample)

    class LaggingNetwork(LocalNetwork):
        def session(self, identity):
            return LaggingBus(self, identity)

    return LaggingNetwork()


def _run_twice(tmp_path: Path, specs, pattern: str, lag: float, **config) -> tuple:
    """The same run in send order and with ``pattern``'s keys lagging: (plain, lagging) LocalRuns and records."""
    sched = tmp_path / "faults.toml"
    sched.write_text(schedule_toml(specs))
    out = []
    for name, network in (("plain", None), ("lagging", lagging_network(f"morph/{config['run_id']}/{pattern}", lag))):
        cfg = RunConfig(**config, phase_timeout=20.0, fault_schedule=sched, output_dir=tmp_path / name)
        out.append((asyncio.run(run_local(cfg, network=network)), (cfg.record_dir / "metrics.csv").read_bytes()))
    return out


def test_a_refusal_that_reaches_its_robot_after_later_ticks_changes_nothing(tmp_path):
    """The sim's refusals carried 0.2 s behind everything else: every robot's decision point waits for the
    refusals its on-board state announces, so the run is the lab's, outcome counters included (without the wait, a
    picker whose refusal came in after the tick it was due by counted its commitment as expired)."""
    from morph_sim.lab.runner import EpisodeSpec, run_episode

    specs, steps = faulted_specs(), 60
    lab = run_episode(EpisodeSpec(scale="tiny", condition="morph", preset="reference", seed=7, steps=steps,
                                  fiedler_every=1, faults=specs))
    sched = tmp_path / "faults.toml"
    sched.write_text(schedule_toml(specs))
    config = RunConfig(run_id="slow", scale="tiny", policy="morph", preset="reference", steps=steps, seed=7,
                       phase_timeout=20.0, fault_schedule=sched, output_dir=tmp_path / "local")
    run = asyncio.run(run_local(config, network=lagging_network("morph/slow/sim/refusal/*", 0.2)))
    assert lab.summary["protocol_refused_stale"] > 0  # refusals were sent, and went the slow way
    protocol = run.sim.protocol
    for name in ("requests", "declined", "expired", "commitment_expired", "late_applied", "refused_stale"):
        assert protocol[name] == lab.summary[f"protocol_{name}"], name
    rows = run.monitor.rows
    assert [r["deliveries_total"] for r in rows] == list(lab.ticks["deliveries_total"])
    assert [r["dispatch_commitment_expired"] for r in rows][-1] == lab.summary["protocol_commitment_expired"]


def test_a_picker_that_lost_its_on_board_state_waits_for_its_refusals_at_the_resolve(tmp_path):
    """A picker whose on-board state is lost skips its tick but still decides at that tick's Resolve: there too it
    waits for the refusals the lost state announced (without, the refusal of the boundary came in after its decision,
    it declined where the run in send order committed, and the runs parted at row 57)."""
    from schemas.faults import FaultSpec, Loss, Scope

    specs = [s for s in faulted_specs() if "refusal" not in s.scope.key_expr]
    specs.append(FaultSpec(id="lost-onboard", seed=12, scope=Scope(key_expr="sim/@onboard/*"), loss=Loss(percent=30)))
    (plain, plain_csv), (lagging, lagging_csv) = _run_twice(
        tmp_path, specs, "sim/refusal/*", 0.2, run_id="sk", scale="tiny", policy="full", preset="reference", steps=70,
        seed=3)
    assert plain.sim.protocol["refused_stale"] > 0 and plain.sim.absences == lagging.sim.absences
    assert lagging_csv == plain_csv


def test_duplicated_requests_count_at_the_pickers_decision_point_whenever_they_arrive(tmp_path):
    """Copies of requests with no latency, the pickers' on-board states 20 ms behind: a copy reaches a picker before
    or after its tick, and is counted at its decision point either way (counted on arrival, the duplicates column
    moved a row earlier in nine rows of sixty)."""
    from schemas.faults import Duplicate, FaultSpec, Scope

    specs = [FaultSpec(id="dup", seed=5, scope=Scope(key_expr="agent/*/request/*"), duplicate=Duplicate(percent=60))]
    (plain, plain_csv), (lagging, lagging_csv) = _run_twice(
        tmp_path, specs, "sim/@onboard/*", 0.02, run_id="dup", scale="tiny", policy="full", preset="reference",
        steps=60, seed=3)
    assert plain.sim.protocol["duplicates"] > 0
    assert lagging_csv == plain_csv
