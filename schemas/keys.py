"""Key expressions of a run: the ONE place that spells them, plus Zenoh's key-expression matching rules.

Everything of a run lives under ``morph/<run>/``::

    sim/tick                      Tick            sim -> monitor, tools (the world record; robots do not read it)
    sim/fleet                     Tick            sim -> robots: the fleet broadcast (a network message, faultable)
    sim/@onboard/<id>             OnBoard         sim -> that robot: its on-board state (not faulted by default)
    sim/resolve                   Resolve         sim -> all
    agent/<id>/ack                Ack             agent -> sim
    agent/<id>/skip               Ack             agent -> sim (virtual time: its Tick/Resolve was lost; never faulted)
    agent/<agv>/request/<picker>  HelpRequest     AGV -> picker
    agent/<picker>/reply/<agv>    HelpReply       picker -> AGV
    agent/<picker>/commit         Commit          picker -> sim
    agent/<id>/state              AgentState      agent -> monitor
    metrics/<name>                MetricSample    monitor -> anyone
    state/**                      (queryable)     monitor: latest values for late joiners
    ctl/faults                    FaultCommand    operator -> everyone (put)
    ctl/faults/<identity>         (queryable)     each process: a FaultCommand query, its FaultReply under its own key
    ctl/stop                      Stop            operator/supervisor -> everyone
    events/<source>               Event           anyone -> monitor
    registry                      (queryable)     sim: RegistrationRequest -> RegistrationReply
    alive/<id>                    liveliness token of a service or agent

Why every agent-sent key starts with ``agent/<sender>/``: Zenoh access control (docs/deploy.md) lets an agent publish only under
its own prefix, and the fault layer reads the link (sender, receiver) of a message off its key. So a help request is
addressed ``agent/<agv>/request/<picker>`` (the picker subscribes to ``agent/*/request/<picker>``) and a commit is
``agent/<picker>/commit`` rather than a shared ``sim/commit``.

Matching follows Zenoh's rules: chunks are separated by ``/``; ``*`` matches exactly one chunk, ``**`` zero or more;
chunks starting with ``@`` are verbatim (only matched by themselves, never by a wildcard); expressions must be
canonical (``**/**`` and ``**/*`` are rejected, ``*/**`` is the canonical spelling). The sub-chunk wildcard ``$*`` is
not supported by this project (both buses reject it).
"""

from __future__ import annotations

import re
from functools import cached_property, lru_cache

ROOT = "morph"
#: the fleet broadcast and the on-board state, relative to ``morph/<run>/`` (fault scopes, the lab's network)
FLEET = "sim/fleet"
#: ``@onboard`` is a verbatim chunk: no wildcard matches it, so a robot's on-board state is outside ``morph/<run>/**``
#: (the monitor's, a recorder's and the access control's whole-run expressions) and outside every fault scope that
#: does not name it: sensing is not networking. Only robot N may subscribe to its own (services/credentials.py).
ONBOARD = "sim/@onboard/*"

# Characters allowed in a run id and in a single literal chunk we build: no '/', no wildcards, no '$#?' (Zenoh
# reserves them), no spaces; printable so ids survive logs, file names and environment variables.
_CHUNK_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")
_FORBIDDEN = set("#?$ \t\r\n")


def check_chunk(value: str, what: str) -> str:
    if not isinstance(value, str) or not _CHUNK_RE.match(value):
        raise ValueError(
            f"{what} {value!r} is not a valid key chunk: use 1-64 characters from A-Z a-z 0-9 _ . - "
            "(not starting with '.' or '-'; no '/', '*', '$', '#', '?', spaces)"
        )
    return value


def validate_run_id(run: str) -> str:
    """Return ``run`` if it is a safe run id, else raise ValueError naming it."""
    return check_chunk(run, "run id")


