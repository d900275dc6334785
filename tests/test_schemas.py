"""Wire contract: codec round trips for every message, typed rejects naming the field, JSON Schema kept current."""

from __future__ import annotations

import math

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from schemas import (
    MESSAGE_TYPES,
    Ack,
    AgentState,
    AirPart,
    AirStats,
    AirVerdicts,
    Commit,
    DecodeError,
    Event,
    FaultCommand,
    FaultReply,
    FaultSpec,
    HelpReply,
    HelpRequest,
    Latency,
    Loss,
    MetricSample,
    OnBoard,
    Partition,
    PolicyAnnouncement,
    PolicyMessage,
    Refusal,
    RegistrationReply,
    RegistrationRequest,
    Resolve,
    Stop,
    Tick,
    codec,
    decode,
    encode,
)
from schemas.faults import Crash, Duplicate, Reorder, Scope
from schemas.jsonschema import JSON_DIR, message_schemas, render

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
nonneg = st.floats(min_value=0.0, max_value=1e9, allow_nan=False, allow_infinity=False)
percent = st.floats(min_value=0.0, max_value=100.0, allow_nan=False)
seq = st.integers(0, 2**63 - 1)
tick_no = st.integers(0, 2**40)
rid = st.integers(0, 200)
chunk = st.from_regex(r"[a-z][a-z0-9_]{0,10}", fullmatch=True)


@st.composite
def ticks(draw: st.DrawFn, max_n: int = 40) -> Tick:
    n = draw(st.integers(1, max_n))
    rows, cols = draw(st.integers(1, 60)), draw(st.integers(1, 60))
    ids = st.integers(0, n - 1)
    opt_ids = st.integers(-1, n - 1)
    xs, ys = st.integers(0, cols - 1), st.integers(0, rows - 1)
    txs, tys = st.integers(-1, cols - 1), st.integers(-1, rows - 1)

    def per(s: st.SearchStrategy) -> list:
        return draw(st.lists(s, min_size=n, max_size=n))

    return Tick(
        t=draw(tick_no), sim_time=draw(nonneg), grid_rows=rows, grid_cols=cols,
        x=per(xs), y=per(ys), heading=per(st.integers(0, 3)), is_agv=per(st.booleans()), busy=per(st.booleans()),
        carrying=per(st.booleans()), carrying_requested=per(st.booleans()), mission=per(st.integers(0, 3)),
        target_x=per(txs), target_y=per(tys), task=per(st.integers(0, 500)), needs_picker=per(st.booleans()),
        partner=per(opt_ids), mission_order=draw(st.lists(ids, max_size=n)),
        free_pickers=draw(st.lists(ids, max_size=n)), request_queue=draw(st.lists(st.integers(0, 500), max_size=40)),
        has_previous=draw(st.booleans()), prev_mission=per(st.integers(0, 3)), prev_target_x=per(txs),
        prev_target_y=per(tys), prev_task=per(st.integers(0, 500)), reward=per(finite),
        delivered_by=draw(st.lists(ids, max_size=3)), loader=per(opt_ids),
        loads=draw(st.lists(st.tuples(ids, ids), max_size=4)), unloads=draw(st.lists(st.tuples(ids, ids), max_size=4)),
        handled=per(st.booleans()), final=draw(st.booleans()),
    )


@st.composite
def agent_states(draw: st.DrawFn) -> AgentState:
    n = draw(st.integers(0, 30))

    def row(s: st.SearchStrategy) -> list:
        return draw(st.lists(s, min_size=n, max_size=n))

    return AgentState(
        agent=draw(rid), role=draw(st.sampled_from(["agv", "picker"])), t=draw(tick_no), w_row=row(finite),
        a_row=row(st.booleans()), theta_row=row(finite), age_row=row(st.integers(0, 10**6)), h=draw(finite),
        eta=draw(finite), d_hat=draw(finite), seq=draw(seq),
        scalars=draw(st.dictionaries(chunk, finite, max_size=3)),
        rows=draw(st.dictionaries(chunk, st.lists(finite, min_size=n, max_size=n), max_size=2)),
    )


