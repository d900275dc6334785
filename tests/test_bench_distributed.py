"""``morph-sim bench distributed``: the CPU-per-tick accounting, and before/after against another checkout (no timing
is asserted)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from morph_sim.bench.distributed import READINGS_MAX, CpuMeter, code_cwd, code_env, code_of, summarize

ROOT = Path(__file__).resolve().parents[1]


def _meter() -> CpuMeter:
    children = {name: SimpleNamespace(pid=pid, alive=lambda: True)
                for name, pid in (("sim", 10), ("monitor", 11), ("agent-0", 20), ("agent-1", 21), ("agent-2", 22))}
    sup = SimpleNamespace(children=children, config=SimpleNamespace(steps=100), progress=SimpleNamespace(t=-1))
    return CpuMeter(sup, n_agvs=2)


# the sim's tick clock: tick t started at 100 + t/10 s, every tenth tick and the final tick 100 (at 110 s); the
# window runs from tick 20 (102 s) to tick 100 (110 s): 80 ticks
CLOCK = [[t, 100.0 + t / 10] for t in range(0, 101, 10)]
# CPU seconds each process uses per second of the run: with ten ticks a second, ms per tick = 100 × this
RATES = {"sim:10": 0.04, "monitor:11": 0.02, "agent-0:20": 0.012, "agent-1:21": 0.012, "agent-2:22": 0.006,
         "supervisor:1": 0.002}


def _readings(meter: CpuMeter, times, rates=RATES) -> None:
    for at in times:
        meter.record({key: (at, 1.0 + rate * (at - 100.0)) for key, rate in rates.items()})


def test_cpu_per_tick_by_role_over_the_sim_s_window():
    meter = _meter()
    assert meter._role("agent-1") == "agv" and meter._role("agent-2") == "picker" and meter._role("sim") == "sim"
    _readings(meter, [100.5, 101.7, 105.05, 110.3])  # none on the window's edges: those are interpolated
    cpu = meter.per_tick_ms(CLOCK)
    expect = {"sim": 4.0, "monitor": 2.0, "agv": 1.2, "picker": 0.6, "supervisor": 0.2}
    assert set(cpu) == {*expect, "total"}
    for role, ms in expect.items():
        assert cpu[role] == pytest.approx(ms), role
    assert cpu["total"] == pytest.approx(4.0 + 2.0 + 1.2 + 1.2 + 0.6 + 0.2)  # agents summed, not averaged


def test_the_window_is_the_sim_s_not_when_the_ticks_reached_the_supervisor():
    # the CPU the sim used before tick 20 and after the final tick is not the window's, however the readings fall:
    # a burst of work before the window and after it changes nothing
    meter = _meter()
    meter.record({"sim:10": (101.0, 1.0)})
    meter.record({"sim:10": (102.0, 3.0)})  # two seconds of CPU in the second before the window: start-up
    meter.record({"sim:10": (110.0, 3.32)})
    meter.record({"sim:10": (111.0, 9.0)})  # the run's end
    assert meter.per_tick_ms(CLOCK) == {"sim": pytest.approx(4.0), "total": pytest.approx(4.0)}


def test_processes_that_exit_before_the_window_closes_keep_their_own_window():
    # the run's agents and monitor may leave before the meter's last reading: each is measured up to its last reading,
    # over the ticks up to then
    meter = _meter()
    _readings(meter, [101.0, 104.0])
    _readings(meter, [106.0, 111.0], {"sim:10": RATES["sim:10"], "supervisor:1": RATES["supervisor:1"]})
    cpu = meter.per_tick_ms(CLOCK)
    expect = {"sim": 4.0, "monitor": 2.0, "agv": 1.2, "picker": 0.6, "supervisor": 0.2}
    assert set(cpu) == {*expect, "total"}
    for role, ms in expect.items():
        assert cpu[role] == pytest.approx(ms), role


def test_a_process_restarted_in_the_run_or_first_seen_inside_the_window_is_left_out():
    meter = _meter()
    _readings(meter, [101.0, 111.0], {"sim:10": 0.04, "agent-0:20": 0.012, "agent-1:21": 0.012})
    _readings(meter, [106.0, 111.0], {"agent-0:99": 0.5, "agent-2:22": 0.5})
    cpu = meter.per_tick_ms(CLOCK)
    assert cpu["agv"] == pytest.approx(1.2)  # agent-1 alone: agent-0 lived twice, neither life spans the window
    assert "picker" not in cpu  # agent-2 was first seen after the window opened
    assert cpu["total"] == pytest.approx(4.0 + 1.2)


def test_no_window_no_figures():
    meter = _meter()
    assert meter.per_tick_ms(CLOCK) == {}  # no readings
    _readings(meter, [101.0, 111.0])
    assert meter.per_tick_ms(None) == {} and meter.per_tick_ms([[0, 100.0]]) == {}  # no clock
    assert meter.per_tick_ms([[0, 100.0], [15, 101.5]]) == {}  # the run ended before the window opened
    assert meter.per_tick_ms([[30, 103.0], [100, 110.0]]) == {}  # the clock starts after the window's first tick


def test_a_long_run_s_readings_stay_bounded_and_keep_their_span():
    meter = _meter()
    for i in range(3 * READINGS_MAX):
        meter.record({"sim:10": (100.0 + i / 100, 1.0 + 0.04 * i / 100)})
    series = meter.series["sim:10"]
    assert len(series) <= READINGS_MAX
    assert series[0] == (100.0, 1.0) and series[-1][0] == pytest.approx(100.0 + (3 * READINGS_MAX - 1) / 100)
    assert meter.per_tick_ms(CLOCK)["sim"] == pytest.approx(4.0)


def test_the_meter_samples_the_live_processes_on_its_own_thread_until_stopped():
    meter = _meter()
    meter.sup.children = {"sim": SimpleNamespace(pid=os.getpid(), alive=lambda: True),
                          "agent-0": SimpleNamespace(pid=None, alive=lambda: False)}
    meter.sample_s = 0.01
    before = time.monotonic()
    meter.start()
    deadline = time.monotonic() + 10
    key = f"sim:{os.getpid()}"

    def seen() -> bool:  # three readings, and CPU used between them (its clock counts in steps of 10 ms)
        readings = list(meter.series.get(key, ()))
        return len(readings) >= 3 and readings[-1][1] > readings[0][1]

    while not seen() and time.monotonic() < deadline:
        sum(range(100_000))
    meter.stop()
    after = time.monotonic()
    assert set(meter.series) == {f"sim:{os.getpid()}", f"supervisor:{os.getpid()}"}
    readings = meter.series[key]
    assert len(readings) >= 3 and not meter._thread.is_alive()
    assert before <= readings[0][0] and all(a <= b for a, b in zip(readings, readings[1:])) and readings[-1][0] <= after
    assert readings[-1][1] > readings[0][1] > 0
    n = len(readings)
    time.sleep(0.05)
    assert len(meter.series[key]) == n  # stopped means stopped


def _copy_of_head(tmp_path: Path) -> Path:
    """This repository's committed code, as another checkout would hold it."""
    copy = tmp_path / "before"
    copy.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "HEAD"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(copy)], input=archive, check=True)
    return copy


