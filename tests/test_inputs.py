"""Bad input, as a user types it, gets one line on stderr naming the field and exit status 2, before the command
allocates anything or opens a connection: endpoints, files to read, paths to write, counts and sizes, seconds.

Most commands run in this process (``morph_sim.cli.main``). The inputs that used to fill memory run in one child
process under an address-space limit, so a check that came too late would fail there instead of in the test
runner."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from morph_sim.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
# The child needs ~250 MB of address space to import the CLI and refuse every input below; each input, read or
# built before its check, would need gigabytes.
CHILD_ADDRESS_SPACE = 1 << 30


def _exit(argv) -> int:
    try:
        return cli_main(argv)
    except SystemExit as exc:
        return int(exc.code)


def _refused(argv, capsys) -> str:
    """The one stderr line of a refused command (exit 2)."""
    code = _exit(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1, err
    return err


@pytest.fixture
def no_connection(monkeypatch):
    """Every session a command would open fails the test: its input must be refused before."""
    import services.process

    async def connect(*args, **kwargs):
        raise AssertionError("the command opened a connection before refusing its input")

    monkeypatch.setattr(services.process, "open_bus", connect)


# -- endpoints ---------------------------------------------------------------------------------------------------
def test_up_refuses_a_listen_port_out_of_range_before_anything_starts(tmp_path, capsys):
    err = _refused(["up", "--listen", "tcp/127.0.0.1:99999", "--output-dir", str(tmp_path)], capsys)
    assert err == "morph-sim up: error: listen: port 99999 out of range 0..65535\n"
    assert not list(tmp_path.iterdir())  # no record directory, no process


@pytest.mark.parametrize("argv, line", [
    (["sim", "--run-id", "r", "--listen", "tcp/127.0.0.1:70000"], "listen: port 70000 out of range 0..65535"),
    (["agent", "--run-id", "r", "--endpoint", "tcp/127.0.0.1:0"], "endpoint: port 0 out of range 1..65535"),
    (["monitor", "--run-id", "r", "--endpoint", "udp/localhost"],
     "endpoint: 'udp/localhost' is not a Zenoh endpoint like tcp/127.0.0.1:7447 (no :port)"),
    (["watch", "--endpoint", "tcp/[::1:7447"],
     "endpoint: 'tcp/[::1:7447' is not a Zenoh endpoint like tcp/127.0.0.1:7447 ([::1 is not an IPv6 address)"),
    (["stop", "--run", "r", "--endpoint", "tcp/localhost:99999"], "endpoint: port 99999 out of range 1..65535"),
    (["faults", "list", "--run", "r", "--endpoint", "ws/host:-1"], "endpoint: port '-1' of 'ws/host:-1' is not a number"),
])
def test_every_command_that_takes_an_endpoint_checks_it_before_connecting(argv, line, capsys, no_connection):
    assert _refused(argv, capsys) == f"morph-sim {argv[0]}: error: {line}\n"


def test_an_endpoint_read_from_a_run_record_is_checked_too(tmp_path, capsys, no_connection):
    where = tmp_path / "r" / "credentials" / "where"
    where.parent.mkdir(parents=True)
    where.write_text("tcp/127.0.0.1:99999\n")
    err = _refused(["stop", "--run", "r", "--output-dir", str(tmp_path)], capsys)
    assert err == f"morph-sim stop: error: endpoint (from {where}): port 99999 out of range 1..65535\n"


def test_record_names_a_bad_endpoint_in_one_line(tmp_path, capsys, no_connection):
    err = _refused(["record", "--out", str(tmp_path / "r.mbr"), "--endpoint", "nonsense"], capsys)
    assert err == "morph-sim record: error: endpoint: 'nonsense' is not a Zenoh endpoint like tcp/127.0.0.1:7447\n"


# -- paths to write ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flag, path, line", [
    ("--gif", "/proc/x.gif", "gif: cannot write /proc/x.gif: No such file or directory"),
    ("--png", "/dev/null", "png: /dev/null is a character device, not a regular file"),
    ("--png", "{tmp}/none/last.png", "png: cannot write {tmp}/none/last.png: the directory {tmp}/none does not exist"),
    ("--gif", "{tmp}", "gif: {tmp} is a directory, not a file"),
])
def test_warehouse_refuses_an_image_path_it_cannot_write_before_the_episode(flag, path, line, tmp_path, capsys):
    path, line = path.format(tmp=tmp_path), line.format(tmp=tmp_path)
    err = _refused(["warehouse", "--steps", "5", "--no-progress", flag, path], capsys)
    assert err == f"morph-sim warehouse: error: {line}\n"


def test_credentials_and_schemas_refuse_a_directory_they_cannot_create(tmp_path, capsys):
    assert _refused(["credentials", "--run-id", "r", "--out", "/proc/x"], capsys) == (
        "morph-sim credentials: error: out: cannot create /proc/x: No such file or directory\n")
    assert _refused(["schemas", "export", "/proc/x"], capsys) == (
        "morph-sim schemas: error: dir: cannot create /proc/x: No such file or directory\n")
    afile = tmp_path / "afile"
    afile.write_text("")
    assert _refused(["schemas", "export", str(afile / "sub")], capsys) == (
        f"morph-sim schemas: error: dir: cannot create {afile}/sub: {afile} is not a directory\n")


def test_up_refuses_a_bus_record_it_cannot_write_before_any_process_starts(tmp_path, capsys):
    err = _refused(["up", "--bus-record", "/proc/x.mbr", "--output-dir", str(tmp_path)], capsys)
    assert err == "morph-sim up: error: bus_record: cannot write /proc/x.mbr: No such file or directory\n"
    assert not list(tmp_path.iterdir())


def test_sweep_refuses_an_output_directory_it_cannot_create(capsys):
    err = _refused(["sweep", "--grid", "policy=morph", "--set", "steps=5", "--out", "/proc/x", "--no-progress"], capsys)
    assert err == "morph-sim sweep: error: out: cannot create /proc/x: No such file or directory\n"


# -- inputs that used to fill memory: one child process under an address-space limit --------------------------------
_PROBE = """
import contextlib, io, json, sys
from morph_sim.cli import main
out = {}
for name, argv in json.loads(sys.argv[1]).items():
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code
        except BaseException as exc:  # MemoryError under the limit: the check came too late
            code = repr(exc)[:200]
    out[name] = [code, err.getvalue()]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def bounded(tmp_path_factory):
    """name -> (exit status, stderr) of each command, run in one child limited to CHILD_ADDRESS_SPACE bytes."""
    tmp = tmp_path_factory.mktemp("bounded")
    (tmp / "dense.toml").write_text('name = "dense"\n[access_points]\nspacing = 1e-6\n')
    (tmp / "huge.toml").write_text("".join('[[at]]\ntick = 0\nspec = { loss = { percent = 1 } }\n'
                                           for _ in range(200_000)))
    cases = {
        "dev_zero": ["run", "--no-record", "--fault-schedule", "/dev/zero"],
        "huge_schedule": ["run", "--no-record", "--fault-schedule", str(tmp / "huge.toml")],
        "dense": ["run", "--no-record", "--steps", "1", "--network", str(tmp / "dense.toml")],
        "seeds": ["sweep", "--grid", "policy=morph,full", "--seeds", "1-100000000", "--out", str(tmp)],
        "episodes": ["sweep", "--grid", "policy=morph,full", "--seeds", "1-60000", "--out", str(tmp)],
        "sweep_file": ["sweep", "/dev/zero"],
        "cell_px": ["warehouse", "--steps", "5", "--cell-px", "100000", "--png", str(tmp / "x.png"), "--no-progress"],
        "credentials": ["stop", "--run", "r", "--credentials", "/dev/zero"],
    }

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (CHILD_ADDRESS_SPACE, CHILD_ADDRESS_SPACE))

    proc = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(cases)], capture_output=True, text=True,
                          timeout=60, cwd=tmp, preexec_fn=limit,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    return {name: tuple(v) for name, v in json.loads(proc.stdout).items()}, tmp