agent_ref = st.one_of(rid, st.sampled_from(["sim", "monitor"]))


@st.composite
def fault_specs(draw: st.DrawFn) -> FaultSpec:
    latency = draw(st.none() | st.builds(Latency, delay=nonneg, jitter=nonneg,
                                          distribution=st.sampled_from(["uniform", "normal", "pareto"]),
                                          correlation=percent))
    loss = draw(st.none() | st.builds(Loss, model=st.just("bernoulli"), percent=percent, correlation=percent)
                | st.builds(Loss, model=st.just("gilbert_elliott"),
                            percent=st.floats(0.0, 50.0), burst_length=st.floats(1.0, 50.0))
                | st.builds(Loss, model=st.just("gilbert_elliott"), p=percent,
                            r=st.floats(0.1, 100.0), one_minus_h=percent, one_minus_k=percent))
    partition = draw(st.none() | st.builds(Partition, from_agents=st.lists(agent_ref, min_size=1, max_size=3),
                                            to_agents=st.lists(agent_ref, min_size=1, max_size=3),
                                            direction=st.sampled_from(["to", "from", "both"])))
    crash = draw(st.none() | st.builds(Crash, agent=st.none() | rid, at_tick=st.integers(0, 10**5), every=st.none()))
    duplicate = draw(st.none() | st.builds(Duplicate, percent=percent, correlation=percent))
    reorder = draw(st.none() | st.builds(Reorder, percent=percent, gap=st.integers(1, 5))) if latency else None
    if all(x is None for x in (latency, loss, partition, crash, duplicate)):
        duplicate = Duplicate(percent=1.0)
    return FaultSpec(
        id=draw(st.none() | chunk), latency=latency, loss=loss, duplicate=duplicate, reorder=reorder,
        partition=partition, crash=crash,
        scope=Scope(key_expr=draw(st.sampled_from(["**", "agent/*/ack", "sim/tick", "agent/*/request/*"])),
                    agents=draw(st.none() | st.lists(agent_ref, max_size=4))),
        duration=draw(st.none() | nonneg), seed=draw(st.none() | st.integers(0, 2**63 - 1)),
    )


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**63 - 1) | finite | st.text(max_size=10),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=10,
)

