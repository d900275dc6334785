"""The security sample of deploy/zenoh/, loaded by live Zenoh 1.10.2 sessions on 127.0.0.1.

A router session opens with ``deploy/zenoh/router.json5`` (user/password authentication + access control) exactly as
shipped, only its listen endpoint and the credentials path are pointed at this machine. Clients authenticate with
the users of ``deploy/zenoh/credentials.txt`` (the two ``client-*.json5`` samples are loaded as files). Every refusal
is checked against a positive control sent right after it on the same session: a client's messages reach the router
in order, so once the allowed sentinel has arrived, a refused message that was going to arrive would have arrived.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import pytest

from schemas.keys import RunKeys
from services.bus.registry import claim_id, mount_registry
from services.bus.zenoh_bus import ZenohBus, endpoint, free_port, zenoh_config

# isort: split
import zenoh  # noqa: E402  (after zenoh_bus set the runtime environment)

DEPLOY = Path(__file__).resolve().parent.parent / "deploy" / "zenoh"
RUN = "acl"
KEYS = RunKeys(RUN)


def _passwords() -> dict[str, str]:
    out = {}
    for line in (DEPLOY / "credentials.txt").read_text().splitlines():
        if line.strip():
            user, _, password = line.partition(":")
            out[user] = password
    return out


PASSWORDS = _passwords()


@pytest.fixture(scope="module")
def router():
    where = endpoint(free_port())
    cfg = zenoh.Config.from_file(str(DEPLOY / "router.json5"))
    cfg.insert_json5("listen/endpoints", json.dumps([where]))
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(DEPLOY / "credentials.txt")))
    assert json.loads(cfg.get_json("access_control/enabled")) is True
    assert json.loads(cfg.get_json("access_control/default_permission")) == "deny"
    session = zenoh.open(cfg)
    try:
        yield where
    finally:
        session.close()


def _client_config(where: str, user: str | None, password: str | None = None, timeout: float = 5.0):
    """The project's own client configuration (ZenohBus) plus the user's credentials."""
    cfg = zenoh_config(connect=where, mode="client", connect_timeout=timeout)
    if user is not None:
        cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        secret = PASSWORDS[user] if password is None else password
        cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(secret))
    return cfg


class Observer:
    """A monitor-credentialled subscriber on the whole run: records (key, payload) in arrival order."""

    def __init__(self, where: str):
        self.session = zenoh.open(_client_config(where, "monitor"))
        self.seen: list[tuple[str, bytes]] = []
        self.probed = threading.Event()  # a readiness probe came through the router (probes are not recorded)
        self._cond = threading.Condition()
        self._sub = self.session.declare_subscriber(KEYS.everything, self._on)

    def _on(self, sample) -> None:
        if sample.payload.to_bytes() == b"probe":
            self.probed.set()
            return
        with self._cond:
            self.seen.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cond.notify_all()

    def wait_for(self, key: str, payload: bytes, timeout: float = 5.0) -> list[tuple[str, bytes]]:
        deadline = time.monotonic() + timeout
        with self._cond:
            while (key, payload) not in self.seen:
                left = deadline - time.monotonic()
                assert left > 0, f"allowed message {key} never arrived; seen {self.seen}"
                self._cond.wait(left)
            return list(self.seen)

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def observer(router):
    obs = Observer(router)
    # Declarations propagate asynchronously: probe through the router until the subscription is in place.
    prober = zenoh.open(_client_config(router, "sim"))
    try:
        deadline = time.monotonic() + 10.0
        while not obs.probed.is_set():
            assert time.monotonic() < deadline, "the observer's subscription never reached the router"
            prober.put(KEYS.tick, b"probe")
            obs.probed.wait(0.05)
    finally:
        prober.close()
    yield obs
    obs.close()


def _open(where: str, user: str):
    return zenoh.open(_client_config(where, user))


def test_an_agent_publishes_only_under_its_own_prefix(router, observer):
    agent = _open(router, "agent-0")
    try:
        allowed = [KEYS.ack(0), KEYS.request(0, 5)]
        refused = [KEYS.ack(1), KEYS.request(1, 5), KEYS.reply(5, 0), KEYS.tick, KEYS.metric("links"),
                   KEYS.event("sim"), KEYS.latest("agent", "0")]
        for key in allowed[:1] + refused + allowed[1:]:
            agent.put(key, b"from-agent-0")
        sentinel = KEYS.agent_state(0)
        agent.put(sentinel, b"sentinel")
        seen = observer.wait_for(sentinel, b"sentinel")
    finally:
        agent.close()
    keys = [k for k, _ in seen]
    assert keys == [*allowed, sentinel], f"refused keys got through: {set(keys) - set(allowed) - {sentinel}}"


def test_only_the_operator_changes_faults(router, observer):
    sessions = {user: _open(router, user) for user in ("agent-0", "sim", "monitor", "operator")}
    try:
        for user in ("agent-0", "sim", "monitor"):
            sessions[user].put(KEYS.faults, f"fault-by-{user}".encode())
            sessions[user].delete(KEYS.faults)
        sessions["operator"].put(KEYS.faults, b"fault-by-operator")
        sessions["sim"].put(KEYS.stop, b"stop-by-sim")  # the sim ends its run; it still cannot touch faults
        for user, own in (("agent-0", KEYS.ack(0)), ("sim", KEYS.tick), ("monitor", KEYS.metric("links"))):
            sessions[user].put(own, b"sentinel")
        for _user, own in (("agent-0", KEYS.ack(0)), ("sim", KEYS.tick), ("monitor", KEYS.metric("links"))):
            observer.wait_for(own, b"sentinel")
        seen = observer.wait_for(KEYS.stop, b"stop-by-sim")
        seen = observer.wait_for(KEYS.faults, b"fault-by-operator")
    finally:
        for s in sessions.values():
            s.close()
    assert [p for k, p in seen if k == KEYS.faults] == [b"fault-by-operator"]


def test_an_agent_answers_fault_queries_under_its_own_key_only_and_cannot_serve_the_registry(router):
    """Every agent runs a fault controller: the operator's `faults list` must reach it, under the agent's own key.
    Under the sim's key (or the bare ctl/faults) it can neither take the query nor answer it: an answer's key says
    whose it is."""
    agent = _open(router, "agent-0")
    operator = _open(router, "operator")
    own, sims = KEYS.fault_answers("agent-0"), KEYS.fault_answers("sim")
    try:
        agent.declare_queryable(sims, lambda q: q.reply(sims, b"forged sim answer"))  # refused first: had it been
        agent.declare_queryable(KEYS.faults, lambda q: q.reply(KEYS.faults, b"forged bare answer"))  # allowed, it
        agent.declare_queryable(own, lambda q: q.reply(own, b"agent-0 controller"))  # would be there before this
        agent.declare_queryable(KEYS.registry, lambda q: q.reply(KEYS.registry, b"fake registry"))
        deadline = time.monotonic() + 10.0
        answers: list[tuple[str, bytes]] = []
        while not answers:  # declarations propagate asynchronously
            assert time.monotonic() < deadline, "the agent's fault controller never answered"
            answers = [(str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in operator.get(KEYS.fault_queries,
                                                                                          timeout=1.0)
                       if r.ok is not None]
        bare = [r.ok.payload.to_bytes() for r in operator.get(KEYS.faults, timeout=1.0) if r.ok is not None]
        registry = [r.ok.payload.to_bytes() for r in operator.get(KEYS.registry, timeout=1.0) if r.ok is not None]
    finally:
        agent.close()
        operator.close()
    assert answers == [(own, b"agent-0 controller")]
    assert bare == []
    assert registry == []


def test_an_agent_cannot_hold_another_robots_liveliness_token(router):
    agent = _open(router, "agent-0")
    watcher = _open(router, "monitor")
    try:
        # The refused token first: had it been allowed, it would reach the router before the allowed one.
        other = agent.liveliness().declare_token(KEYS.alive(1))
        own = agent.liveliness().declare_token(KEYS.alive(0))
        deadline = time.monotonic() + 5.0
        while True:
            present = {str(r.ok.key_expr) for r in watcher.liveliness().get(KEYS.alive_all, timeout=2.0)
                       if r.ok is not None}
            if KEYS.alive(0) in present or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert present == {KEYS.alive(0)}
        own.undeclare()
        other.undeclare()
    finally:
        agent.close()
        watcher.close()


def test_wrong_or_missing_credentials_cannot_connect(router):
    for user, password in (("agent-0", "not-the-password"), ("intruder", "x"), (None, None)):
        cfg = _client_config(router, None, timeout=1.0)
        if user is not None:
            cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
            cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
        with pytest.raises(zenoh.ZError):
            zenoh.open(cfg).close()
    _open(router, "agent-0").close()  # positive control: the right password connects


def test_the_client_samples_load_and_authenticate(router, observer):
    for user, key in (("operator", KEYS.faults), ("agent-0", KEYS.ack(0))):
        cfg = zenoh.Config.from_file(str(DEPLOY / f"client-{user}.json5"))
        cfg.insert_json5("connect/endpoints", json.dumps([router]))  # the sample points at the compose host name
        session = zenoh.open(cfg)
        try:
            session.put(key, f"sample-{user}".encode())
            observer.wait_for(key, f"sample-{user}".encode())
        finally:
            session.close()


async def test_registration_works_through_the_router_and_an_agent_cannot_fake_the_registry(router):
    def bus_config(user: str):
        return _client_config(router, user)

    sim = await ZenohBus.open("sim", config=bus_config("sim"))
    agent = await ZenohBus.open("agent-0", config=bus_config("agent-0"))
    other = await ZenohBus.open("monitor", config=bus_config("monitor"))
    try:
        await mount_registry(sim, KEYS, 2, 1)
        # An agent that declares a queryable on the registry is refused by the router: it never answers queries.
        await agent.declare_queryable(KEYS.registry, lambda q: q.reply(KEYS.registry, b"forged"))
        await asyncio.sleep(0.3)
        replies = await other.get(KEYS.registry, payload=None, timeout=2.0)
        assert all(r.payload != b"forged" for r in replies) and replies, replies
        # (The forged queryable still answers its own session's queries — locally, where no ACL applies; the
        # claim skips that undecodable answer and takes the registry's.)
        granted = await claim_id(agent, KEYS, "robot-host-a", timeout=5.0)
        assert (granted.agent_id, granted.n_agvs, granted.n_pickers) == (0, 2, 1)
    finally:
        for bus in (agent, other, sim):
            await bus.close()


def test_a_robot_alone_receives_its_on_board_state(router, observer):
    """The sim publishes each robot's on-board state on a verbatim key: robot 0 receives its own, not robot 1's; a
    whole-run subscriber (the observer's morph/<run>/**) sees none."""
    sim, agent0 = _open(router, "sim"), _open(router, "agent-0")
    got: list[str] = []
    try:
        subs = [agent0.declare_subscriber(KEYS.onboard(r), lambda s: got.append(str(s.key_expr))) for r in (0, 1)]
        deadline = time.monotonic() + 10.0
        while KEYS.onboard(0) not in got:  # declarations propagate asynchronously
            assert time.monotonic() < deadline, "robot 0 never received its on-board state"
            sim.put(KEYS.onboard(1), b"robot 1")
            sim.put(KEYS.onboard(0), b"robot 0")
            time.sleep(0.05)
        sim.put(KEYS.onboard(1), b"robot 1")
        sim.put(KEYS.tick, b"sentinel")
        observer.wait_for(KEYS.tick, b"sentinel")
        for sub in subs:
            sub.undeclare()
    finally:
        sim.close()
        agent0.close()
    assert set(got) == {KEYS.onboard(0)}
    assert not [k for k, _ in observer.seen if "@onboard" in k]
