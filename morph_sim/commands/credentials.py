"""``morph-sim credentials --run-id ID --out DIR``: a run's credentials and access control as files, for processes
that ``morph-sim up`` does not start (compose, Kubernetes, by hand).

Writes what ``up`` writes into ``runs/<id>/credentials/`` (owner-only): ``endpoint.json5`` for the sim that hosts
the endpoint, ``operator.json5``, ``monitor.json5`` and ``agent-<N>.json5`` for the others, and ``passwords.txt``.
Start each process with ``ZENOH_CONFIG`` naming its file (docs/deploy.md). ``--mounted-at DIR`` writes them for
containers that mount them under DIR (compose secrets, Kubernetes Secrets).
"""

from __future__ import annotations

import argparse

NAME = "credentials"
HELP = "write a run's per-process credentials and the endpoint's access control (for compose / by-hand runs)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runconfig import add_config_arguments

    parser.add_argument("--out", required=True, help="directory to write (created 0700; files 0600)")
    parser.add_argument("--mounted-at", default=None, metavar="DIR",
                        help="where the processes will see these files, e.g. a container's secrets mount "
                             "/run/secrets/morph: the endpoint's config names DIR/passwords.txt, and the files are "
                             "0644 inside the 0700 directory so that a container user other than yours can read "
                             "the one mounted into it")
    add_config_arguments(parser, skip=("listen", "endpoint"))


def run(args: argparse.Namespace) -> int:
    from services.credentials import RunCredentials
    from services.inputs import output_dir
    from services.runconfig import RunConfig, config_from_args

    if getattr(args, "cfg_run_id", None) is None and not __import__("os").environ.get(RunConfig.env_name("run_id")):
        raise ValueError("run_id: credentials are per run; pass --run-id (or MORPH_RUN_ID)")
    config = config_from_args(args)
    out = output_dir(args.out, "out")
    mounted_at = args.mounted_at
    if mounted_at is not None and not mounted_at.startswith("/"):
        raise ValueError(f"mounted_at: {mounted_at!r} must be an absolute path (where a container mounts the files)")
    creds = RunCredentials.create(out, config.run_id, config.n_agents, mounted_at=mounted_at)
    print(f"run {config.run_id}: credentials for the operator, the monitor and {config.n_agents} agents in "
          f"{creds.directory} (sim: ZENOH_CONFIG={creds.endpoint})")
    return 0