MESSAGE_STRATEGIES: dict[type, st.SearchStrategy] = {
    Tick: ticks(),
    Ack: st.builds(Ack, t=tick_no, agent=rid, phase=st.sampled_from([0, 1]), requests_sent=st.lists(rid, max_size=4),
                   seq=seq, view_age=st.none() | st.floats(0.0, 1e6)),
    OnBoard: st.builds(OnBoard, t=tick_no, robot=rid, x=st.integers(0, 999), y=st.integers(0, 999),
                       heading=st.integers(0, 3), mission=st.integers(0, 3), target_x=st.integers(-1, 999),
                       target_y=st.integers(-1, 999), task=st.integers(0, 99), needs_picker=st.booleans(),
                       free=st.booleans(), carrying=st.booleans(), reward=finite, handled=st.booleans(),
                       final=st.booleans(), replied=st.integers(0, 2**40)),
    Resolve: st.integers(0, 6).flatmap(lambda k: st.builds(
        Resolve, t=tick_no, pickers=st.lists(rid, min_size=k, max_size=k),
        requesters=st.lists(st.lists(rid, max_size=4), min_size=k, max_size=k))),
    HelpRequest: st.builds(HelpRequest, t=tick_no, agv=rid, picker=rid, target_x=st.integers(0, 999),
                           target_y=st.integers(0, 999), mission=st.sampled_from([1, 3]), seq=seq),
    HelpReply: st.builds(HelpReply, t=tick_no, picker=rid, agv=rid, accepted=st.booleans(), seq=seq),
    Commit: st.builds(Commit, t=tick_no, picker=rid, agv=rid, seq=seq),
    Refusal: st.builds(Refusal, t=tick_no, picker=rid, agv=rid, commit_seq=seq, seq=seq),
    AgentState: agent_states(),
    MetricSample: st.builds(MetricSample, name=st.sampled_from(["deliveries", "links", "w_mean/agv_picker"]),
                            t=tick_no, sim_time=nonneg, value=finite, labels=st.dictionaries(chunk, chunk, max_size=2))
    | st.builds(MetricSample, name=st.just("latency_quantiles"), t=tick_no, sim_time=nonneg,
                values=st.lists(finite, max_size=5), unit=st.just("s")),
    Event: st.builds(Event, kind=st.sampled_from(["fault.set", "fault.healed", "crash", "restart"]),
                     source=agent_ref, t=st.none() | tick_no, sim_time=st.none() | nonneg,
                     details=st.dictionaries(st.text(max_size=8), json_values, max_size=4)),
    Stop: st.builds(Stop, reason=st.text(max_size=20)),
    FaultCommand: st.builds(FaultCommand, op=st.just("set"), spec=fault_specs())
    | st.builds(FaultCommand, op=st.sampled_from(["list", "reset"]), fault_id=st.none() | chunk),
    FaultReply: st.builds(FaultReply, ok=st.booleans(), error=st.none() | st.text(max_size=20),
                          active=st.lists(fault_specs(), max_size=2)),
    RegistrationRequest: st.builds(RegistrationRequest, instance=st.text(min_size=1, max_size=20),
                                   want_id=st.none() | rid, want_role=st.none() | st.sampled_from(["agv", "picker"])),
    RegistrationReply: st.builds(RegistrationReply, ok=st.just(True), agent_id=rid,
                                 role=st.sampled_from(["agv", "picker"]), n_agvs=st.integers(0, 99),
                                 n_pickers=st.integers(0, 99))
    | st.builds(RegistrationReply, ok=st.just(False), reason=st.text(max_size=20)),
    PolicyMessage: st.builds(PolicyMessage, t=tick_no, sender=rid, to=st.none() | rid, pseq=st.integers(0, 2**40),
                             data=st.binary(max_size=64)),
    AirPart: st.integers(0, 5).flatmap(lambda k: st.builds(
        AirPart, sent_at=nonneg, part=st.sampled_from([0, 1]),
        publishers=st.lists(st.integers(-1, 99), min_size=k, max_size=k),
        keys=st.lists(st.sampled_from(["sim/fleet", "agent/3/request/5", "agent/5/commit"]), min_size=k, max_size=k),
        counts=st.lists(st.integers(1, 9), min_size=k, max_size=k))),
    AirVerdicts: st.integers(0, 5).flatmap(lambda k: st.builds(
        AirVerdicts, publishers=st.lists(st.integers(-1, 99), min_size=k, max_size=k),
        keys=st.lists(st.sampled_from(["sim/fleet", "agent/3/reply/1"]), min_size=k, max_size=k),
        seqs=st.lists(seq, min_size=k, max_size=k), at=st.lists(st.none() | nonneg, min_size=k, max_size=k),
        causes=st.lists(st.none() | st.sampled_from(["ap_queue", "loss"]), min_size=k, max_size=k))),
    AirStats: st.integers(0, 4).flatmap(lambda k: st.builds(
        AirStats, t=tick_no, sim_time=nonneg, ap_bytes=st.lists(st.integers(0, 2**40), min_size=k, max_size=k),
        ap_queue=st.lists(st.integers(0, 99), min_size=k, max_size=k),
        ap_drops=st.lists(st.integers(0, 2**20), min_size=k, max_size=k))),
    PolicyAnnouncement: st.builds(PolicyAnnouncement, policy=st.sampled_from(["morph", "proximity", "pkg.mod:Cls"]),
                                  options=st.dictionaries(st.text(min_size=1, max_size=8),
                                                          st.none() | st.booleans() | st.integers(-9, 9)
                                                          | st.text(max_size=8), max_size=4)),
}


