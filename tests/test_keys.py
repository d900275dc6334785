"""Key expressions: builders, validation, and Zenoh's matching rules (checked against zenoh's own KeyExpr)."""

from __future__ import annotations

import re

import pytest
from hypothesis import given, settings, strategies as st

from schemas.keys import (
    RunKeys,
    intersects,
    matches,
    validate_key,
    validate_key_expr,
    validate_run_id,
)

MATCH_TABLE = [
    # (expression, concrete key, matches)
    ("a/b", "a/b", True),
    ("a/b", "a/c", False),
    ("a/*", "a/b", True),
    ("a/*", "a", False),
    ("a/*", "a/b/c", False),
    ("a/**", "a", True),  # '**' matches zero chunks
    ("a/**", "a/b/c", True),
    ("**", "a/b/c", True),
    ("*/b", "a/b", True),
    ("a/*/c", "a/b/c", True),
    ("a/*/c", "a/b/d", False),
    ("a/**/c", "a/c", True),
    ("a/**/c", "a/b/x/c", True),
    ("a/**/c", "a/b/x/d", False),
    ("a/*/**", "a", False),  # '*' needs one chunk
    ("a/*/**", "a/b", True),
    ("a/b", "a/b/c", False),
    ("a/*", "a/@x", False),  # verbatim chunks are never matched by wildcards
    ("a/**", "a/@x/y", False),
    ("a/@x", "a/@x", True),
    ("a/@x/*", "a/@x/y", True),
    ("morph/r1/agent/*/ack", "morph/r1/agent/12/ack", True),
    ("morph/r1/agent/*/ack", "morph/r1/agent/12/state", False),
    ("morph/r1/agent/*/request/5", "morph/r1/agent/2/request/5", True),
    ("morph/r1/agent/*/request/5", "morph/r1/agent/2/request/6", False),
    ("morph/r1/**", "morph/r2/sim/tick", False),
]


@pytest.mark.parametrize(("expr", "key", "expected"), MATCH_TABLE)
def test_match_table(expr: str, key: str, expected: bool) -> None:
    assert matches(expr, key) is expected
    assert intersects(key, expr) is expected  # symmetric


INTERSECT_TABLE = [
    ("a/*/c", "a/b/*", True),
    ("a/**", "*/b", True),
    ("a/*", "b/*", False),
    ("**", "**", True),
    ("a/**/b", "a/**/c", False),  # the last chunks differ
    ("a/**/b", "**/c/b", True),
    ("a/*/b", "a/**/c", False),
    ("morph/r/agent/*/ack", "morph/r/agent/3/**", True),
]


@pytest.mark.parametrize(("a", "b", "expected"), INTERSECT_TABLE)
def test_intersect_table(a: str, b: str, expected: bool) -> None:
    import zenoh

    assert intersects(a, b) is expected
    assert zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)) is expected  # the table itself is Zenoh's behaviour


_chunks = st.sampled_from(["a", "b", "c", "*", "**", "@v"])


def _canonical(chunks: list[str]) -> str | None:
    expr = "/".join(chunks)
    try:
        return validate_key_expr(expr)
    except ValueError:
        return None


@settings(max_examples=600, deadline=None)
@given(st.lists(_chunks, min_size=1, max_size=5), st.lists(_chunks, min_size=1, max_size=5))
def test_intersects_agrees_with_zenoh(a: list[str], b: list[str]) -> None:
    import zenoh

    ea, eb = _canonical(a), _canonical(b)
    if ea is None or eb is None:
        return
    assert intersects(ea, eb) == zenoh.KeyExpr(ea).intersects(zenoh.KeyExpr(eb)), (ea, eb)


@pytest.mark.parametrize("bad", ["", "/a", "a/", "a//b", "a*", "a/b*c", "a/$*", "a/b?x", "a/#", "a b", "a/**/*",
                                 "a/**/**"])
def test_invalid_key_expressions_are_rejected(bad: str) -> None:
    with pytest.raises(ValueError, match="key expression"):
        validate_key_expr(bad)


def test_non_canonical_names_the_canonical_form() -> None:
    with pytest.raises(ValueError, match=r"'a/\*/\*\*'"):
        validate_key_expr("a/**/*")


def test_publish_key_must_be_concrete() -> None:
    with pytest.raises(ValueError, match="wildcard"):
        validate_key("morph/r/agent/*/ack")
    assert validate_key("morph/r/agent/1/ack") == "morph/r/agent/1/ack"


@pytest.mark.parametrize("run", ["r1", "exp_2026-11-22.a", "A", "0"])
def test_valid_run_ids(run: str) -> None:
    assert validate_run_id(run) == run


@pytest.mark.parametrize("run", ["", "a/b", "a*", "a b", "-x", ".x", "x$", "x#", "x?", "é", "x" * 65])
def test_invalid_run_ids_name_the_field(run: str) -> None:
    with pytest.raises(ValueError, match="run id"):
        RunKeys(run)