def _round(revision: str, ticks_per_s: float, total: float | None, **roles: float) -> dict:
    cpu = {} if total is None else {**roles, "total": total}
    return {"revision": revision, "distributed_ticks_per_s": ticks_per_s, "ratio": ticks_per_s / 1000.0,
            "cpu_ms_per_tick": cpu}


def test_the_before_after_summary_gives_medians_their_ratio_each_round_s_ratio_and_each_role():
    runs = {"before": [_round("b", 90.0, 20.0, agv=1.0, sim=4.0), _round("b", 60.0, 30.0, agv=1.5, sim=6.0),
                       _round("b", 100.0, 18.0, agv=0.9, sim=3.6)],
            "after": [_round("a", 81.0, 22.0, agv=1.1, sim=4.4), _round("a", 57.0, 31.5, agv=1.6, sim=6.3),
                      _round("a", 100.0, 18.0, agv=0.9, sim=3.6)]}
    s = summarize(runs)
    assert s["before"]["ticks_per_s"] == 90.0 and s["after"]["ticks_per_s"] == 81.0
    assert s["after_over_before"]["ticks_per_s"] == pytest.approx(0.9)
    assert s["after_over_before"]["cpu_ms_per_tick"] == pytest.approx(22.0 / 20.0)
    # the machine slowed down in round 2 for both sides alike: round by round the ratios stay near each other
    assert s["pairs"]["ticks_per_s"] == pytest.approx([0.9, 0.95, 1.0])
    assert s["pairs"]["cpu_ms_per_tick"] == pytest.approx([1.1, 1.05, 1.0])
    assert s["by_role"] == {"agv": {"before": 1.0, "after": 1.1}, "sim": {"before": 4.0, "after": 4.4}}
    # a round without CPU figures (the accounting saw no window) leaves the CPU pairs and roles out, not zero
    bare = summarize({"before": [_round("b", 90.0, None)], "after": [_round("a", 81.0, None)]})
    assert bare["pairs"] == {"ticks_per_s": [pytest.approx(0.9)], "cpu_ms_per_tick": []}
    assert bare["after_over_before"]["cpu_ms_per_tick"] is None and bare["by_role"] == {}


