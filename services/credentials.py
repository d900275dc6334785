"""Per-run credentials and the matching Zenoh access control: a run is closed to everyone it did not invite.

``morph-sim up`` (and ``morph-sim credentials`` for compose, Kubernetes or hand-started processes) writes one
directory per run, owner-only (0700, every file 0600)::

    passwords.txt        user:password lines, read by the endpoint (Zenoh's usrpwd dictionary)
    endpoint.json5       the endpoint's config: user/password authentication + access control for this run id
    operator.json5       the operator's client config (up's supervisor, watch, faults, record, stop)
    monitor.json5        the monitor's client config
    air.json5            the shared air's client config (used by runs whose network profile limits rates)
    agent-<N>.json5      robot N's client config
    where                the endpoint the run is hosted on (not a secret: how ``watch`` finds the run's files)

A process is handed its file through ``ZENOH_CONFIG`` (the variable names a file; no secret is ever on a command
line, where ``ps`` shows it). The sim hosts the endpoint with ``endpoint.json5``; every other process connects with its
own file. What the access control allows (default deny; docs/deploy.md shows the table):

* every user may subscribe and watch liveliness under the run, and receive what is routed to it;
* robot N may publish only under ``agent/N/**``, ``alive/N`` and ``events/N``, and answer fault-list queries; it
  alone receives its on-board state ``sim/@onboard/N``;
* the monitor publishes ``metrics/**``, its token and events, and answers ``state/**``;
* the air (a rate-limited network profile's radio) publishes its verdicts ``air/verdict/**``, its per access point
  counters ``air/stats``, its token and events;
* ``up``'s supervisor connects as the operator and answers fault queries for the crash faults it carries out;
* only the operator may put on ``ctl/**`` (stop, faults), query ``ctl/faults`` (``faults set`` is a query) and publish
  the supervisor's events; nobody else may query ``ctl/**``;
* the sim publishes ``sim/**``, ``events/sim`` and the end-of-run ``ctl/stop`` from inside the endpoint (its own
  session is not an ingress), so no connecting user can speak as the sim.

The endpoint also drops any message larger than :data:`MAX_MESSAGE_BYTES` on arrival (Zenoh's ``low_pass_filter``),
in secure and insecure mode alike: see :func:`size_limits`.
"""

from __future__ import annotations

import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from schemas.keys import ONBOARD, ROOT, validate_run_id

DIRNAME = "credentials"
ENDPOINT_FILE = "endpoint.json5"
PASSWORDS_FILE = "passwords.txt"
WHERE_FILE = "where"
OPERATOR = "operator"
MONITOR = "monitor"
AIR = "air"
#: the bus identity of `morph-sim up`'s supervisor (it connects with the operator's credentials)
SUPERVISOR = "supervisor"

# The embedded endpoint runs Zenoh's lowlatency transport, which cannot fragment: one message that does not fit a
# link's batch closes that link. The endpoint reassembles a large message from a client that fragments and then
# fails to forward it to every lowlatency subscriber at once, dropping every agent's session (measured with zenoh
# 1.10.2: 48.5 KB forwarded, 50 KB disconnected every subscriber). The largest message of a run is a Tick (about
# 45 bytes per robot: 1.2 KB for 24 robots), so 32 KiB leaves room for ~700 robots and a margin below the failure.
from schemas.limits import MAX_MESSAGE_BYTES  # noqa: E402


def user_of_agent(agent: int) -> str:
    return f"agent-{int(agent)}"


def size_limits() -> list[dict]:
    """The endpoint's ``low_pass_filter``: oversized data messages never get past the endpoint's ingress."""
    return [{
        "id": "message-size",
        "flows": ["ingress"],
        "messages": ["put", "delete", "query", "reply"],
        "key_exprs": ["**"],
        "size_limit": MAX_MESSAGE_BYTES,
    }]