def test_every_message_has_a_strategy_and_a_kind() -> None:
    assert set(MESSAGE_STRATEGIES) == set(MESSAGE_TYPES)
    kinds = [cls.KIND for cls in MESSAGE_TYPES]
    assert len(set(kinds)) == len(kinds) and all(kinds)
    for cls in MESSAGE_TYPES:  # the default of ``v`` is the class's VERSION
        assert cls.model_fields["v"].default == cls.VERSION


@pytest.mark.parametrize("cls", MESSAGE_TYPES, ids=lambda c: c.KIND)
@settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])  # examples: the profile's (tests/conftest.py)
@given(data=st.data())
def test_codec_round_trip(cls: type, data: st.DataObject) -> None:
    msg = data.draw(MESSAGE_STRATEGIES[cls])
    wire = encode(msg)
    assert isinstance(wire, bytes)
    back = decode(wire, cls)
    assert back == msg
    assert decode(wire) == msg  # kind dispatch without an expected type
    assert encode(back) == wire  # canonical: re-encoding gives the same bytes


@settings(max_examples=16 * settings.default.max_examples, deadline=None)  # cheap examples: 400 by default
@given(st.binary(max_size=200))
def test_garbage_bytes_raise_decode_error_only(data: bytes) -> None:
    try:
        decode(data)
    except DecodeError as exc:
        assert exc.field
        assert isinstance(exc, ValueError)


_any_value = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=6)
    | st.binary(max_size=6),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=8,
)


@pytest.mark.parametrize("cls", MESSAGE_TYPES, ids=lambda c: c.KIND)
@settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])  # examples: the profile's (tests/conftest.py)
@given(data=st.data())
def test_one_corrupted_field_is_named(cls: type, data: st.DataObject) -> None:
    msg = data.draw(MESSAGE_STRATEGIES[cls])
    body = msgpack.unpackb(encode(msg), raw=False)
    field = data.draw(st.sampled_from(sorted(body)))
    body[field] = data.draw(_any_value)
    wire = msgpack.packb(body, use_bin_type=True)
    try:
        decode(wire, cls)
    except DecodeError as exc:
        allowed = {field}
        if cls is Tick and field in (*Tick.PER_ROBOT, "x"):
            allowed |= {*Tick.PER_ROBOT, "x"}  # a per-robot array of another length: the first mismatch is named
        if cls is Tick and field in ("grid_rows", "grid_cols"):
            allowed |= {"x", "target_x", "prev_target_x", "y", "target_y", "prev_target_y"}  # a smaller grid: the
            # coordinate that no longer fits is named
        if cls is Resolve and field == "pickers":
            allowed.add("requesters")
        if cls is AirStats and field == "ap_bytes":
            allowed |= {"ap_queue", "ap_drops"}  # the lists must be as long as it: the first short one
        if cls in (AirPart, AirVerdicts) and field == "publishers":
            allowed |= set(body) - {"v", "sent_at", "part"}  # the lists must be as long as it: the first short one
        if cls is AgentState and field == "w_row":
            allowed |= {"a_row", "theta_row", "age_row"} | {f"rows.{k}" for k in body.get("rows", {})}
        if cls is MetricSample and field == "values":
            allowed.add("value")
        if cls is RegistrationReply and field == "ok":
            allowed |= {"agent_id", "role"}  # ok=True needs both: the first missing one is named
        assert exc.field.replace("[", ".").split(".")[0] in {a.split(".")[0] for a in allowed}, (field, exc)


