"""Operator commands against no run end with one line and a non-zero status, within their timeout (never a
traceback, never an empty view that exits 0)."""

from __future__ import annotations

import asyncio
import sys
import time

from services.bus.zenoh_bus import ZenohBus, endpoint, free_port

COMMANDS = (["watch"], ["faults", "list", "--run", "nothere"], ["record", "--out", "{tmp}/r.mbr"])


async def _run(argv: list[str], timeout: float = 180.0) -> tuple[int, str, float]:
    started = time.monotonic()
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "morph_sim.cli", *argv,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        out, err = await asyncio.wait_for(proc.communicate(), timeout)
    except asyncio.TimeoutError:
        proc.kill()
        await proc.communicate()
        raise AssertionError(f"{argv} did not end within {timeout} s") from None
    return proc.returncode, (out + err).decode(errors="replace"), time.monotonic() - started


async def _start_up_cost() -> float:
    """Seconds the CLI takes to start and exit doing nothing (``--help``), measured beside the commands under test:
    what they take beyond it is their own waiting, whatever the machine's load."""
    code, _, took = await _run(["watch", "--help"])
    assert code == 0
    return took


WAIT_BOUND = 20.0  # seconds a command may wait beyond its start-up: its connect timeout (2 s) or query timeouts


def _one_error_line(argv: list[str], text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"morph-sim {argv[0]}: error: "), text
    assert "Traceback" not in text
    return lines[0]


async def test_commands_against_an_endpoint_where_nothing_listens(tmp_path):
    where = endpoint(free_port())
    # --connect-timeout bounds the wait for the endpoint (default 10 s); the line says how long it waited
    start_up, *results = await asyncio.gather(_start_up_cost(), *(
        _run([*(a.format(tmp=tmp_path) for a in argv), "--endpoint", where, "--connect-timeout", "2"])
        for argv in COMMANDS))
    for argv, (code, text, took) in zip(COMMANDS, results):
        assert code == 1, (argv, text)
        line = _one_error_line(argv, text)
        assert f"cannot reach the Zenoh endpoint {where}: nothing answered within 2 s" in line, line
        assert took < start_up + WAIT_BOUND, (argv, took, start_up)


async def test_a_connect_timeout_that_is_not_a_duration_is_refused_naming_the_option():
    code, text, _ = await _run(["watch", "--connect-timeout", "0"])
    assert code == 2 and text.strip().splitlines()[-1] == (
        "morph-sim watch: error: connect_timeout: must be a finite number > 0, got 0.0"), text


async def test_commands_against_an_endpoint_without_the_run(tmp_path):
    port = free_port()
    router = await ZenohBus.open("router", listen=endpoint(port), mode="router")
    try:
        cases = (["watch"], ["watch", "--run", "wrongid"], ["record", "--run-id", "wrongid", "--out",
                                                                str(tmp_path / "r.mbr")],
                 ["faults", "list", "--run", "wrongid"])
        start_up, *results = await asyncio.gather(_start_up_cost(),
                                                  *(_run([*argv, "--endpoint", endpoint(port)]) for argv in cases))
    finally:
        await router.close()
    for argv, (code, text, took) in zip(cases, results):
        assert code != 0, (argv, text)
        assert took < start_up + WAIT_BOUND, (argv, took, start_up)
        if argv[0] == "faults":  # its one JSON answer says nobody answered
            assert '"ok": false' in text and "wrongid" in text, text
            continue
        line = _one_error_line(argv, text)
        assert ("wrongid" in line) if "wrongid" in argv else ("no monitor is alive" in line), line
    assert not (tmp_path / "r.mbr").exists()