def test_a_fault_schedule_that_is_not_a_file_is_refused_before_it_is_read(bounded):
    assert bounded[0]["dev_zero"] == (
        2, "morph-sim run: error: fault_schedule: /dev/zero is a character device, not a regular file\n")


def test_a_fault_schedule_of_200000_entries_is_refused_by_its_size(bounded):
    results, tmp = bounded
    size = (tmp / "huge.toml").stat().st_size
    assert results["huge_schedule"] == (2, f"morph-sim run: error: fault_schedule: {tmp / 'huge.toml'} has "
                                           f"{size:,} bytes, more than the 1,048,576 a file given here may have\n")


def test_a_network_profile_that_would_place_endless_access_points_is_refused(bounded):
    results, tmp = bounded
    assert results["dense"] == (2, f"morph-sim run: error: network: {tmp / 'dense.toml'}: access_points.spacing: "
                                   "1e-06 cells is closer than one access point per cell (at least 1)\n")


def test_sweep_counts_its_seeds_and_episodes_before_listing_them(bounded):
    assert bounded[0]["seeds"] == (2, "morph-sim sweep: error: seeds: 100,000,000 seeds, at most 100,000\n")
    assert bounded[0]["episodes"] == (
        2, "morph-sim sweep: error: grid: 120,000 episodes (2 conditions × 60,000 seeds), at most 100,000\n")
    assert bounded[0]["sweep_file"] == (
        2, "morph-sim sweep: error: sweep file: /dev/zero is a character device, not a regular file\n")