def access_control(run_id: str, n_agents: int) -> dict:
    """Zenoh ``access_control`` for run ``run_id`` with robots ``0..n_agents-1`` (users named as in this module)."""
    run = f"{ROOT}/{validate_run_id(run_id)}"
    pub = ["put", "delete", "liveliness_token"]
    agents = [user_of_agent(a) for a in range(n_agents)]
    everyone = [OPERATOR, MONITOR, AIR, *agents]
    rules = [
        # morph/** rather than this run's prefix: a subscriber on morph/*/metrics/** (any run on this endpoint,
        # which hosts only this one) must be allowed too; observing publishes nothing
        {"id": "observe", "flows": ["ingress", "egress"], "permission": "allow",
         "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
         "key_exprs": [f"{ROOT}/**"]},
        {"id": "receive", "flows": ["egress"], "permission": "allow",
         "messages": ["put", "delete", "reply", "query", "liveliness_token", "declare_queryable"],
         "key_exprs": [f"{run}/**"]},
        {"id": "ask", "flows": ["ingress"], "permission": "allow", "messages": ["query"],
         "key_exprs": [f"{run}/registry", f"{run}/registry/policy", f"{run}/state/**"]},
        {"id": "monitor-publish", "flows": ["ingress"], "permission": "allow", "messages": pub,
         "key_exprs": [f"{run}/metrics/**", f"{run}/alive/{MONITOR}", f"{run}/events/{MONITOR}"]},
        {"id": "monitor-serve", "flows": ["ingress"], "permission": "allow",
         "messages": ["declare_queryable", "reply"], "key_exprs": [f"{run}/state/**"]},
        # the shared air (a rate-limited profile's radio) gives each receiver its verdicts
        {"id": "air-publish", "flows": ["ingress"], "permission": "allow", "messages": pub,
         "key_exprs": [f"{run}/air/verdict/**", f"{run}/air/stats", f"{run}/alive/{AIR}", f"{run}/events/{AIR}"]},
        {"id": "operator-control", "flows": ["ingress"], "permission": "allow", "messages": ["put", "delete"],
         "key_exprs": [f"{run}/ctl/**", f"{run}/events/supervisor"]},
        {"id": "operator-query", "flows": ["ingress"], "permission": "allow", "messages": ["query"],
         "key_exprs": [f"{run}/**"]},
    ]
    policies = [
        {"id": "everyone", "rules": ["observe", "receive", "ask"], "subjects": everyone},
        {"id": "monitor", "rules": ["monitor-publish", "monitor-serve", "monitor-fault-answers"], "subjects": [MONITOR]},
        {"id": "air", "rules": ["air-publish", "air-fault-answers"], "subjects": [AIR]},
        {"id": "operator", "rules": ["operator-control", "operator-query", "operator-fault-answers"],
         "subjects": [OPERATOR]},
    ]
    # each process answers fault queries under its own key only (schemas/keys.py fault_answers), so an answer's key
    # says who gave it; up's supervisor (operator credentials) carries out crash faults and answers for them
    for rule, identity in (("monitor-fault-answers", MONITOR), ("operator-fault-answers", SUPERVISOR),
                           ("air-fault-answers", AIR)):
        rules.append({"id": rule, "flows": ["ingress"], "permission": "allow", "messages": ["declare_queryable", "reply"],
                      "key_exprs": [f"{run}/ctl/faults/{identity}"]})
    for agent, user in enumerate(agents):
        rules.append({"id": f"{user}-publish", "flows": ["ingress"], "permission": "allow", "messages": pub,
                      "key_exprs": [f"{run}/agent/{agent}/**", f"{run}/alive/{agent}", f"{run}/events/{agent}"]})
        # its own on-board state, and nobody else's (a verbatim chunk: no run-wide expression above reaches it)
        onboard = f"{run}/{ONBOARD.removesuffix('*')}{agent}"
        rules.append({"id": f"{user}-sense", "flows": ["ingress", "egress"], "permission": "allow",
                      "messages": ["declare_subscriber"], "key_exprs": [onboard]})
        rules.append({"id": f"{user}-sensed", "flows": ["egress"], "permission": "allow", "messages": ["put"],
                      "key_exprs": [onboard]})
        rules.append({"id": f"{user}-fault-answers", "flows": ["ingress"], "permission": "allow",
                      "messages": ["declare_queryable", "reply"], "key_exprs": [f"{run}/ctl/faults/{user}"]})
        policies.append({"id": user, "rules": [f"{user}-publish", f"{user}-sense", f"{user}-sensed",
                                               f"{user}-fault-answers"], "subjects": [user]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": user, "usernames": [user]} for user in everyone],
        "policies": policies,
    }


def endpoint_config(run_id: str, n_agents: int, passwords_file: Path) -> dict:
    """The endpoint's Zenoh config (JSON): authentication, access control, size limit. ``passwords_file`` is where
    the endpoint's process reads the passwords, an absolute path (Zenoh would resolve a relative one against its
    working directory)."""
    return {
        "transport": {"auth": {"usrpwd": {"dictionary_file": str(passwords_file)}}},
        "access_control": access_control(run_id, n_agents),
        "low_pass_filter": size_limits(),
    }


def client_config(user: str, password: str) -> dict:
    return {"transport": {"auth": {"usrpwd": {"user": user, "password": password}}}}


def _write_private(path: Path, text: str, mode: int = 0o600) -> None:
    """Create ``path`` with ``mode`` (default 0600) from the start (never wider, not even for a moment)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        with os.fdopen(fd, "w") as out:
            out.write(text)
    except OSError as exc:  # a failed write names no file of its own: name the one it was writing
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    os.chmod(path, mode)  # an existing file keeps its old mode through O_CREAT


@dataclass(frozen=True)
class RunCredentials:
    """The credentials directory of one run (see the module docstring)."""

    directory: Path

    @property
    def endpoint(self) -> Path:
        return self.directory / ENDPOINT_FILE

    @property
    def operator(self) -> Path:
        return self.directory / f"{OPERATOR}.json5"

    @property
    def monitor(self) -> Path:
        return self.directory / f"{MONITOR}.json5"

    def agent(self, agent: int) -> Path:
        return self.directory / f"{user_of_agent(agent)}.json5"

    def for_role(self, role: str, agent: int | None = None) -> Path:
        """The config file a process of ``role`` is started with."""
        if role == "sim":
            return self.endpoint
        if role == "monitor":
            return self.monitor
        if role == "air":
            return self.directory / f"{AIR}.json5"
        if role == "agent":
            assert agent is not None
            return self.agent(agent)
        return self.operator

    @classmethod
    def create(cls, directory: Path, run_id: str, n_agents: int, where: str | None = None,
               mounted_at: str | None = None) -> RunCredentials:
        """Fresh random passwords for the operator, the monitor and every robot, written owner-only.

        ``mounted_at``: the directory in which the processes will see these files (a container's secrets mount),
        so the endpoint's config names the passwords file there. The directory stays owner-only, and its files are
        written readable by others (0644): a container's user is not the host's, and a file mounted from the host
        keeps the host's owner and mode, so an owner-only file could not be read in the container."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(directory, 0o700)
        mode = 0o600 if mounted_at is None else 0o644
        users = [OPERATOR, MONITOR, AIR, *(user_of_agent(a) for a in range(n_agents))]
        passwords = {user: secrets.token_urlsafe(24) for user in users}
        creds = cls(directory)
        _write_private(directory / PASSWORDS_FILE, "".join(f"{u}:{p}\n" for u, p in passwords.items()), mode)
        # a path in the container is taken as it is: resolving it would follow this machine's links
        seen_at = directory.resolve() if mounted_at is None else Path(mounted_at)
        _write_private(creds.endpoint, json.dumps(
            endpoint_config(run_id, n_agents, seen_at / PASSWORDS_FILE), indent=1) + "\n", mode)
        for user, password in passwords.items():
            _write_private(directory / f"{user}.json5", json.dumps(client_config(user, password)) + "\n", mode)
        if where:
            _write_private(directory / WHERE_FILE, where + "\n", mode)
        return creds


def run_credentials(record_dir: Path) -> RunCredentials:
    """Where ``up`` keeps a run's credentials: ``<record>/credentials``."""
    return RunCredentials(Path(record_dir) / DIRNAME)


def operator_config_path(record_dir: Path, environ: dict[str, str] | None = None) -> str | None:
    """The Zenoh config an operator command (watch, faults, record, stop) connects with: ``ZENOH_CONFIG`` if set,
    else the run's ``credentials/operator.json5`` if the run directory has one, else None (an insecure run)."""
    env = os.environ if environ is None else environ
    if env.get("ZENOH_CONFIG"):
        return env["ZENOH_CONFIG"]
    path = run_credentials(record_dir).operator
    return str(path) if path.is_file() else None


def find_operator_config(output_dir: Path, where: str) -> str | None:
    """The operator config of the newest run under ``output_dir`` hosted on endpoint ``where`` (``watch --endpoint``
    without ``--run``), or None."""
    found = []
    for path in Path(output_dir).glob(f"*/{DIRNAME}/{WHERE_FILE}"):
        try:
            if path.read_text().strip() == where and (path.parent / f"{OPERATOR}.json5").is_file():
                found.append((path.stat().st_mtime, path.parent / f"{OPERATOR}.json5"))
        except OSError:
            continue
    return str(max(found)[1]) if found else None
