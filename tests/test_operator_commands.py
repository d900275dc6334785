"""The operator commands find their run from its record, as ``up`` tells the user: a secure run on a port ``up`` chose
itself, and ``faults``, ``watch``, ``record`` and ``stop`` given only ``--run ID --output-dir D`` (real CLI processes,
their exit codes and last lines); afterwards ``watch`` on the finished run says so at once, with the record's numbers.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from types import SimpleNamespace

from _procs import FEW_ROBOTS

CLI_TIMEOUT = 60  # seconds a command may take on a loaded machine before the test gives up on it


def _cli(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "morph_sim.cli", *argv], capture_output=True, text=True,
                          timeout=CLI_TIMEOUT)


def test_watch_faults_record_and_stop_find_a_run_on_a_free_port_by_its_id(live_run, tmp_path):
    up = live_run("u1", "--steps", "100000", "--mode", "paced", "--period", "0.1", *FEW_ROBOTS, listen=False)
    where = up.record / "credentials" / "where"
    up.wait_for_rows(3, timeout=90)
    endpoint = where.read_text().strip()
    assert endpoint.startswith("tcp/127.0.0.1:") and not endpoint.endswith(":7447")
    hint = f"(watch/faults/record/stop find them with --run u1 --output-dir {up.output_dir})"
    assert hint in up.stderr()
    run = ("--output-dir", str(up.output_dir))

    faults = _cli("faults", "set", "--run", "u1", *run, "--loss", "20", "--duration", "6", "--id", "L")
    assert faults.returncode == 0, faults.stderr
    reply = json.loads(faults.stdout.splitlines()[-1])
    assert reply["ok"] and "sim" in reply["sources"] and reply["active"][0]["duration"] == 6.0
    # the confirmation says which clock the 6 s run on: the run's (virtual, paced at 0.1 s per tick)
    assert faults.stderr.strip().splitlines()[-1] == (
        "faults: L: heals after 6 sim seconds (the run's --fault-time is virtual): 6 ticks of Δ = 1 s, about 0.6 s "
        "of wall time at its period of 0.1 s per tick")

    recording = tmp_path / "u1.mbr"
    watch = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "watch", "--run", "u1", *run, "--duration", "2"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        record = _cli("record", "--run-id", "u1", *run, "--out", str(recording), "--timeout", "2", "--quiet")
        watched_out, watched_err = watch.communicate(timeout=CLI_TIMEOUT)
    finally:
        if watch.poll() is None:
            watch.kill()
            watch.communicate()
    assert record.returncode == 0, record.stderr
    assert record.stdout.splitlines()[-1].startswith("recorded ") and " messages of run u1 to " in record.stdout
    assert recording.stat().st_size > 0
    assert watch.returncode == 0, watched_err
    assert watched_out.splitlines()[-1].startswith("run u1: tick ")

    stop = _cli("stop", "--run", "u1", *run)
    assert stop.returncode == 0, stop.stderr
    assert stop.stdout.splitlines()[-1] == "run u1: stop sent (operator stop)"
    assert up.wait(timeout=60) == 3  # stopped from outside
    assert up.stdout().splitlines()[-1].startswith("run u1: stopped from outside at tick ")

    # finished: the record has its summary, so watch says so without looking for the run on the network
    summary = json.loads((up.record / "summary.json").read_text())
    started = time.monotonic()
    late = _cli("watch", "--run", "u1", *run)
    took = time.monotonic() - started
    assert late.returncode == 0, late.stderr
    assert late.stdout.splitlines()[-1] == (
        f"run u1: tick {summary['steps']}, deliveries {summary['deliveries_total']} (finished: its record {up.record} "
        "has its summary; nothing to watch)")
    assert took < 6, f"watch of a finished run took {took:.1f} s"


def test_the_endpoint_comes_from_the_flag_then_the_record_then_the_default(tmp_path):
    """--endpoint wins; an insecure run's record (no credentials) still names its endpoint in the manifest."""
    from services.process import DEFAULT_ENDPOINT, operator_endpoint

    secure = tmp_path / "s" / "credentials"
    secure.mkdir(parents=True)
    (secure / "where").write_text("tcp/127.0.0.1:12001\n")
    (tmp_path / "open").mkdir()
    (tmp_path / "open" / "manifest.json").write_text(json.dumps({"config": {"endpoint": "tcp/127.0.0.1:12002"}}))
    args = SimpleNamespace(endpoint=None, output_dir=str(tmp_path))
    assert operator_endpoint(args, "s") == "tcp/127.0.0.1:12001"
    assert operator_endpoint(args, "open") == "tcp/127.0.0.1:12002"
    assert operator_endpoint(args, "elsewhere") == DEFAULT_ENDPOINT
    assert operator_endpoint(args, None) == DEFAULT_ENDPOINT
    given = SimpleNamespace(endpoint="tcp/127.0.0.1:12003", output_dir=str(tmp_path))
    assert operator_endpoint(given, "s") == "tcp/127.0.0.1:12003"