def test_cell_px_is_bounded_by_the_image_it_would_draw(bounded):
    assert bounded[0]["cell_px"] == (2, "morph-sim warehouse: error: cell-px: 2,212,093,700,750 pixels in a "
                                        "1400015×1580050 image of the tiny warehouse, at most 16,777,216\n")


def test_a_credentials_file_that_is_a_device_is_refused_before_zenoh_reads_it(bounded):
    assert bounded[0]["credentials"] == (
        2, "morph-sim stop: error: credentials: /dev/zero is a character device, not a regular file\n")


def test_a_fault_schedule_has_at_most_256_entries(tmp_path, capsys):
    schedule = tmp_path / "many.toml"
    schedule.write_text("".join(f"[[at]]\ntick = 0\nspec = {{ id = \"f{i}\", loss = {{ percent = 1 }} }}\n"
                                for i in range(257)))
    err = _refused(["run", "--no-record", "--steps", "1", "--fault-schedule", str(schedule)], capsys)
    assert err == f"morph-sim run: error: fault schedule {schedule}: at: 257 entries, at most 256\n"


def test_a_network_profile_lists_at_most_4096_access_points(tmp_path, capsys):
    profile = tmp_path / "many.toml"
    profile.write_text('name = "many"\n[access_points]\ncells = [' + ", ".join(["[1, 1]"] * 4097) + "]\n")
    err = _refused(["run", "--no-record", "--steps", "1", "--network", str(profile)], capsys)
    assert err == (f"morph-sim run: error: network: {profile}: access_points.cells: 4,097 access points, "
                   "at most 4,096\n")


def test_a_gif_keeps_at_most_10000_frames(tmp_path, capsys):
    err = _refused(["warehouse", "--steps", "20000", "--gif-every", "1", "--gif", str(tmp_path / "a.gif"),
                    "--no-progress"], capsys)
    assert err == ("morph-sim warehouse: error: gif-every: 20,001 GIF frames (20000 steps, one kept every 1), "
                   "at most 10,000\n")