def test_run_keys_spell_the_contract() -> None:
    k = RunKeys("r1")
    assert k.tick == "morph/r1/sim/tick"
    assert k.resolve == "morph/r1/sim/resolve"
    assert k.ack(3) == "morph/r1/agent/3/ack"
    assert k.acks == "morph/r1/agent/*/ack"
    assert k.request(2, 7) == "morph/r1/agent/2/request/7"
    assert k.requests_to(7) == "morph/r1/agent/*/request/7"
    assert k.reply(7, 2) == "morph/r1/agent/7/reply/2"
    assert k.replies_to(2) == "morph/r1/agent/*/reply/2"
    assert k.commit(7) == "morph/r1/agent/7/commit"
    assert k.commits == "morph/r1/agent/*/commit"
    assert k.agent_state(4) == "morph/r1/agent/4/state"
    assert k.metric("deliveries") == "morph/r1/metrics/deliveries"
    assert k.metric("w_mean/agv_picker") == "morph/r1/metrics/w_mean/agv_picker"
    assert k.latest("agent", "4") == "morph/r1/state/agent/4"
    assert k.latest_all == "morph/r1/state/**"
    assert k.faults == "morph/r1/ctl/faults"
    assert k.stop == "morph/r1/ctl/stop"
    assert k.event("sim") == "morph/r1/events/sim"
    assert k.registry == "morph/r1/registry"
    assert k.alive(5) == "morph/r1/alive/5"
    assert k.alive("monitor") == "morph/r1/alive/monitor"
    assert k.alive_all == "morph/r1/alive/*"
    # every builder's output is a valid key expression and the subscriptions match what they should
    assert matches(k.requests_to(7), k.request(2, 7))
    assert not matches(k.requests_to(7), k.request(2, 8))
    assert matches(k.replies_to(2), k.reply(7, 2))
    assert matches(k.acks, k.ack(3)) and not matches(k.acks, k.commit(3))
    assert matches(k.everything, k.tick)
    assert matches(k.agent_prefix(2), k.request(2, 7)) and not matches(k.agent_prefix(2), k.reply(7, 2))


def test_key_parsing() -> None:
    k = RunKeys("r1")
    assert k.sender_of(k.request(2, 7)) == 2
    assert k.recipient_of(k.request(2, 7)) == 7
    assert k.sender_of(k.reply(7, 2)) == 7 and k.recipient_of(k.reply(7, 2)) == 2
    assert k.recipient_of(k.ack(3)) == "sim"
    assert k.sender_of(k.tick) == "sim" and k.recipient_of(k.tick) is None
    assert k.alive_id(k.alive(12)) == 12 and k.alive_id(k.alive("monitor")) == "monitor"
    with pytest.raises(ValueError, match="not under"):
        k.relative("morph/r2/sim/tick")


@pytest.mark.parametrize("bad", [-1, True, "a/b", "*"])
def test_bad_agent_ids_are_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match="agent id"):
        RunKeys("r1").ack(bad)  # type: ignore[arg-type]


def test_sender_of_answers_the_same_every_time_refuses_other_runs_every_time_and_stays_bounded():
    k = RunKeys("r1")
    for _ in range(2):  # the second answer comes from the table
        assert k.sender_of(k.ack(3)) == 3 and k.sender_of(k.tick) == "sim" and k.sender_of(k.event(7)) == 7
        assert k.sender_of(k.metric("deliveries")) is None
        with pytest.raises(ValueError):
            k.sender_of("morph/r2/agent/3/ack")
    for i in range(5000):  # a fuzzer's keys
        assert k.sender_of(f"morph/r1/agent/{i}/x{i}") == i
    assert len(k._senders) <= 4096


def test_a_robots_keys_are_the_protocols_and_nothing_it_makes_up():
    from schemas.keys import check_robot_key

    k = RunKeys("r")
    for key in (k.ack(3), k.skip(3), k.request(1, 5), k.reply(5, 1), k.policy(3, None), k.policy(3, 4), k.commit(5),
                k.agent_state(3)):
        check_robot_key(k.relative(key), 8)
    for key, why in (("agent/3/k1", "no message kind 'k1'"), ("agent/3/ack/x", "no message kind 'ack/x'"),
                     ("agent/3", "no message kind ''"), ("agent/9/ack", "robot '9' outside 0..7"),
                     ("agent/monitor/ack", "robot 'monitor' outside"), ("agent/3/request", "request to ''"),
                     ("agent/3/request/zz", "request to 'zz'"), ("agent/3/request/8", "request to '8'"),
                     ("agent/3/reply/all", "reply to 'all'"), ("agent/3/policy/all/x", "policy to 'all/x'")):
        with pytest.raises(ValueError, match=re.escape(why)):
            check_robot_key(k.relative(f"morph/r/{key}"), 8)
