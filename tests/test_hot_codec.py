"""The hot path's cheap codec (schemas/tick.py, codec.encode_fields) agrees with the pydantic models exactly.

Every tick of a short run, and a list of malformed variants of one tick, are decoded both ways: either both accept with
the same arrays, or both raise a DecodeError naming the same field.
"""

from __future__ import annotations

import copy
import math

import msgpack
import numpy as np
import pytest

from schemas import Ack, Commit, DecodeError, HelpReply, HelpRequest, Phase, Tick, decode
from schemas.codec import encode_fields
from schemas.tick import (
    FLAG_ROWS,
    INT_ROWS,
    TickArrays,
    arrays_from_tick,
    decode_tick,
    encode_tick_body,
    observation_from_arrays,
    observation_from_tick,
    replace_fields,
    tick_fields,
    tick_from_observation,
    tick_number,
)
from services.runconfig import RunConfig
from services.sim.wire import make_controller, world_fields


def _ticks(steps: int = 40) -> list[tuple[object, dict]]:
    """(observation, tick field map) of the first ticks of a small run with random dispatches."""
    config = RunConfig(run_id="hot", scale="small", policy="full", steps=steps, seed=5)
    ctl = make_controller(config)
    rng = np.random.default_rng(1)
    out = []
    for t in range(steps):
        obs = ctl.begin_tick()
        out.append((obs, tick_fields(obs, t * 1.0, world_fields(ctl, obs))))
        free = np.flatnonzero(obs.free_picker).tolist()
        commits = []
        for agv in obs.requesters():
            if free and rng.random() < 0.7:
                commits.append((free.pop(0), int(agv)))
        ctl.commit(commits)
        ctl.finish_tick()
    final = ctl.final_observation()
    out.append((final, tick_fields(final, steps * 1.0, world_fields(ctl, final))))
    return out


TICKS = _ticks()


def _same(a: TickArrays, b: TickArrays) -> None:
    for name in TickArrays.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), name
        else:
            assert x == y and type(x) is type(y), name


def _both(payload: bytes) -> None:
    try:
        slow = arrays_from_tick(decode(payload, Tick))
    except DecodeError as exc:
        with pytest.raises(DecodeError) as fast:
            decode_tick(payload)
        assert fast.value.field == exc.field
        return
    _same(decode_tick(payload), slow)


def test_the_sims_tick_bytes_decode_to_the_model_and_back_to_the_observation():
    assert any(f["loads"] or f["unloads"] for _, f in TICKS) and any(f["delivered_by"] for _, f in TICKS)
    for obs, fields in TICKS:
        payload = encode_tick_body(fields)
        tick = decode(payload, Tick)
        assert tick == tick_from_observation(obs, fields["sim_time"], world_fields_of(fields))
        _same(decode_tick(payload), arrays_from_tick(tick))
        back = observation_from_arrays(decode_tick(payload), 1000)
        ref = observation_from_tick(tick, 1000)
        for name in ref.__dataclass_fields__:
            x, y = getattr(back, name), getattr(ref, name)
            assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, name


def world_fields_of(fields: dict) -> dict:
    return {k: fields[k] for k in ("heading", "busy", "carrying", "carrying_requested", "partner", "request_queue",
                                   "loads", "unloads", "deliveries_total")}


def _variants(body: dict) -> list[dict]:
    """Malformed (and a few oddly typed but valid) variants of a tick's field map."""
    n = len(body["x"])
    out = []

    def change(**kw):
        b = copy.deepcopy(body)
        b.update(kw)
        out.append(b)

    def set_item(name, i, value):
        b = copy.deepcopy(body)
        b[name][i] = value
        out.append(b)

    for name in INT_ROWS:
        for value in (1.5, 2.0, "3", None, True, -2, 70000, 2**63, 2**64 - 1, [1]):
            set_item(name, 0, value)
        change(**{name: body[name][:-1]})  # ragged
        change(**{name: "x" * n})
    for name in FLAG_ROWS:
        for value in (0, 1, 2, 1.0, "true", None):
            set_item(name, n - 1, value)
    set_item("x", 1, body["grid_cols"])
    set_item("y", 1, body["grid_rows"])
    set_item("target_x", 2, -1)
    set_item("loader", 0, n)
    set_item("partner", 0, n)
    for value in (math.nan, math.inf, 1, True, "0.5"):
        set_item("reward", 0, value)
    for name in ("mission_order", "free_pickers", "delivered_by", "request_queue"):
        for value in ([n], [-1], [1.0], [True], ["1"], None, [[1]], 5):
            change(**{name: value})
    for name in ("loads", "unloads"):
        for value in ([[0, n]], [[0, 1, 2]], [[0]], [(0, 1.0)], [[0, 1]], None, [5]):
            change(**{name: value})
    for name, values in (("t", (-1, True, 1.0, None)), ("sim_time", (0, -1.0, math.inf, "1")),
                         ("grid_rows", (0, 65536, 3.0)), ("grid_cols", (0, True)), ("has_previous", (1, 0, None)),
                         ("final", (1, "yes")), ("v", (2, 0, True)),
                         ("deliveries_total", (-1, 1.0, True, "3", 2**63, None, 0))):
        for value in values:
            change(**{name: value})
    b = copy.deepcopy(body)
    del b["reward"]
    out.append(b)
    b = copy.deepcopy(body)
    del b["final"]
    out.append(b)
    change(extra_field=1)
    for name in INT_ROWS + FLAG_ROWS + ("reward",):  # an empty fleet
        change(**{name: []})
    return out