# -- seconds, rates, counts, ids: checked before connecting ------------------------------------------------------
@pytest.mark.parametrize("argv, line", [
    (["faults", "set", "--run", "r", "--loss", "5", "--timeout", "nan"], "timeout: must be a finite number > 0, got nan"),
    (["faults", "set", "--run", "r", "--loss", "5", "--agents", "a,b"],
     "spec.scope.agents: 'a' is not a robot id (0, 1, …) nor a service (sim, monitor)"),
    (["faults", "set", "--run", "r", "--loss", "5", "--agents", "1,-2"],
     "spec.scope.agents: '-2' is not a robot id (0, 1, …) nor a service (sim, monitor)"),
    (["faults", "list", "--run", "r", "--timeout", "inf"], "timeout: must be a finite number > 0, got inf"),
    (["stop", "--run", "r", "--timeout", "-1"], "timeout: must be a finite number > 0, got -1.0"),
    (["stop", "--run", "r", "--connect-timeout", "nan"], "connect_timeout: must be a finite number > 0, got nan"),
    (["watch", "--duration", "inf"], "duration: must be a finite number > 0, got inf"),
    (["monitor", "--run-id", "r", "--endpoint", "tcp/127.0.0.1:7447", "--max-rate", "nan"],
     "max_rate: must be a finite number >= 0, got nan"),
])
def test_seconds_rates_and_agents_are_checked_before_any_connection(argv, line, capsys, no_connection):
    assert _refused(argv, capsys) == f"morph-sim {argv[0]}: error: {line}\n"


@pytest.mark.parametrize("argv, line", [
    (["warehouse", "--steps", "5", "--seed", "-1", "--no-progress"], "seed: must be in 0..4294967295, got -1"),
    (["warehouse", "--steps", "5", "--fps", "nan", "--gif", "{tmp}/a.gif", "--no-progress"],
     "fps: must be a finite number > 0, got nan"),
    (["sweep", "--grid", "policy=morph", "--set", "steps=5", "--jobs", "100000", "--out", "{tmp}", "--no-progress"],
     "jobs: 100,000 worker processes, at most 256"),
])
def test_sibling_options_are_refused_in_one_line(argv, line, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert _refused(argv, capsys) == f"morph-sim {argv[0]}: error: {line}\n"


# -- a record cut short ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def record(tmp_path_factory):
    out = tmp_path_factory.mktemp("records")
    assert cli_main(["run", "--steps", "4", "--run-id", "whole", "--output-dir", str(out), "--quiet"]) == 0
    return out / "whole"


def test_report_leaves_out_a_last_line_cut_short_and_says_so(record, tmp_path, capsys):
    import shutil

    cut = tmp_path / "cut"
    shutil.copytree(record, cut)
    metrics = cut / "metrics.csv"
    metrics.write_bytes(metrics.read_bytes()[:-20])  # the disk filled in the middle of the last row
    capsys.readouterr()
    assert cli_main(["report", str(cut), "--no-gif", "--out", str(tmp_path / "report")]) == 0
    err = capsys.readouterr().err
    assert err == (f"morph-sim report: warning: left out the unfinished last line of {metrics} (line 5) (its writer "
                   "stopped mid-line: a killed monitor or a full disk)\n")
    table = (tmp_path / "report" / "report.md").read_text()
    assert "| cut | tiny | morph | 42 | ideal (none) | 3 |" in table  # three whole rows of four
    assert f"unfinished last line of {metrics} (line 5)" in table


def test_report_refuses_a_record_damaged_before_its_last_line(record, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(record, bad)
    events = bad / "events.jsonl"
    lines = events.read_text().splitlines(keepends=True)
    events.write_text(lines[0] + '{"kind": \n' + "".join(lines[1:]))
    err = _refused(["report", str(bad), "--no-gif", "--out", str(tmp_path / "report")], capsys)
    assert err.startswith(f"morph-sim report: error: run_dir: {events} line 2 is not a line of this table (")
    assert err.endswith("); the record is damaged\n")
    assert _refused(["report", str(record), "--out", "/proc/x"], capsys) == (
        "morph-sim report: error: out: cannot create /proc/x: No such file or directory\n")
