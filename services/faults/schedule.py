"""A schedule of timed faults for one run (TOML), validated by pydantic with errors naming the field.

Format — one ``[[at]]`` table per command, at a tick or at a sim time (seconds)::

    [[at]]
    tick = 100                       # or: time = 100.0
    [at.spec]                        # op defaults to "set"
    id = "burst"
    duration = 50.0                  # auto-heal after 50 sim seconds
    [at.spec.loss]
    model = "gilbert_elliott"
    percent = 20
    burst_length = 4

    [[at]]
    tick = 300
    op = "reset"                     # heal everything (or fault_id = "burst")

Every process of a run loads the same file and applies each command locally at its boundary (no message has to
race the tick traffic), so a scheduled run is as deterministic as one without faults.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from schemas.errors import invalid
from schemas.faults import FaultOp, FaultSpec
from schemas.messages import FaultCommand
from services.inputs import at_most, read_text


class TimedCommand(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    tick: int | None = Field(default=None, ge=0, description="apply at the start of this tick")
    time: float | None = Field(default=None, ge=0.0, allow_inf_nan=False, description="apply at this sim time, s")
    op: FaultOp = "set"
    spec: FaultSpec | None = None
    fault_id: str | None = None

    @model_validator(mode="after")
    def _when_and_what(self) -> TimedCommand:
        if (self.tick is None) == (self.time is None):
            raise ValueError("give exactly one of tick and time")
        FaultCommand(op=self.op, spec=self.spec, fault_id=self.fault_id)  # same rules as the wire command
        return self

    def at(self, dt: float) -> float:
        """Sim time of this command for a run with Δ = ``dt``."""
        return self.tick * dt if self.tick is not None else self.time  # type: ignore[return-value]

    def command(self) -> FaultCommand:
        return FaultCommand(op=self.op, spec=self.spec, fault_id=self.fault_id, sender="schedule")


class FaultSchedule(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    at: list[TimedCommand] = Field(default_factory=list)

    def timeline(self, dt: float) -> list[tuple[float, FaultCommand]]:
        """(sim time, command) in time order; commands at the same time keep their file order."""
        indexed = sorted(enumerate(self.at), key=lambda ic: (ic[1].at(dt), ic[0]))
        return [(c.at(dt), c.command()) for _, c in indexed]


#: Most entries a schedule may have. A schedule is a handful of timed faults written by hand (the ones the project
#: ships have one to a few); each active fault is checked against every message, and each answer about the faults
#: names all of them, so the cost in every process grows with the square of the faults active at once: 300 set at
#: tick 0 already take 36 MB more and seconds per tick, 2000 take 1.3 GB.
MAX_SCHEDULE_ENTRIES = 256


def parse_schedule(data: dict, where: str = "schedule") -> FaultSchedule:
    entries = data.get("at") if isinstance(data, dict) else None
    if isinstance(entries, list):  # counted before pydantic builds a model of each
        at_most(len(entries), MAX_SCHEDULE_ENTRIES, f"{where}: at", "entries")
    try:
        return FaultSchedule.model_validate(data)
    except ValidationError as exc:
        raise invalid(exc, where) from None


def load_schedule(path: str | Path, n_agents: int | None = None) -> FaultSchedule:
    """Read and validate a schedule file; ValueError naming the file and the bad field. With ``n_agents``, every
    agent a command names must be in the fleet (a crash of agent 99 in a fleet of 8 would otherwise never happen)."""
    path = Path(path)
    text = read_text(path, "fault_schedule")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"fault schedule {path}: not valid TOML: {exc}") from None
    schedule = parse_schedule(data, f"fault schedule {path}")
    if n_agents is not None:
        check_fleet(schedule, n_agents, f"fault schedule {path}")
    return schedule


def check_fleet(schedule: FaultSchedule, n_agents: int, where: str = "schedule") -> None:
    """ValueError naming the entry whose crash or scope names an agent outside ``0..n_agents-1``."""
    for i, timed in enumerate(schedule.at):
        spec = timed.spec
        if spec is None:
            continue
        if spec.crash is not None and spec.crash.agent is not None and not 0 <= spec.crash.agent < n_agents:
            raise ValueError(f"{where}: at[{i}].spec.crash.agent: agent {spec.crash.agent} outside 0..{n_agents - 1} "
                             f"(a fleet of {n_agents})")
        agents = getattr(getattr(spec, "scope", None), "agents", None) or []
        for a in agents:
            if isinstance(a, int) and not 0 <= a < n_agents:
                raise ValueError(f"{where}: at[{i}].spec.scope.agents: agent {a} outside 0..{n_agents - 1} "
                                 f"(a fleet of {n_agents})")
