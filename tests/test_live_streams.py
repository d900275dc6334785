"""The live side of a default lockstep ``morph-sim up``, seen from the user's side: the metric streams flow for the
whole run to any default-settings Zenoh client, and every live view ends on the record's numbers.

Before: the monitor's event loop delivered its inbox until it was empty, which under the run's steady stream it never
was, so its metric publications (and query answers) waited for the end of the run; streams stopped for many
seconds and the live views ended on stale values.
"""

from __future__ import annotations

import json
import re

from conftest import SHARED_STEPS
from test_long_run import END_LAG, MONITOR_RSS_BOUND

from services.metrics.catalogue import CATALOGUE
from services.monitor.recorder import read_metrics
from services.runconfig import RunConfig

# Streams that have a value in every second of a default run (dispatch_delay exists only in ticks with a dispatch,
# net/* only with --network, the air's only with a rate-limited one).
EVERY_SECOND = {m.name for m in CATALOGUE if m.name != "dispatch_delay" and m.source not in ("network", "air")}
# ticks in which every stream has a value: twice k, as agents publish their states (and the monitor its link
# counters) every k ticks
WINDOW_TICKS = 2 * RunConfig.model_fields["state_every"].default


def test_streams_flow_every_second_and_live_views_end_on_the_record(shared_default_up):
    """The shared default run (tests/conftest.py): a user's Zenoh client and ``morph-sim watch`` followed it from its
    start. The run is judged over every whole second it ran (at least 3 s; 10 s in the slow 2500-step version)."""
    shared = shared_default_up.finished()
    up, sub, watch = shared.run, shared.observer("streams"), shared.observer("watch")
    steps = int(up.argv[up.argv.index("--steps") + 1])
    out, err = up.stdout(), up.stderr()
    assert up.proc.returncode == 0, (out, err[-3000:])
    assert sub.returncode == 0, sub.err[-2000:]
    rows = read_metrics(up.record)
    summary = json.loads((up.record / "summary.json").read_text())
    final = int(rows[-1]["deliveries_total"])
    assert [int(r["t"]) for r in rows] == list(range(steps)) and summary["deliveries_total"] == final
    assert summary["steps"] == steps
    events = [json.loads(ln) for ln in (up.record / "events.jsonl").read_text().splitlines()]
    finished = [e for e in events if e["kind"] == "run.finished"]
    assert len(finished) == 1 and finished[0]["details"]["deliveries"] == final
    # the record ends with the run (no backlog to work off), in bounded memory
    assert (up.record / "summary.json").stat().st_mtime - finished[0]["wall_time"] < END_LAG
    rss = shared.rss
    assert rss and max(rss) < MONITOR_RSS_BOUND, f"monitor RSS peaked at {max(rss) / 2**20:.0f} MB"

    got = json.loads(sub.out)
    ticks = {int(k): v for k, v in got["ticks"].items()}
    seconds = {int(k): set(v) for k, v in got["seconds"].items()}
    first, end = min(ticks), got["last"]["finished_at"]
    # A lockstep run lasts as long as its ticks take: 1,000 tiny ticks take 4-6 s alone on two cores (165-235
    # ticks/s), so the default twin asks for 3 whole seconds, which holds up to ~330 ticks/s.
    need = 10 if steps > SHARED_STEPS else 3
    assert end - first >= need, f"the run lasted {end - first} s; the check needs {need}"
    # Judged second by second: at full speed a second holds far more than WINDOW_TICKS ticks. A second with fewer
    # (the run slowed down by a loaded machine, the client descheduled) is judged together with the next ones until
    # they hold WINDOW_TICKS: the k-tick streams (W block means, link counters) have a value only every k ticks.
    windows: list[list[int]] = []
    held = 0
    for sec in range(first + 1, end):  # whole seconds after the first tick, before the sim's end
        if not windows or held >= WINDOW_TICKS:
            windows.append([])
            held = 0
        windows[-1].append(sec)
        held += ticks.get(sec, 0)
    if len(windows) > 1 and held < WINDOW_TICKS:
        windows[-2] += windows.pop()
    missing = {tuple(w): sorted(EVERY_SECOND - set().union(*(seconds.get(sec, set()) for sec in w))) for w in windows}
    assert not any(missing.values()), ({w: m for w, m in missing.items() if m},
                                       {sec: ticks.get(sec, 0) for sec in range(first + 1, end)})
    assert got["last"]["value"] == final and got["last"]["t"] == steps - 1
    assert got["last"]["latency_labels"]["clock"] == "sim"  # a virtual-time run: the latency says its clock

    # the up's final progress line and its last line: the record's numbers
    progress = [ln for ln in err.splitlines() if ln.startswith(f"tick {steps}/{steps}")]
    assert progress and re.search(rf"deliveries {final}\b", progress[-1]), err[-2000:]
    assert f"completed; {steps} rows, {final} deliveries" in out.strip().splitlines()[-1], out
    # watch's final line: summary.json
    assert watch.returncode == 0, watch.err[-2000:]
    assert watch.out.strip().splitlines()[-1] == f"run {up.run_id}: tick {steps}, deliveries {final} (finished)"
