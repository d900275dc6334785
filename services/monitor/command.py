"""``morph-sim monitor`` / ``python -m services.monitor``: metrics, metric streams, latest-state queryable and the
run record, as its own process."""

from __future__ import annotations

import argparse
import json
import sys

NAME = "monitor"
HELP = "run the monitor service (metrics, streams, run record) over Zenoh"
# On SIGTERM the sim ends the run within a second (final tick, run.finished); the monitor waits that long for it so
# the record says how the run ended, and still exits well within the supervisor's 3 s before SIGKILL.
SIGNAL_GRACE = 1.5
# Exit status of a monitor whose run record cannot be written (EX_IOERR): the supervisor does not restart it (a new
# monitor would fail on the same disk) but stops the run and reports the cause.
RECORD_FAILED = 74


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--max-rate", type=float, default=10.0,
                        help="metric stream updates per second at most (0 = none; the record is always complete)")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    parser.add_argument("--prometheus-port", type=int, default=None,
                        help="serve Prometheus /metrics on 127.0.0.1:PORT (compose uses 9464; default: off)")
    parser.add_argument("--prometheus-host", default="127.0.0.1",
                        help="address of the /metrics endpoint (0.0.0.0 inside a container)")
    parser.add_argument("--prometheus-grace", type=float, default=15.0,
                        help="seconds /metrics keeps serving the final values after the run (default 15: one "
                             "scrape interval, so that a short run is not missed)")
    parser.add_argument("--bus-record", default=None, metavar="FILE",
                        help="also write every message of the run this monitor receives (all but its own metric "
                             "streams and events) to FILE: a bus recording for `morph-sim replay`, appended by a "
                             "restarted monitor")
    add_config_arguments(parser, skip=("listen",))
    from services.envconfig import apply_env_defaults

    apply_env_defaults(parser)


def run(args: argparse.Namespace) -> int:
    from services.monitor.service import MonitorService
    from services.process import announce, exit_now, run_or_exit, serve, service_config, setup_logging

    config = service_config(args)
    if not config.endpoint:
        raise ValueError("endpoint: the monitor needs --endpoint ENDPOINT (e.g. tcp/127.0.0.1:7447)")
    from services.inputs import finite, output_file

    finite(args.max_rate, "max_rate", at_least=0)
    finite(args.prometheus_grace, "prometheus_grace", at_least=0)
    if args.bus_record:  # before the session opens
        output_file(args.bus_record, "bus_record", parents=True)
    setup_logging(args.log_level, "monitor")
    port = None if args.prometheus_port in (None, "") else int(args.prometheus_port)

    taps = []

    def make(bus):
        tap = None
        if args.bus_record:
            from pathlib import Path

            from services.monitor.replay import BusRecorder

            try:
                taps.append(BusRecorder(bus, config, Path(args.bus_record)))
            except OSError as exc:
                raise ValueError(f"bus_record: cannot write {args.bus_record}: {exc.strerror or exc}") from None
            tap = taps[0].on_sample
        svc = MonitorService(config, bus, max_rate=float(args.max_rate), keep_rows=False, tap=tap)
        if config.fault_time == "virtual":
            # The monitor is the run's measuring instrument: no fault layer (it records what was sent and what the
            # sim decided, docs/decisions.md), but it stamps sim time like every process of a virtual-time run:
            # the start of the last tick it saw.
            bus.set_clock(lambda: max(svc.last_tick, 0) * config.dt)
        if port is not None:
            from services.monitor.prometheus import PrometheusExporter

            try:  # daemon thread; lives as long as the process
                PrometheusExporter(svc, port, args.prometheus_host)
            except OSError as exc:
                raise ValueError(f"prometheus_port: cannot serve /metrics on {args.prometheus_host}:{port}: "
                                 f"{exc.strerror or exc}") from None
        announce(NAME, f"run {config.run_id}, connected to {config.endpoint}; recording to {config.record_dir}"
                       + (f"; Prometheus /metrics on {args.prometheus_host}:{port}" if port is not None else ""))
        return svc

    signalled: list[str] = []
    try:
        result = run_or_exit(NAME, serve(
            "monitor", make,
            lambda svc: svc.run(), lambda svc, why: (signalled.append(why), svc.stop(grace=SIGNAL_GRACE)),
            connect=config.endpoint))
    except OSError as exc:  # the record's directory cannot be created or opened
        where = exc.filename or config.record_dir
        print(f"morph-sim monitor: error: cannot write the run record {where}: {exc.strerror or exc}",
              file=sys.stderr)
        exit_now(RECORD_FAILED)
    finally:
        for recording in taps:  # what it holds reaches the disk (the process leaves without interpreter teardown)
            recording.close()
    if result.failure is not None:
        print(f"morph-sim monitor: error: {result.failure}", file=sys.stderr)
        exit_now(RECORD_FAILED)
    if port is not None and args.prometheus_grace > 0 and not signalled:
        import signal
        import time

        for sig in (signal.SIGTERM, signal.SIGINT):  # a stop during the grace ends it at once
            signal.signal(sig, lambda *_: exit_now(0))
        time.sleep(args.prometheus_grace)  # the record is complete; /metrics serves the final values meanwhile
    print(json.dumps({"record": str(config.record_dir), "deliveries": result.deliveries_total,
                      "rejected": result.rejected}))
    exit_now(0)
    return 1  # not reached