@lru_cache(maxsize=8192)  # services validate the same few keys on every publish
def validate_key_expr(expr: str) -> str:
    """Return ``expr`` if it is a canonical key expression this project accepts, else raise ValueError."""
    if not isinstance(expr, str) or not expr:
        raise ValueError(f"key expression {expr!r} is empty")
    if expr.startswith("/") or expr.endswith("/"):
        raise ValueError(f"key expression {expr!r} must not start or end with '/'")
    bad = _FORBIDDEN.intersection(expr)
    if bad:
        raise ValueError(f"key expression {expr!r} contains forbidden characters {''.join(sorted(bad))!r}")
    chunks = expr.split("/")
    for i, chunk in enumerate(chunks):
        if chunk == "":
            raise ValueError(f"key expression {expr!r} has an empty chunk (double '/')")
        if "*" in chunk and chunk not in ("*", "**"):
            raise ValueError(f"key expression {expr!r}: '*' must be a whole chunk, got {chunk!r}")
        if chunk == "**" and i + 1 < len(chunks) and chunks[i + 1] in ("*", "**"):
            canon = "/".join(_canonize(chunks))
            raise ValueError(f"key expression {expr!r} is not canonical; write {canon!r}")
    return expr


def _canonize(chunks: list[str]) -> list[str]:
    # Zenoh's canonical form: '**/*' -> '*/**', '**/**' -> '**'.
    out = list(chunks)
    changed = True
    while changed:
        changed = False
        for i in range(len(out) - 1):
            if out[i] == "**" and out[i + 1] == "**":
                del out[i + 1]
                changed = True
                break
            if out[i] == "**" and out[i + 1] == "*":
                out[i], out[i + 1] = "*", "**"
                changed = True
                break
    return out


def is_concrete(key: str) -> bool:
    """True if ``key`` names one key (no wildcard chunk)."""
    return "*" not in key


@lru_cache(maxsize=8192)
def validate_key(key: str) -> str:
    """A key to publish on: a valid key expression without wildcards."""
    validate_key_expr(key)
    if not is_concrete(key):
        raise ValueError(f"key {key!r} contains a wildcard; publish needs a concrete key")
    return key


@lru_cache(maxsize=16384)
def intersects(a: str, b: str) -> bool:
    """True if some concrete key matches both expressions (Zenoh's ``KeyExpr.intersects``)."""
    return _intersects(tuple(a.split("/")), tuple(b.split("/")))


def matches(expr: str, key: str) -> bool:
    """True if the concrete ``key`` is matched by ``expr``."""
    return intersects(expr, key)


def _verbatim(chunk: str) -> bool:
    return chunk.startswith("@")


