"""``morph-sim up``'s exit status and last line tell the truth: completed only when steps, rows and summary agree;
non-zero, naming the cause, when the record cannot be written, the output directory is unusable, the run id is
taken, or someone else stopped the run. Real processes; every pid is checked gone."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from services.bus.zenoh_bus import endpoint, free_port
from services.monitor.recorder import read_metrics

from _procs import FEW_ROBOTS, alive, descendants, kill_all, wait_for_port


def _up(tmp_path: Path, run: str, *extra: str, **popen) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--scale", "tiny",
                             "--run-id", run, "--output-dir", str(tmp_path), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def _finish(proc: subprocess.Popen, timeout: float) -> tuple[str, str, set[int]]:
    seen: set[int] = set()
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        seen |= descendants(proc.pid)
        time.sleep(0.05)
    if proc.poll() is None:
        proc.kill()
    out, err = proc.communicate(timeout=15)
    left = alive(seen)
    kill_all(left)
    assert left == [], f"processes left behind: {left}"
    return out, err


def test_a_taken_run_id_and_an_unusable_output_dir_are_refused_in_one_line(tmp_path):
    (tmp_path / "taken").mkdir()
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("x")
    for out_dir, run, field in ((tmp_path, "taken", "run_id"), (not_a_dir, "r", "output_dir")):
        proc = subprocess.run([sys.executable, "-m", "morph_sim.cli", "up", "--quiet", "--steps", "10",
                               "--run-id", run, "--output-dir", str(out_dir)],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"morph-sim up: error: {field}: "), proc.stderr
    assert not (tmp_path / "taken" / "manifest.json").exists()  # nothing was started, nothing written


def test_a_record_that_cannot_be_written_stops_the_run_with_one_line(tmp_path):
    # a full disk, as the monitor meets it: its files may not grow beyond 16 KB (RLIMIT_FSIZE; Python then gets
    # EFBIG instead of SIGXFSZ), which the record's tables reach within a few hundred ticks (and the run's
    # credentials, ~11 KB, fit)
    limit = 16 * 1024

    def small_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = _up(tmp_path, "full", "--steps", "20000", *FEW_ROBOTS, preexec_fn=small_disk)
    out, err = _finish(proc, 180)
    assert proc.returncode == 1, (out, err)
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if "error" in ln]
    assert len(lines) == 1 and err.strip().splitlines()[-1] == lines[0], err  # one error line, the last
    assert lines[0].startswith("morph-sim up: error: monitor: cannot write the run record") \
        and "File too large" in lines[0] and "the run was stopped" in lines[0], lines[0]
    rows = read_metrics(tmp_path / "full")
    assert 0 < len(rows) < 20000  # the run did stop early


def test_credentials_that_cannot_be_written_refuse_the_run_in_one_line(tmp_path):
    # a disk too full for the run's credentials (RLIMIT_FSIZE 2 KB, under the endpoint's access-control file): the
    # run is refused before any process starts, naming the file, with no traceback
    def tiny_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))

    proc = _up(tmp_path, "nocreds", "--steps", "5", preexec_fn=tiny_disk)
    out, err = _finish(proc, 120)
    assert proc.returncode == 1, (out, err)
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("morph-sim up: error: credentials: cannot write "), err
    assert "/nocreds/credentials/" in lines[0] and "File too large" in lines[0], lines[0]
    assert not (tmp_path / "nocreds").exists()  # refused whole: the run id is free again


def test_a_stop_from_outside_ends_up_with_status_3_naming_it(tmp_path):
    port = free_port()
    # paced (20 ticks/s): the run goes on while the stop command starts, connects and is answered, for no more ticks
    # than that takes
    proc = _up(tmp_path, "outside", "--steps", "1000000", "--mode", "paced", "--period", "0.05",
               "--listen", endpoint(port), *FEW_ROBOTS)
    wait_for_port(port, proc, time.monotonic() + 60, 0.05)
    metrics = tmp_path / "outside" / "metrics.csv"
    deadline = time.monotonic() + 60
    while not metrics.exists() or metrics.read_text().count("\n") < 20:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate(timeout=10)
        time.sleep(0.05)

    # the operator's stop (with the run's operator credentials, which `up` wrote into the run directory)
    stop = subprocess.run([sys.executable, "-m", "morph_sim.cli", "stop", "--run", "outside", "--endpoint",
                           endpoint(port), "--reason", "operator says enough", "--output-dir", str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert stop.returncode == 0, stop.stderr
    out, err = _finish(proc, 60)
    assert proc.returncode == 3, (out, err)
    last = out.strip().splitlines()[-1]
    assert "stopped from outside at tick" in last and "operator says enough" in last, last
    rows = read_metrics(tmp_path / "outside")
    summary = json.loads((tmp_path / "outside" / "summary.json").read_text())
    assert summary["steps"] == len(rows) and f"{len(rows)} rows" in last
