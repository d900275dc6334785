"""``morph-sim stop --run ID``: ask a running run to end (``ctl/stop``), as the operator.

The sim finishes the current tick, publishes its final tick and ``run.finished``, and every process leaves; ``up``
reports the run as stopped from outside. A secured run only accepts this with the operator's credentials (found in
the run directory, or ``--credentials FILE`` / ``ZENOH_CONFIG``).
"""

from __future__ import annotations

import argparse
import asyncio

NAME = "stop"
HELP = "stop a running run (ctl/stop) with the operator's credentials"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.process import add_operator_arguments

    parser.add_argument("--run", required=True, help="run id (key prefix morph/<run>/)")
    parser.add_argument("--reason", default="operator stop", help="reason recorded with the stop")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the sim to hear it")
    add_operator_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from schemas import Stop
    from schemas.keys import RunKeys, validate_run_id
    from services.inputs import finite
    from services.process import open_operator_bus, operator_endpoint

    keys = RunKeys(validate_run_id(args.run))
    finite(args.timeout, "timeout", above=0)
    endpoint = operator_endpoint(args, args.run)  # checks it, and the other operator options

    async def main() -> bool:
        bus = await open_operator_bus("operator-stop", endpoint, args, args.run)
        try:
            try:  # a put made before the sim's subscription is known here would be lost silently
                await bus.wait_for_subscribers(keys.stop, timeout=args.timeout)
            except TimeoutError:
                return False
            await bus.publish(keys.stop, Stop(reason=args.reason))
            await asyncio.sleep(0.2)  # let the put leave before the session closes
            return True
        finally:
            await bus.close()

    if not asyncio.run(main()):
        print(f"morph-sim stop: error: nobody of run {args.run!r} listens on {endpoint}")
        return 1
    print(f"run {args.run}: stop sent ({args.reason})")
    return 0
