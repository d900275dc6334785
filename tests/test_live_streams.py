"""The live side of a default lockstep ``morph-sim up``, seen from the user's side: the metric streams flow for the
whole run to any default-settings Zenoh client, and every live view ends on the record's numbers.

Before: the monitor's event loop delivered its inbox until it was empty, which under the run's steady stream it never
was, so its metric publications (and query answers) waited for the end of the run; streams stopped for many
seconds and the live views ended on stale values.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest
from test_long_run import END_LAG, MONITOR_RSS_BOUND

from services.bus.zenoh_bus import free_port
from services.monitor.catalogue import CATALOGUE
from services.monitor.recorder import read_metrics

from _procs import kill_tree, sample_rss, wait_for_port

# A default-settings client (a user's script): per one-second window, the streams seen; the last deliveries_total.
SUBSCRIBER = r'''
import json, sys, time, collections, msgpack, zenoh
port, run, duration, credentials = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
while True:  # `up` writes the run's operator credentials before it starts the sim
    try:
        conf = zenoh.Config.from_file(credentials)
        break
    except Exception:
        time.sleep(0.1)
conf.insert_json5("mode", '"client"'); conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:%s"]' % port)
seconds = collections.defaultdict(set)
ticks = collections.defaultdict(int)
last = {}
t0 = time.monotonic()
def on_metric(s):
    sec = int(time.monotonic() - t0)
    name = str(s.key_expr).split("/metrics/", 1)[1]
    seconds[sec].add(name)
    if name == "deliveries_total":
        m = msgpack.unpackb(s.payload.to_bytes())
        if m["t"] >= last.get("t", -1):
            last.update(t=m["t"], value=m["value"])
    elif name == "latency_seconds":
        last["latency_labels"] = msgpack.unpackb(s.payload.to_bytes())["labels"]
def on_tick(s):
    ticks[int(time.monotonic() - t0)] += 1
def on_event(s):
    if b"run.finished" in s.payload.to_bytes():
        last["finished_at"] = int(time.monotonic() - t0)
with zenoh.open(conf) as session:
    session.declare_subscriber(f"morph/{run}/metrics/**", on_metric)
    session.declare_subscriber(f"morph/{run}/sim/tick", on_tick)
    session.declare_subscriber(f"morph/{run}/events/*", on_event)
    end = time.monotonic() + duration
    while time.monotonic() < end and "finished_at" not in last:
        time.sleep(0.1)
    time.sleep(1.0)  # the monitor's last publications follow the sim's end
print(json.dumps({"seconds": {k: sorted(v) for k, v in seconds.items()}, "ticks": ticks, "last": last}))
'''

# Streams that have a value in every second of a default run (dispatch_delay exists only in ticks with a dispatch,
# net/* only with --network).
EVERY_SECOND = {m.name for m in CATALOGUE if m.name != "dispatch_delay" and m.source != "network"}


def _user_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("ZENOH_")}


@pytest.mark.parametrize("steps", [2500])
def test_streams_flow_every_second_and_live_views_end_on_the_record(tmp_path, steps):
    port = free_port()
    run = "live"
    up_err = tmp_path / "up.err"
    up = subprocess.Popen(
        [sys.executable, "-m", "morph_sim.cli", "up", "--scale", "tiny", "--steps", str(steps), "--run-id", run,
         "--listen", f"tcp/127.0.0.1:{port}", "--output-dir", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=up_err.open("wb"), text=True, start_new_session=True)
    sub = watch = None
    rss: list[int] = []
    try:
        wait_for_port(port, up, time.monotonic() + 60, 0.05)
        credentials = tmp_path / run / "credentials" / "operator.json5"  # the README's subscriber uses them too
        sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(port), run, "240", str(credentials)],
                               stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=_user_env())
        watch = subprocess.Popen([sys.executable, "-m", "morph_sim.cli", "watch", "--run", run, "--endpoint",
                                  f"tcp/127.0.0.1:{port}", "--duration", "240", "--output-dir", str(tmp_path)],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        deadline = time.monotonic() + 240
        while up.poll() is None and time.monotonic() < deadline:  # the monitor's memory while the run goes on
            sample_rss(up.pid, "monitor", rss)
            time.sleep(0.5)
        out, _ = up.communicate(timeout=30)
        sub_out, sub_err = sub.communicate(timeout=30)
        watch_out, _ = watch.communicate(timeout=30)
    finally:
        for proc in (sub, watch):
            if proc is not None:
                kill_tree(proc)
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait(timeout=5)
    err = up_err.read_text(errors="replace")
    assert up.returncode == 0, (out, err[-3000:])
    assert sub.returncode == 0, sub_err[-2000:]
    rows = read_metrics(tmp_path / run)
    summary = json.loads((tmp_path / run / "summary.json").read_text())
    final = int(rows[-1]["deliveries_total"])
    assert [int(r["t"]) for r in rows] == list(range(steps)) and summary["deliveries_total"] == final
    assert summary["steps"] == steps
    events = [json.loads(ln) for ln in (tmp_path / run / "events.jsonl").read_text().splitlines()]
    finished = [e for e in events if e["kind"] == "run.finished"]
    assert len(finished) == 1 and finished[0]["details"]["deliveries"] == final
    # the record ends with the run (no backlog to work off), in bounded memory
    assert (tmp_path / run / "summary.json").stat().st_mtime - finished[0]["wall_time"] < END_LAG
    assert rss and max(rss) < MONITOR_RSS_BOUND, f"monitor RSS peaked at {max(rss) / 2**20:.0f} MB"

    got = json.loads(sub_out)
    ticks = {int(k): v for k, v in got["ticks"].items()}
    seconds = {int(k): set(v) for k, v in got["seconds"].items()}
    first, end = min(ticks), got["last"]["finished_at"]
    windows = range(first + 1, end)  # whole seconds after the first tick, before the sim's end
    assert end - first >= 10, f"the run lasted {end - first} s; the check needs 10"
    missing = {sec: sorted(EVERY_SECOND - seconds.get(sec, set())) for sec in windows}
    assert not any(missing.values()), {sec: m for sec, m in missing.items() if m}
    assert got["last"]["value"] == final and got["last"]["t"] == steps - 1
    assert got["last"]["latency_labels"]["clock"] == "sim"  # a virtual-time run: the latency says its clock

    # the up's final progress line and its last line: the record's numbers
    progress = [ln for ln in err.splitlines() if ln.startswith(f"tick {steps}/{steps}")]
    assert progress and re.search(rf"deliveries {final}\b", progress[-1]), err[-2000:]
    assert f"completed; {steps} rows, {final} deliveries" in out.strip().splitlines()[-1], out
    # watch's final line: summary.json
    assert watch.returncode == 0
    assert watch_out.strip().splitlines()[-1] == (f"run {run}: tick {steps}, deliveries {final} (finished)")
