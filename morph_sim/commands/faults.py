"""``morph-sim faults set|list|reset``: runtime fault control of a running run over ``morph/<run>/ctl/faults``.

The command is sent as a query, so every process of the run that carries the fault out applies it and answers (each
holds its own fault layer: the sim, every agent; the supervisor of ``morph-sim up`` for crash faults; a process a
command does not concern stays silent). Processes that answer alike are merged into one JSON line with their
``sources`` (a run of 100 agents that all agree prints one line); ``--each`` prints one line per process. A spec is
validated here first, so a bad one is rejected with the field that is wrong before anything is sent (exit 2); a
process that rejects it answers ``ok: false`` with the reason (exit 1), and a crash fault that no supervisor took on
is reported as not carried out (exit 1).

    morph-sim faults set --run r1 --endpoint tcp/127.0.0.1:7447 --loss 20 --burst 4 --key 'agent/*/ack'
    morph-sim faults set --run r1 --endpoint … --spec '{"latency": {"delay": 0.5, "jitter": 0.2}}'
    morph-sim faults list --run r1 --endpoint …
    morph-sim faults reset --run r1 --endpoint …            # heals everything, always
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time

NAME = "faults"
HELP = "set, list or reset faults of a running run (ctl/faults)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="faults_op", metavar="OP", required=True)
    for op, help_ in (("set", "activate a fault"), ("list", "list the active faults"),
                      ("reset", "heal one fault (--id) or all of them")):
        p = sub.add_parser(op, help=help_)
        p.add_argument("--run", required=True, help="run id (key prefix morph/<run>/)")
        p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for answers")
        p.add_argument("--id", dest="fault_id", help="fault id (set: name it; reset: heal only this one)")
        p.add_argument("--each", action="store_true", help="one line per answering process (default: alike merged)")
        from services.process import add_operator_arguments

        add_operator_arguments(p)
        if op in ("set", "reset"):
            p.add_argument("--at-tick", type=int, default=None,
                           help="apply at the start of this (future) tick in every process, not on arrival: the run "
                                "stays reproducible in virtual time (default: at once)")
        if op != "set":
            continue
        p.add_argument("--spec", help="the whole FaultSpec as JSON (other flags are then not allowed)")
        p.add_argument("--loss", type=float, help="loss, percent")
        p.add_argument("--burst", type=float, help="Gilbert–Elliott mean burst length (with --loss), messages")
        p.add_argument("--delay", type=float, help="latency, seconds (sim seconds in virtual time)")
        p.add_argument("--jitter", type=float, help="latency jitter, seconds")
        p.add_argument("--distribution", choices=("uniform", "normal", "pareto"), help="latency distribution")
        p.add_argument("--duplicate", type=float, help="duplicate, percent")
        p.add_argument("--rate", type=float, help="the shared air: every access point's airtime, bytes/s (a run whose "
                                                  "network profile limits it, e.g. congested; alone, without a scope)")
        p.add_argument("--limit", type=int, help="with --rate: each access point's queue, messages (default 1000)")
        p.add_argument("--key", help="scope: key expression relative to morph/<run>/ (default **)")
        p.add_argument("--agents", help="scope: comma-separated agent ids")
        p.add_argument("--duration", type=float,
                       help="auto-heal after this many seconds of the run's fault clock: sim seconds under "
                            "--fault-time virtual (the default: Δ per tick, however long a tick takes on the wall "
                            "clock), wall-clock seconds under --fault-time wall")
        p.add_argument("--seed", type=int, help="seed of this fault's random streams")


_FLAG_FIELDS = ("loss", "burst", "delay", "jitter", "distribution", "duplicate", "rate", "limit", "key", "agents",
                "duration", "seed")


def build_command(args: argparse.Namespace):
    """The FaultCommand the arguments describe; ValueError naming the bad field."""
    from pydantic import ValidationError

    from schemas.errors import invalid
    from schemas.keys import validate_run_id
    from schemas.messages import FaultCommand
    from services.inputs import finite

    validate_run_id(args.run)
    finite(args.timeout, "timeout", above=0)  # nan would pass a `<= 0` test and reach the query
    at_tick = getattr(args, "at_tick", None)
    if at_tick is not None and at_tick < 0:
        raise ValueError(f"at_tick: must be >= 0, got {at_tick}")
    if args.faults_op != "set":
        if args.faults_op == "reset":
            return FaultCommand(op="reset", fault_id=args.fault_id, at_tick=at_tick)
        return FaultCommand(op=args.faults_op)
    flags = {f: getattr(args, f) for f in _FLAG_FIELDS if getattr(args, f) is not None}
    if args.spec is not None:
        if flags:
            raise ValueError(f"spec: --spec cannot be combined with --{', --'.join(flags)}")
        try:
            spec = json.loads(args.spec)
        except json.JSONDecodeError as exc:
            raise ValueError(f"spec: not valid JSON: {exc}") from None
        if not isinstance(spec, dict):
            raise ValueError("spec: must be a JSON object")
    else:
        spec = {}
        if "loss" in flags:
            spec["loss"] = ({"model": "gilbert_elliott", "percent": flags["loss"], "burst_length": flags["burst"]}
                            if "burst" in flags else {"percent": flags["loss"]})
        elif "burst" in flags:
            raise ValueError("burst: needs --loss")
        if "delay" in flags:
            spec["latency"] = {"delay": flags["delay"], **({"jitter": flags["jitter"]} if "jitter" in flags else {}),
                               **({"distribution": flags["distribution"]} if "distribution" in flags else {})}
        elif "jitter" in flags or "distribution" in flags:
            raise ValueError("jitter: --jitter and --distribution need --delay")
        if "duplicate" in flags:
            spec["duplicate"] = {"percent": flags["duplicate"]}
        if "rate" in flags:
            spec["rate"] = {"rate": flags["rate"], **({"limit": flags["limit"]} if "limit" in flags else {})}
        elif "limit" in flags:
            raise ValueError("limit: needs --rate")
        scope = {}
        if "key" in flags:
            scope["key_expr"] = flags["key"]
        if "agents" in flags:
            scope["agents"] = [a.strip() for a in flags["agents"].split(",") if a.strip()]
        if scope:
            spec["scope"] = scope
        for name in ("duration", "seed"):
            if name in flags:
                spec[name] = flags[name]
    if args.fault_id is not None:
        spec["id"] = args.fault_id
    # one id for the fault in every process's layer, so `reset --id` and the event log agree
    spec.setdefault("id", time.strftime("op-%H%M%S", time.gmtime()))
    try:
        return FaultCommand(op="set", spec=spec, at_tick=at_tick)
    except ValidationError as exc:  # the location already starts at spec (spec.loss.percent: …)
        raise invalid(exc) from None


async def send(endpoint: str, run: str, command, timeout: float = 2.0, bus=None, args=None) -> list:
    """Send ``command`` as a query to every process's ``morph/<run>/ctl/faults/<identity>``; the FaultReply of every
    process that answered. An answer counts only under the key of the process it names as its ``source``: on a
    secured endpoint only that process may answer there, so a robot cannot speak for the sim. Others (and error
    replies, which carry no key) are left out, and a line on stderr says how many."""
    from schemas.keys import RunKeys
    from schemas.messages import FaultReply

    own = bus is None
    if own:
        from services.process import open_operator_bus

        bus = await open_operator_bus(f"faults-cli-{int(time.time() * 1000) % 10**9}", endpoint, args, run)
    try:
        keys = RunKeys(run)
        replies = await bus.get(keys.fault_queries, payload=command, timeout=timeout)
        out, ignored = [], []
        for r in replies:
            try:
                reply = r.decode(FaultReply) if r.ok else None
            except ValueError:
                reply = None
            if reply is None or reply.source is None or r.key != keys.fault_answers(reply.source):
                ignored.append(r.key or "(an error reply)")
                continue
            out.append(reply)
        if ignored:
            print(f"morph-sim faults: ignored {len(ignored)} answer(s) not given under the key of the process they "
                  f"name ({', '.join(sorted(set(ignored))[:3])})", file=sys.stderr)
        return sorted(out, key=lambda r: r.source or "")
    finally:
        if own:
            await bus.close()


def merge(replies: list) -> list[dict]:
    """One answer per distinct (ok, error, active), with the ``sources`` that gave it, in source order."""
    groups: dict[str, dict] = {}
    for reply in replies:
        body = reply.model_dump(mode="json", exclude_none=True)
        source = body.pop("source", None)
        key = json.dumps(body, sort_keys=True)
        group = groups.setdefault(key, {**body, "sources": []})
        if source is not None:  # (a verdict of the command itself, e.g. nobody answered, has no source)
            group["sources"].append(source)
    return list(groups.values())


from services.credentials import SUPERVISOR  # noqa: E402  (the bus identity of up's supervisor: it carries out crashes)


def verdict(command, replies: list, run: str, endpoint: str) -> list:
    """The replies plus what is missing from them: a crash fault no supervisor answered for is not carried out."""
    from schemas.messages import FaultReply

    crash = command.op == "set" and command.spec is not None and command.spec.crash is not None
    if not replies and not crash:
        return [FaultReply(ok=False, error=f"no process of run {run!r} answered on {endpoint}")]
    if command.op == "reset" and command.fault_id is not None and any(r.ok for r in replies):
        # the fault is gone everywhere: removed where it was active; a process that never held it (an agent
        # restarted since it was set) has nothing to remove, which is no failure of the reset
        absent = f"fault_id: no active fault {command.fault_id!r}"
        replies = [FaultReply(ok=True, active=r.active, source=r.source) if not r.ok and r.error == absent else r
                   for r in replies]
    if crash and not any(r.source == SUPERVISOR for r in replies):
        replies = replies + [FaultReply(ok=False, error=f"crash: no supervisor of run {run!r} answered on "
                                        f"{endpoint}, so nobody would carry the crash out (crash faults need a run "
                                        "started with `morph-sim up`)")]
    return replies


def duration_clock(duration: float, output_dir, run_id: str) -> str:
    """Which clock a fault's ``duration`` runs on in run ``run_id``: its fault time, from the run's record under
    ``output_dir`` (each process of a run heals on the run's fault clock, the CLI's own clock plays no part)."""
    from pathlib import Path

    from services.runconfig import RunConfig

    try:
        config = RunConfig.coerce(json.loads((Path(output_dir) / run_id / "manifest.json").read_text())["config"])
    except (OSError, ValueError, KeyError, TypeError):
        return (f"heals after {duration:g} s of the run's fault clock: sim seconds if its --fault-time is virtual "
                "(the default), wall-clock seconds if wall (no record of the run here to tell which)")
    if config.fault_time == "wall":
        return f"heals after {duration:g} wall-clock seconds (the run's --fault-time is wall)"
    ticks = duration / config.dt
    pace = (f", about {ticks * config.period:g} s of wall time at its period of {config.period:g} s per tick"
            if config.mode == "paced" else ", however long they take on the wall clock (lock-step)")
    return (f"heals after {duration:g} sim seconds (the run's --fault-time is virtual): {ticks:g} ticks of "
            f"Δ = {config.dt:g} s{pace}")


def run(args: argparse.Namespace) -> int:
    from services.process import operator_endpoint

    command = build_command(args)
    endpoint = operator_endpoint(args, args.run)
    replies = verdict(command, asyncio.run(send(endpoint, args.run, command, args.timeout, args=args)), args.run,
                      endpoint)
    if all(r.ok for r in replies) and command.spec is not None and command.spec.duration is not None:
        # a fault's duration runs on the run's fault clock, which is not the operator's wall clock under virtual
        # time: said on stderr, so that stdout stays the processes' answers
        print(f"faults: {command.spec.id}: {duration_clock(command.spec.duration, args.output_dir, args.run)}",
              file=sys.stderr)
    if getattr(args, "each", False):
        for reply in replies:
            print(reply.model_dump_json(exclude_none=True))
    else:
        for group in merge(replies):
            print(json.dumps(group))
    return 0 if all(r.ok for r in replies) else 1
