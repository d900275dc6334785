"""The dispatch outcome streams of a live ``morph-sim up`` under 2.5 ticks of dispatch latency, as a user's Zenoh client
receives them: tick after tick, each value the record's, the last ones the run's totals (``run.finished``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from test_dispatch_outcomes import BURSTY, LATE, OUTCOME_COLUMNS, _finished, schedule_toml

from morph_sim.lab.network import dispatch_faults
from services.metrics import catalogue
from services.monitor.recorder import read_metrics

from _procs import FEW_ROBOTS, OPERATOR_CLIENT

# A default-settings Zenoh client with the run's operator credentials (the README's subscriber): every sample of the
# dispatch outcome streams, and the end of the run.
SUBSCRIBER = r'''
import json, sys, time, msgpack, zenoh
port, run, credentials, duration, last = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), int(sys.argv[5])
''' + OPERATOR_CLIENT + r'''got, end, seen = {}, {}, {"samples": 0, "last_t": -1, "events": []}
t0 = time.monotonic()
def on_metric(s):
    m = msgpack.unpackb(s.payload.to_bytes())
    seen["samples"] += 1
    seen["last_t"] = max(seen["last_t"], m["t"])
    seen["last_at"] = round(time.monotonic() - t0, 3)
    if m["name"].startswith("dispatch_") and m["name"] != "dispatch_delay":
        got.setdefault(m["name"], []).append([m["t"], m["value"], m["unit"]])
def on_event(s):
    payload = s.payload.to_bytes()
    seen["events"].append([round(time.monotonic() - t0, 3), payload[:60].decode(errors="replace")])
    if b"run.finished" in payload:
        end["at"] = time.monotonic()
while True:  # and opens its endpoint
    try:
        session = zenoh.open(conf)
        break
    except Exception:
        time.sleep(0.1)
with session:
    session.declare_subscriber(f"morph/{run}/metrics/**", on_metric)
    session.declare_subscriber(f"morph/{run}/events/*", on_event)
    print("subscribed", flush=True)
    deadline = time.monotonic() + duration
    # until the last row's samples came (the monitor publishes them after the sim's end), or the run ended long ago
    while time.monotonic() < deadline and not (len(got) == 7 and all(v[-1][0] == last for v in got.values())):
        if "at" in end and time.monotonic() > end["at"] + 20:
            break
        # when the session last had its endpoint (the run's endpoint is a peer), for a failure's message
        if list(session.info.peers_zid()) or list(session.info.routers_zid()):
            seen["endpoint_seen_at"] = round(time.monotonic() - t0, 3)
        time.sleep(0.05)
    seen["run_finished_at"] = round(end["at"] - t0, 3) if "at" in end else None
print(json.dumps(got))
print("client saw:", json.dumps(seen)[-1200:], file=sys.stderr)  # for a failure's message
'''


def test_a_live_up_streams_every_outcome_every_tick_and_ends_on_the_record(tmp_path, live_run):
    """``morph-sim up`` with 2.5 ticks of dispatch latency (and loss): a user's Zenoh client receives the outcome
    streams tick after tick, each value the record's for that tick, the last ones the run's totals. Three robots (two
    AGVs asking one picker): the streams and the record are the monitor's whatever the fleet."""
    steps = 300
    (tmp_path / "faults.toml").write_text(schedule_toml((*dispatch_faults(LATE), *dispatch_faults(BURSTY))))
    env = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH_")}
    subscriber: list[subprocess.Popen] = []

    def start_subscriber(run) -> None:
        # started before the run (it waits for the credentials and the endpoint): a client started after it was
        # once still importing while a 300-tick run went by
        subscriber.append(subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(run.port), "live-oc",
                                            str(run.record / "credentials" / "operator.json5"), "120",
                                            str(steps - 1)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                           text=True, env=env))

    up = live_run("live-oc", "--policy", "full", "--seed", "5", "--steps", str(steps), "--max-rate", "0",
                  "--phase-timeout", "20", "--fault-schedule", str(tmp_path / "faults.toml"), *FEW_ROBOTS,
                  before=start_subscriber)
    sub = subscriber[0]
    try:
        assert up.wait(timeout=150) == 0, up.stderr()[-3000:]
        out, err = sub.communicate(timeout=30)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.communicate()
    assert sub.returncode == 0, err[-2000:]
    got = json.loads(out.splitlines()[-1])
    rows = read_metrics(up.record)
    finished = _finished(up.record)["protocol"]
    assert len(rows) == steps
    assert sorted(got) == sorted(OUTCOME_COLUMNS)
    for name in OUTCOME_COLUMNS:
        samples = got[name]
        # continuity: a sample per row as the monitor writes it (--max-rate 0), in tick order, from the moment the
        # client joined (the run may start before it has subscribed). Metric samples are telemetry, published with
        # Zenoh's DROP congestion control while the run goes on: on a loaded machine a client may lose some
        # (measured: 0-17 % of the rows before the monitor published one batch at a time); the rows the monitor
        # publishes after the run's end come whole; the record has every row
        ticks = [t for t, _, _ in samples]
        gaps = [b - a for a, b in zip(ticks, ticks[1:])]
        assert ticks == sorted(ticks) and ticks[0] <= steps // 3, (name, ticks[0])
        assert len(set(ticks)) >= 0.8 * (steps - ticks[0]) and max(gaps) <= 20, (name, len(ticks), max(gaps), err[-1500:])
        assert {u for _, _, u in samples} == {"messages"}
        # each value is the record's for that tick; the last is the run's total
        assert all(v == int(rows[t][name]) for t, v, _ in samples), name
        assert ticks[-1] == steps - 1 and samples[-1][1] == catalogue.outcome_values(finished)[name], (name, err[-1500:])
    assert finished["late_applied"] > 0 and finished["on_time"] == 0 and finished["expired"] > 0
