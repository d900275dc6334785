"""Field types and enums shared by the wire messages: robot ids, grid cells, tick numbers, headings, missions.

Per-robot data travels as parallel arrays indexed by robot id (0..N−1); ``-1`` means "none" in id and cell arrays.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Annotated, Literal

from pydantic import Field
from pydantic_core import PydanticCustomError

MAX_ROBOTS = 4096
#: a policy message's content, bytes: a bid or a claim is a few numbers; a consensus round over a fleet's bundle of
#: missions is a few hundred bytes (the policy interface refuses more before sending)
MAX_POLICY_DATA = 1024
#: policy messages one robot may send at one decision point (the acks that announce them stay small)
MAX_POLICY_MESSAGES = 64
RobotId = Annotated[int, Field(ge=0, lt=MAX_ROBOTS)]
OptRobotId = Annotated[int, Field(ge=-1, lt=MAX_ROBOTS)]  # -1 = none
Coord = Annotated[int, Field(ge=0, lt=65536)]
OptCoord = Annotated[int, Field(ge=-1, lt=65536)]  # -1 = no target
TickNo = Annotated[int, Field(ge=0)]
SimTime = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Seq = Annotated[int, Field(ge=0, lt=2**63)]
Finite = Annotated[float, Field(allow_inf_nan=False)]

#: What became of the dispatch protocol's messages, counted at the robots and the sim, by name on the wire (the
#: counters of ``services.protocol.dispatch.Outcomes``, which checks it has exactly these fields)
DISPATCH_OUTCOMES = ("requests", "declined", "expired", "commitment_expired", "on_time", "late_applied",
                     "refused_stale", "duplicates")
#: cumulative counts of one endpoint (a robot, or the sim); a counter left out is zero
OutcomeCounts = dict[Literal[DISPATCH_OUTCOMES], Annotated[int, Field(ge=0, lt=2**63)]]


class Heading(IntEnum):
    """TA-RWARE's direction enum order."""

    UP = 0
    DOWN = 1
    LEFT = 2
    RIGHT = 3


class MissionType(IntEnum):
    """A robot's current mission kind (TA-RWARE heuristic vocabulary, 0 = none)."""

    NONE = 0
    PICKING = 1  # AGV: fetch the requested shelf at a rack cell; picker: help at that rack cell
    DELIVERING = 2  # AGV: carry the shelf to a goal cell
    RETURNING = 3  # AGV: put the shelf back on an empty rack cell


def length_mismatch(field: str, got: int, want: int) -> PydanticCustomError:
    return PydanticCustomError(
        "length_mismatch", "{field} has {got} entries, expected {want} (one per robot)",
        {"field": field, "got": got, "want": want},
    )


def robot_id_out_of_range(field: str, value: int, n: int) -> PydanticCustomError:
    return PydanticCustomError(
        "robot_id_range", "{field} holds robot id {value}, but the tick has {n} robots",
        {"field": field, "value": value, "n": n},
    )