def _intersects(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    memo: dict[tuple[int, int], bool] = {}

    def go(i: int, j: int) -> bool:
        hit = memo.get((i, j))
        if hit is not None:
            return hit
        if i == len(a) and j == len(b):
            res = True
        elif i == len(a):
            res = all(c == "**" for c in b[j:])
        elif j == len(b):
            res = all(c == "**" for c in a[i:])
        else:
            ca, cb = a[i], b[j]
            if ca == "**" or cb == "**":
                res = False
                if ca == "**":
                    # '**' matches nothing more, or swallows b's chunk (never a verbatim one).
                    res = go(i + 1, j) or (cb != "**" and not _verbatim(cb) and go(i, j + 1))
                if not res and cb == "**":
                    res = go(i, j + 1) or (ca != "**" and not _verbatim(ca) and go(i + 1, j))
                if not res and ca == "**" and cb == "**":
                    res = go(i + 1, j + 1)
            elif ca == cb or (ca == "*" and not _verbatim(cb)) or (cb == "*" and not _verbatim(ca)):
                res = go(i + 1, j + 1)
            else:
                res = False
        memo[(i, j)] = res
        return res

    return go(0, 0)


def _agent_chunk(agent: int | str) -> str:
    if isinstance(agent, bool):
        raise ValueError(f"agent id {agent!r} must be an int >= 0 or a service name")
    if isinstance(agent, int):
        if agent < 0:
            raise ValueError(f"agent id {agent} must be >= 0")
        return str(agent)
    return check_chunk(agent, "agent id")


def parse_agent_id(chunk: str) -> int | str:
    """The agent id a key chunk stands for: an int for robots, the name for services (``sim``, ``monitor``)."""
    return int(chunk) if chunk.isdigit() else chunk


#: what a robot publishes under its own keys ``agent/<id>/<kind>``; ``request``, ``reply`` and ``policy`` name their
#: receiver in one more chunk (a robot id; ``policy`` also ``all``), the others end there
ROBOT_KINDS = ("ack", "skip", "request", "reply", "policy", "commit", "state")
ADDRESSED_KINDS = ("request", "reply", "policy")


def check_robot_key(rel: list[str], n_agents: int) -> None:
    """ValueError unless ``rel`` (a key's chunks after the run, ``["agent", id, kind, ...]``) is a key a robot of a
    fleet of ``n_agents`` publishes on: a receiver that takes every key of the run keeps per-key state (counts,
    sequence numbers) only for these, never for new sub-keys a robot makes up."""
    if len(rel) < 3 or rel[2] not in ROBOT_KINDS:
        raise ValueError(f"no message kind {'/'.join(rel[2:])[:64]!r} under a robot's keys")
    robot = parse_agent_id(rel[1])
    if not isinstance(robot, int) or not 0 <= robot < n_agents:
        raise ValueError(f"robot {rel[1][:16]!r} outside 0..{n_agents - 1}")
    if rel[2] in ADDRESSED_KINDS:
        to = rel[3] if len(rel) == 4 else ""
        receiver = parse_agent_id(to)
        if not (to == "all" and rel[2] == "policy" or isinstance(receiver, int) and 0 <= receiver < n_agents):
            raise ValueError(f"{rel[2]} to {'/'.join(rel[3:])[:32]!r}: not a robot of the fleet")
    elif len(rel) != 3:
        raise ValueError(f"no message kind {'/'.join(rel[2:])[:64]!r} under a robot's keys")


class RunKeys:
    """Key expressions of one run. ``RunKeys("r1").tick == "morph/r1/sim/tick"``. (The keys without arguments are
    built once: handlers on the hot path name them for every message.)"""

    def __init__(self, run: str):
        self.run = validate_run_id(run)
        self.prefix = f"{ROOT}/{run}"
        self._senders: dict[str, int | str | None] = {}  # key -> sender_of(key): every message asks it, twice
        self._metric_keys: dict[str, str] = {}  # stream name -> its key

    def _k(self, *chunks: str) -> str:
        return "/".join((self.prefix, *chunks))

    # -- whole run ---------------------------------------------------------------------------------------------
    @cached_property
    def everything(self) -> str:
        return self._k("**")

    # -- sim clock ---------------------------------------------------------------------------------------------
    @cached_property
    def tick(self) -> str:
        return self._k("sim", "tick")

    @cached_property
    def fleet(self) -> str:
        """The fleet broadcast: the whole fleet's state as the robots receive it over the network."""
        return self._k("sim", "fleet")

    def onboard(self, robot: int) -> str:
        """One robot's own state as its on-board sensing gives it (never through the network)."""
        return self._k("sim", "@onboard", _agent_chunk(robot))

    @cached_property
    def resolve(self) -> str:
        return self._k("sim", "resolve")

    def refusal(self, agent: int) -> str:
        """The sim tells an AGV and a picker that their commitment was no longer valid when it arrived."""
        return self._k("sim", "refusal", _agent_chunk(agent))

    # -- the shared air (a profile with rate-limited queues) ----------------------------------------------------
    @cached_property
    def air_parts(self) -> str:
        """The sim tells the air what was published at an instant (schemas.messages.AirPart)."""
        return self._k("air", "part")

    @cached_property
    def air_stats(self) -> str:
        """The air's per access point load, queue and drops, once a tick (schemas.messages.AirStats)."""
        return self._k("air", "stats")

    def air_verdicts(self, receiver: int | str) -> str:
        """The air's verdicts on the radio messages to ``receiver`` (a robot id, or ``sim``)."""
        return self._k("air", "verdict", _agent_chunk(receiver))

    # -- agents ------------------------------------------------------------------------------------------------
    def ack(self, agent: int | str) -> str:
        return self._k("agent", _agent_chunk(agent), "ack")

    @cached_property
    def acks(self) -> str:
        return self._k("agent", "*", "ack")

    def skip(self, agent: int | str) -> str:
        """An agent's "I will not answer this phase" (its Tick or Resolve was lost or held in virtual time)."""
        return self._k("agent", _agent_chunk(agent), "skip")

    @cached_property
    def skips(self) -> str:
        return self._k("agent", "*", "skip")

    def request(self, agv: int, picker: int) -> str:
        return self._k("agent", _agent_chunk(agv), "request", _agent_chunk(picker))

    def requests_to(self, picker: int) -> str:
        return self._k("agent", "*", "request", _agent_chunk(picker))

    @cached_property
    def requests(self) -> str:
        return self._k("agent", "*", "request", "*")

    def reply(self, picker: int, agv: int) -> str:
        return self._k("agent", _agent_chunk(picker), "reply", _agent_chunk(agv))

    def replies_to(self, agv: int) -> str:
        return self._k("agent", "*", "reply", _agent_chunk(agv))

    @cached_property
    def replies(self) -> str:
        return self._k("agent", "*", "reply", "*")

    def policy(self, sender: int, to: int | None) -> str:
        """Robot ``sender``'s policy message to robot ``to`` (None: to every other robot)."""
        return self._k("agent", _agent_chunk(sender), "policy", "all" if to is None else _agent_chunk(to))

    def policies_to(self, robot: int) -> str:
        """Every policy message addressed to ``robot`` alone."""
        return self._k("agent", "*", "policy", _agent_chunk(robot))

    @cached_property
    def policies_to_all(self) -> str:
        """Every policy message addressed to every robot."""
        return self._k("agent", "*", "policy", "all")

    def commit(self, picker: int) -> str:
        return self._k("agent", _agent_chunk(picker), "commit")

    @cached_property
    def commits(self) -> str:
        return self._k("agent", "*", "commit")

    def agent_state(self, agent: int | str) -> str:
        return self._k("agent", _agent_chunk(agent), "state")

    @cached_property
    def agent_states(self) -> str:
        return self._k("agent", "*", "state")

    def agent_prefix(self, agent: int | str) -> str:
        """Everything an agent may publish (access-control prefix)."""
        return self._k("agent", _agent_chunk(agent), "**")

    # -- monitor -----------------------------------------------------------------------------------------------
    def metric(self, name: str) -> str:
        key = self._metric_keys.get(name)
        if key is None:  # the monitor publishes a few dozen streams, each many times
            if len(self._metric_keys) >= 4096:
                self._metric_keys.clear()
            key = self._k("metrics", *(check_chunk(c, "metric name chunk") for c in name.split("/")))
            self._metric_keys[name] = key  # a bad name raises above and is not kept
        return key

    @cached_property
    def metrics(self) -> str:
        return self._k("metrics", "**")

    def latest(self, *chunks: str) -> str:
        """A key of the monitor's latest-state queryable, e.g. ``latest("agent", "3")``."""
        return self._k("state", *(check_chunk(c, "state key chunk") for c in chunks))

    @cached_property
    def latest_all(self) -> str:
        return self._k("state", "**")

    # -- control, events, registry, liveliness -------------------------------------------------------------------
    @cached_property
    def faults(self) -> str:
        return self._k("ctl", "faults")

    def fault_answers(self, identity: str) -> str:
        """Where the process ``identity`` (its bus identity: sim, monitor, supervisor, agent-<id>) takes fault
        queries and answers them. Access control lets only that process declare and reply there, so the key of an
        answer says who gave it (an answer's own ``source`` field is only what its author claims)."""
        return self._k("ctl", "faults", check_chunk(identity, "fault answer identity"))

    @cached_property
    def fault_queries(self) -> str:
        """What ``morph-sim faults`` queries: every process's :meth:`fault_answers` key."""
        return self._k("ctl", "faults", "*")

    @cached_property
    def stop(self) -> str:
        return self._k("ctl", "stop")

    def event(self, source: int | str) -> str:
        return self._k("events", _agent_chunk(source))

    @cached_property
    def events(self) -> str:
        return self._k("events", "*")

    @cached_property
    def registry(self) -> str:
        return self._k("registry")

    @cached_property
    def registry_policy(self) -> str:
        """The sim's announcement of the run's policy (:class:`~schemas.messages.PolicyAnnouncement`)."""
        return self._k("registry", "policy")

    def alive(self, agent: int | str) -> str:
        return self._k("alive", _agent_chunk(agent))

    @cached_property
    def alive_all(self) -> str:
        return self._k("alive", "*")

    # -- parsing -------------------------------------------------------------------------------------------------
    def local(self, key: str) -> str:
        """``key`` without ``morph/<run>/`` (the form the fault layer, the air and the lab name a key by)."""
        return "/".join(self.relative(key))

    def relative(self, key: str) -> list[str]:
        """The chunks of ``key`` after ``morph/<run>/``; ValueError if the key is not of this run."""
        head = self.prefix + "/"
        if not key.startswith(head):
            raise ValueError(f"key {key!r} is not under {head!r}")
        return key[len(head):].split("/")

    def sender_of(self, key: str) -> int | str | None:
        """The agent that published ``key`` (``agent/<id>/…``), the service for ``sim/…``, else None."""
        senders = self._senders
        if key in senders:
            return senders[key]
        if len(senders) >= 4096:  # keys nobody planned (a fuzzer's): the table stays bounded
            senders.clear()
        who = senders[key] = self._sender_of(key)  # a key not of this run raises and is not kept
        return who

    def _sender_of(self, key: str) -> int | str | None:
        rel = self.relative(key)
        if len(rel) >= 2 and rel[0] == "agent":
            return parse_agent_id(rel[1])
        if rel[0] == "sim":
            return "sim"
        if rel[0] == "air":
            return "air"
        if rel[0] == "events" and len(rel) == 2:
            return parse_agent_id(rel[1])
        return None

    def check_author(self, key: str, author: int | str, what: str) -> None:
        """ValueError unless ``key`` lies under ``author``'s own prefix: a message that names its author (an ack's
        agent, a commit's picker) must come from that author (as the access control of docs/deploy.md wants; enforced in the services)."""
        sender = self.sender_of(key)
        if sender != author:
            raise ValueError(f"{what} {author} on the key of {sender}")

    def recipient_of(self, key: str) -> int | str | None:
        """The addressee of a point-to-point key (request/reply), ``sim`` for ack/commit, else None (broadcast)."""
        rel = self.relative(key)
        if len(rel) == 4 and rel[0] == "agent" and rel[2] in ("request", "reply", "policy") and rel[3] != "all":
            return parse_agent_id(rel[3])
        if len(rel) == 3 and rel[0] == "agent" and rel[2] in ("ack", "commit"):
            return "sim"
        if len(rel) == 3 and rel[0] == "sim" and rel[1] == "@onboard":
            return parse_agent_id(rel[2])
        return None

    def alive_id(self, key: str) -> int | str:
        rel = self.relative(key)
        if len(rel) != 2 or rel[0] != "alive":
            raise ValueError(f"key {key!r} is not a liveliness key of run {self.run!r}")
        return parse_agent_id(rel[1])