def _tick(n: int = 3, **changes: object) -> dict:
    body = dict(
        t=4, sim_time=4.0, grid_rows=10, grid_cols=10, x=[1] * n, y=[2] * n, heading=[0] * n, is_agv=[True] * n,
        busy=[False] * n, carrying=[False] * n, carrying_requested=[False] * n, mission=[0] * n, target_x=[-1] * n,
        target_y=[-1] * n, task=[0] * n, needs_picker=[False] * n, partner=[-1] * n, mission_order=[],
        free_pickers=[], request_queue=[], has_previous=True, prev_mission=[0] * n, prev_target_x=[-1] * n,
        prev_target_y=[-1] * n, prev_task=[0] * n, reward=[0.0] * n, delivered_by=[], loader=[-1] * n, loads=[],
        unloads=[], handled=[False] * n,
    )
    body.update(changes)
    return body


def _wire(kind: str, body: dict) -> bytes:
    return msgpack.packb({"k": kind, "v": 1, **body}, use_bin_type=True)


@pytest.mark.parametrize(("changes", "field", "reason"), [
    ({"heading": [0, 9, 0]}, "heading[1]", "less than or equal to 3"),
    ({"busy": [True, False]}, "busy", "2 entries, expected 3"),
    ({"free_pickers": [5]}, "free_pickers", "robot id 5"),
    ({"loads": [[0, 7]]}, "loads", "robot id 7"),
    ({"x": [1, 2, 30]}, "x", "outside"),
    ({"t": -1}, "t", "greater than or equal to 0"),
    ({"sim_time": float("nan")}, "sim_time", "finite"),
    ({"surprise": 1}, "surprise", "not a known field"),
])
def test_bad_tick_field_is_named(changes: dict, field: str, reason: str) -> None:
    with pytest.raises(DecodeError, match=reason) as info:
        decode(_wire("tick", _tick(**changes)), Tick)
    assert info.value.field == field
    assert info.value.kind == "tick"


def test_missing_field_is_named() -> None:
    body = _tick()
    del body["target_y"]
    with pytest.raises(DecodeError) as info:
        decode(_wire("tick", body))
    assert info.value.field == "target_y"


def test_wrong_version_is_rejected_naming_v() -> None:
    wire = msgpack.packb({"k": "ack", "v": 2, "t": 1, "agent": 0}, use_bin_type=True)
    with pytest.raises(DecodeError, match="newer") as info:
        decode(wire, Ack)
    assert info.value.field == "v"
    for bad_v in (0, "1", None, True):
        wire = msgpack.packb({"k": "ack", "v": bad_v, "t": 1, "agent": 0}, use_bin_type=True)
        with pytest.raises(DecodeError) as info:
            decode(wire, Ack)
        assert info.value.field == "v"


def test_wrong_kind_and_unknown_kind_name_k() -> None:
    with pytest.raises(DecodeError, match="expected a 'tick'") as info:
        decode(encode(Ack(t=1, agent=0)), Tick)
    assert info.value.field == "k"
    with pytest.raises(DecodeError, match="unknown message kind") as info:
        decode(msgpack.packb({"k": "nope", "v": 1}))
    assert info.value.field == "k"
    with pytest.raises(DecodeError) as info:
        decode(msgpack.packb([1, 2, 3]))
    assert info.value.field == "<root>"
    with pytest.raises(DecodeError) as info:
        decode(b"\xc1")
    assert info.value.field == "<payload>"


def test_nested_fault_spec_error_path() -> None:
    wire = _wire("fault_command", {"op": "set", "spec": {"loss": {"model": "bernoulli", "percent": 140}}})
    with pytest.raises(DecodeError, match="less than or equal to 100") as info:
        decode(wire, FaultCommand)
    assert info.value.field == "spec.loss.percent"
    wire = _wire("fault_command", {"op": "set"})
    with pytest.raises(DecodeError) as info:
        decode(wire, FaultCommand)
    assert info.value.field == "spec"