def test_a_measurement_of_another_checkout_runs_that_checkout_s_code(tmp_path):
    copy = _copy_of_head(tmp_path)
    assert code_of(code_env(copy.resolve()), code_cwd(copy.resolve())) == copy.resolve()
    assert code_of(code_env(None), code_cwd(None)) == ROOT
    bad = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "distributed", "--against", str(tmp_path)],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip().endswith(
        f"--against: {tmp_path.resolve()} is not a morph-sim checkout (no morph_sim/ there)")


@pytest.mark.slow
def test_before_after_measures_both_checkouts_in_one_invocation(tmp_path):
    copy = _copy_of_head(tmp_path)
    done = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "distributed", "--against", str(copy),
                           "--scale", "tiny", "--steps", "80", "--barrier-ticks", "200", "--json"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["runs"]["before"][0]["code"] == str(copy.resolve()) and out["runs"]["after"][0]["code"] == str(ROOT)
    for label in ("before", "after"):
        assert out["summary"][label]["ticks_per_s"] > 0 and out["summary"][label]["cpu_ms_per_tick"] > 0
    assert out["summary"]["after_over_before"]["ticks_per_s"] > 0
    assert len(out["summary"]["pairs"]["ticks_per_s"]) == 1 and {"agv", "picker", "sim"} <= set(out["summary"]["by_role"])


def test_bench_startup_measures_every_role_of_one_up_run():
    done = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "startup", "--rounds", "1", "--steps", "5",
                           "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    run = out["runs"]["after"][0]
    roles = run["first_tick_cpu_s"]
    assert {"supervisor", "sim", "agent", "monitor"} <= set(roles)  # every process of the run was seen starting
    assert 0 < roles["total"] <= run["cpu_s"] and run["first_tick_wall_s"] > 0
    bad = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "startup", "--rounds", "0"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip().endswith("--rounds: 0 must be at least 1")