def test_malformed_ticks_are_rejected_naming_the_same_field_as_the_model():
    _, fields = next((o, f) for o, f in TICKS if (f["loads"] or f["unloads"]) and f["mission_order"])
    body = {**fields, "v": 1}
    variants = _variants(body)
    assert len(variants) > 150
    accepted = 0
    for b in variants:
        payload = msgpack.packb({**b, "k": "tick"}, use_bin_type=True)
        _both(payload)
        try:
            decode(payload, Tick)
            accepted += 1
        except DecodeError:
            pass
    assert accepted > 5  # some variants are valid after the model's coercions (bool ints, 0/1 flags, int floats)
    for payload in (b"", b"\x81", msgpack.packb([1, 2]), msgpack.packb({"k": "ack", "v": 1, "t": 1, "agent": 0}),
                    msgpack.packb({**body, "k": "tick", "v": 0})):
        _both(payload)


def test_the_tick_number_is_read_without_the_rest_and_refuses_what_is_not_a_tick_number():
    obs, fields = TICKS[3]
    assert tick_number(encode_tick_body(fields)) == obs.t == decode_tick(encode_tick_body(fields)).t
    body = {**fields, "v": 1, "k": "tick"}
    for bad, field in ((dict(t=-1), "t"), (dict(t=2.0), "t"), (dict(t=True), "t"), (dict(t=None), "t"),
                       (dict(k="ack"), "k")):
        with pytest.raises(DecodeError) as err:
            tick_number(msgpack.packb({**body, **bad}, use_bin_type=True))
        assert err.value.field == field
    with pytest.raises(DecodeError):
        tick_number(b"\x81")


@pytest.mark.parametrize(("cls", "fields"), [
    (Ack, dict(t=3, agent=2, phase=int(Phase.TICK), requests_sent=[7], seq=9, links=[0, 5], eta=-0.25)),
    (Ack, dict(t=3, agent=2, phase=int(Phase.TICK), requests_sent=[], seq=1, links=[], eta=None)),
    (HelpRequest, dict(t=4, agv=1, picker=6, target_x=3, target_y=8, mission=1, seq=2)),
    (Commit, dict(t=4, picker=6, agv=1, seq=3)),
    (HelpReply, dict(t=4, picker=6, agv=1, accepted=False, seq=4)),
])
def test_encode_fields_decodes_to_the_model(cls, fields):
    assert decode(encode_fields(cls, **fields), cls) == cls(**fields)


def test_rows_by_name_match_the_tick_fields():
    """Every named row and cell block of the decoded arrays is the Tick field of that name."""
    for _obs, fields in _ticks(6):
        arrays = decode_tick(encode_tick_body(fields))
        for name in INT_ROWS + FLAG_ROWS:
            assert arrays.row(name).tolist() == fields[name], name
        for x, y in (("x", "y"), ("target_x", "target_y"), ("prev_target_x", "prev_target_y")):
            assert arrays.cells(x, y).tolist() == [list(c) for c in zip(fields[x], fields[y])]
            assert arrays.cells(x, y).base is not None  # a view of the block, not a copy
    with pytest.raises(KeyError):
        arrays.cells("x", "target_y")


def test_sim_and_agent_services_do_not_import_each_other():
    """The tick's shared pieces live in schemas.tick: neither service package reaches into the other's modules
    (the agent may use the sim's registration helpers only through its command, never its service)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "services"
    for own, other in (("sim", "services.agent"), ("agent", "services.sim.service"), ("agent", "services.world")):
        for path in (root / own).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ImportFrom) and node.module:
                    assert not node.module.startswith(other), f"{path}: imports {node.module}"
                elif isinstance(node, ast.Import):
                    assert not any(a.name.startswith(other) for a in node.names), f"{path}: imports {other}"


def test_each_robots_on_board_state_decodes_to_the_model_and_is_its_own_row_of_the_tick():
    """The sim encodes every robot's OnBoard from the Tick's field map without the model (hot path): it decodes to
    the model, and holds that robot's own entries of the tick, nobody else's."""
    from schemas import OnBoard
    from schemas.tick import onboard_fields

    for obs, fields in _ticks(12):
        free = set(fields["free_pickers"])
        for robot in range(obs.n):
            f = onboard_fields(fields, robot, robot in free, replied=robot)
            msg = decode(encode_fields(OnBoard, **f), OnBoard)
            assert msg == OnBoard(**f)
            assert (msg.t, msg.robot, msg.x, msg.y) == (obs.t, robot, *obs.cells[robot].tolist())
            assert (msg.target_x, msg.target_y) == tuple(obs.target[robot].tolist())
            assert msg.needs_picker == bool(obs.needs_picker[robot]) and msg.free == bool(obs.free_picker[robot])
            assert msg.mission == int(obs.mission[robot]) and msg.final == bool(obs.final)


def test_replace_fields_is_dataclasses_replace_without_the_cached_lists():
    # an agent's own view (its cell and target from on board) is made this way several times a tick
    from dataclasses import fields, replace

    obs = TICKS[5][0]
    _ = obs.cell_list, obs.target_list  # cached on the original
    cells, target = obs.cells.copy(), obs.target.copy()
    cells[0], target[0] = (99, 98), (97, 96)
    fast, slow = replace_fields(obs, cells=cells, target=target), replace(obs, cells=cells, target=target)
    for f in fields(obs):
        assert getattr(fast, f.name) is getattr(slow, f.name), f.name
    assert fast.__dict__.keys() == slow.__dict__.keys()  # no cached list carried over
    assert fast.cell_list[0] == [99, 98] and obs.cell_list[0] != [99, 98]
    with pytest.raises(TypeError, match="'cell' is not a field"):
        replace_fields(obs, cell=cells)