def test_fault_spec_validation() -> None:
    with pytest.raises(ValueError, match="at least one"):
        FaultSpec()
    with pytest.raises(ValueError, match="percent is required"):
        Loss(model="bernoulli")
    with pytest.raises(ValueError, match="either"):
        Loss(model="gilbert_elliott", percent=10, burst_length=3, p=1, r=2)
    with pytest.raises(ValueError, match="reorder needs latency"):
        FaultSpec(reorder=Reorder(percent=10))
    with pytest.raises(ValueError, match="not canonical"):
        Scope(key_expr="agent/**/*")
    with pytest.raises(ValueError, match="at_tick or every"):
        Crash(agent=1)
    p, r, h1, k1 = Loss(model="gilbert_elliott", percent=20, burst_length=4).gilbert_elliott()
    assert r == pytest.approx(0.25) and p == pytest.approx(0.2 * 0.25 / 0.8) and (h1, k1) == (1.0, 0.0)
    assert math.isclose(p / (p + r), 0.2)  # stationary loss rate of simple Gilbert equals the setting
    cut = Partition(from_agents=[1, 2], to_agents=["sim"], direction="to")
    assert cut.cuts(1, "sim") and not cut.cuts("sim", 1)
    assert Partition(from_agents=["3", "sim"], to_agents=[1]).from_agents == [3, "sim"]  # "3" and 3: one robot
    assert Scope(agents=["2", 5]).agents == [2, 5]
    both = Partition(from_agents=[1], to_agents=[2], direction="both")
    assert both.cuts(1, 2) and both.cuts(2, 1) and not both.cuts(1, 3)


def test_upgrade_path_for_old_versions() -> None:
    old = msgpack.packb({"k": "stop", "v": 0, "why": "old field name"}, use_bin_type=True)
    with pytest.raises(DecodeError, match="no longer supported"):
        decode(old)

    def upgrade(body: dict) -> dict:
        body["reason"] = body.pop("why")
        return body

    codec.register_upgrade("stop", 0, upgrade)
    try:
        assert decode(old, Stop) == Stop(reason="old field name")
    finally:
        codec._UPGRADES.pop(("stop", 0))


def test_tick_at_128_robots_stays_small() -> None:
    n = 128
    tick = Tick(**_tick(
        n, x=list(range(20)) * 6 + [0] * 8, grid_rows=40, grid_cols=30, y=[39] * n, is_agv=[True] * 85 + [False] * 43,
        busy=[True] * n, mission=[1, 2, 3, 0] * 32, target_x=[29] * n, target_y=[39] * n, task=[250] * n,
        partner=list(range(-1, 127)), mission_order=list(range(85)), free_pickers=list(range(85, 128)),
        request_queue=list(range(100, 160)), prev_mission=[1] * n, prev_target_x=[29] * n, prev_target_y=[39] * n,
        prev_task=[250] * n, reward=[-0.001] * n, delivered_by=[1, 2], loader=[-1] * n, loads=[(1, 90)],
        handled=[False] * n))
    wire = encode(tick)
    assert len(wire) < 5000, len(wire)  # ~34 B per robot, most of it the float64 rewards
    assert decode(wire, Tick) == tick


def test_json_schema_files_are_current() -> None:
    fresh = message_schemas()
    committed = {p.name for p in JSON_DIR.glob("*.json")}
    assert committed == set(fresh), "run: morph-sim schemas export schemas/json"
    for name, schema in fresh.items():
        assert (JSON_DIR / name).read_text(encoding="utf-8") == render(schema), (
            f"{name} is stale; run: morph-sim schemas export schemas/json")


def test_schemas_export_command(tmp_path) -> None:
    from morph_sim.cli import main

    assert main(["schemas", "export", str(tmp_path / "out")]) == 0
    assert sorted(p.name for p in (tmp_path / "out").glob("*.json")) == sorted(message_schemas())