def test_insecure_measures_an_open_endpoint_and_is_passed_only_to_code_that_has_it(tmp_path):
    from morph_sim.bench.distributed import _knows_insecure

    done = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "distributed", "--insecure", "--scale", "tiny",
                           "--agvs", "2", "--pickers", "1", "--steps", "40", "--barrier-ticks", "100", "--json",
                           "--output-dir", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1])["distributed_ticks"] == 40
    (record,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert (record / "metrics.csv").is_file() and not (record / "credentials").exists()  # no credentials made
    assert _knows_insecure(code_env(None), code_cwd(None))


# -- bench fleet --------------------------------------------------------------------------------------------------------

def test_fleet_sizes_periods_verdicts_and_the_knee():
    from morph_sim.bench.fleet import PERIODS, _parse_sizes, fleet_of, held, knee, schedule

    assert [fleet_of(n) for n in (4, 8, 32, 64, 128)] == [(3, 1), (6, 2), (24, 8), (48, 16), (96, 32)]
    # held at 0.1 s: shorter periods next, longest first, no shorter than the lockstep capacity allows (25 ticks/s)
    assert schedule(0.1, 25.0, True) == [0.05]
    assert schedule(0.1, 1000.0, True) == [0.05, 0.025]
    # not held: longer ones, shortest first
    assert schedule(0.1, 5.0, False) == [0.2, 0.4]
    assert schedule(PERIODS[-1], 1.0, False) == []
    pace = {"interval_mean": 0.104, "interval_max_settled": 0.19, "rescheduled": 0}
    assert held(pace, 0.1)
    assert not held({**pace, "interval_mean": 0.106}, 0.1)
    assert not held({**pace, "interval_max_settled": 0.21}, 0.1)
    assert not held({**pace, "rescheduled": 1}, 0.1)
    rows = [{"robots": 8, "holds_requested": True}, {"robots": 64, "holds_requested": False},
            {"robots": 32, "holds_requested": False}, {"robots": 128, "holds_requested": False}]
    assert knee(rows) == 32 and knee(rows[:1]) is None
    assert _parse_sizes("128,8,32,8") == [8, 32, 128]
    for bad in ("", "3", "8,x", "300"):
        with pytest.raises(ValueError, match="^sizes: "):
            _parse_sizes(bad)


def test_bench_fleet_measures_a_fleet_and_its_paced_runs_in_one_invocation():
    """The reduced twin of ``bench fleet`` (8 to 128 robots): one size, a short lockstep run and paced runs from a
    period of 25 ms; whether a period holds depends on the machine's load, so only its consistency is checked."""
    done = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "fleet", "--sizes", "4", "--ticks", "150",
                           "--period", "0.025", "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    row, end = (json.loads(line) for line in done.stdout.strip().splitlines())
    assert (row["robots"], row["agvs"], row["pickers"]) == (4, 3, 1)
    assert row["lockstep_ticks_per_s"] > 0 and row["cpu_ms_per_tick"]["total"] > 0
    assert {"sim", "monitor", "supervisor", "agv", "picker"} <= set(row["cpu_ms_per_tick"])
    assert 0 < row["agent_uss_mib"] < 200
    tries = row["tries"]
    assert tries[0]["period"] == 0.025 and tries[0] == row["requested"] and row["holds_requested"] == tries[0]["held"]
    # the tries go on until the verdict changes: longer periods after a miss, none shorter than 25 ms is a candidate
    assert all(t["held"] == tries[0]["held"] for t in tries[:-1]) and len(tries) <= 3
    assert row["shortest_period_held"] == min((t["period"] for t in tries if t["held"]), default=None)
    assert end["knee"] == (None if row["holds_requested"] else 4)
    bad = subprocess.run([sys.executable, "-m", "morph_sim.cli", "bench", "fleet", "--sizes", "2"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip().endswith("sizes: each from 4 to 256 robots, got '2'")


def test_the_sim_s_tick_clock_keeps_a_bounded_number_of_tick_starts_and_the_final_tick():
    from services.sim.result import TICK_CLOCK_POINTS, TickClock

    for steps in (1, 60, TICK_CLOCK_POINTS, TICK_CLOCK_POINTS + 1, 1000, 100_000):
        clock = TickClock.for_steps(steps)
        for t in range(steps):
            clock.started(t, 5.0 + t)
        clock.started(steps, 5.0 + steps, last=True)
        ticks = [t for t, _ in clock.summary()]
        assert ticks[0] == 0 and ticks[-1] == steps and len(ticks) <= TICK_CLOCK_POINTS + 1, steps
        assert ticks[:-1] == list(range(0, steps, clock.stride)), steps
        assert all(at == 5.0 + t for t, at in clock.summary()), steps
    # it rides in the run.finished event: however long the run, a small part of what an event may weigh
    from schemas.codec import encode
    from schemas.limits import max_payload
    from schemas.messages import Event

    clock = TickClock.for_steps(10**7)
    for t in range(0, 10**7, clock.stride):
        clock.started(t, 1e6 + t / 10)
    clock.started(10**7, 2e6, last=True)
    size = len(encode(Event(kind="run.finished", details={"tick_clock": clock.summary()})))
    assert size < max_payload(["events"]) / 3


def test_the_fleet_bench_reads_the_agents_memory_in_rounds_and_takes_the_round_nearest_the_middle_tick():
    from morph_sim.bench.fleet import _MemoryMeter

    children = {"sim": SimpleNamespace(pid=os.getpid(), alive=lambda: True),
                "agent-0": SimpleNamespace(pid=os.getpid(), alive=lambda: True),
                "agent-1": SimpleNamespace(pid=None, alive=lambda: False)}
    memory = _MemoryMeter(SimpleNamespace(children=children), sample_s=0.01)
    before = time.monotonic()
    memory.start()
    deadline = time.monotonic() + 10
    while len(memory.rounds) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    memory.stop()
    after = time.monotonic()
    rounds = list(memory.rounds)
    assert len(rounds) >= 3 and not memory._thread.is_alive()
    assert before <= rounds[0][0] and rounds[-1][0] <= after and all(1 << 20 < uss < 1 << 40 for _, uss in rounds)
    time.sleep(0.05)
    assert memory.rounds == rounds  # stopped means stopped
    # placed by the sim's clock: ticks 0..100 from 100 s to 110 s, the middle tick 50 at 105 s
    memory.rounds = [(99.0, 1 << 20), (103.0, 2 << 20), (105.4, 3 << 20), (106.0, 4 << 20), (111.0, 9 << 20)]
    clock = [[t, 100.0 + t / 10] for t in range(0, 101, 10)]
    assert memory.uss_mib(clock) == 3.0
    # none while the run ticked: the agents after the run, not before its first tick
    memory.rounds = [(99.0, 1 << 20), (99.9, 2 << 20), (111.0, 9 << 20), (112.0, 8 << 20)]
    assert memory.uss_mib(clock) == 9.0
    memory.rounds = [(99.0, 1 << 20), (99.9, 2 << 20)]
    assert memory.uss_mib(clock) is None and memory.uss_mib(None) is None
