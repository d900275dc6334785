"""Fault specification models (docs/faults.md). Names follow netem / Chaos Mesh so experiments carry over.

Units: times are seconds of sim time (virtual-time runs) or wall time (paced runs); probabilities are percent
(0–100) as in ``tc netem``; correlation is percent as in netem and Chaos Mesh.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.keys import validate_key_expr

Percent = Annotated[float, Field(ge=0.0, le=100.0, allow_inf_nan=False)]
Seconds = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
AgentRef = int | str  # robot ids are ints; services are named ("sim", "monitor")
SERVICE_AGENTS = ("sim", "monitor")  # the services a fault may name as an agent (they send and receive too)


def _normalize_agents(values: list[AgentRef] | None) -> list[AgentRef] | None:
    # "3" and 3 name the same robot (ids arrive as strings from key chunks, CLI flags and env vars).
    if values is None:
        return None
    out = [int(v) if isinstance(v, str) and v.isdigit() else v for v in values]
    for v in out:  # any other name matches no sender: the fault would silently apply to nobody
        if isinstance(v, int) and v < 0 or isinstance(v, str) and v not in SERVICE_AGENTS:
            raise ValueError(f"{v!r} is not a robot id (0, 1, …) nor a service ({', '.join(SERVICE_AGENTS)})")
    return out


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, use_enum_values=True, validate_default=True)


class Distribution(str, Enum):
    uniform = "uniform"
    normal = "normal"
    pareto = "pareto"


class Latency(_Spec):
    """netem ``delay TIME [JITTER [CORRELATION]] distribution DIST``."""

    delay: Seconds = Field(description="mean added latency, seconds")
    jitter: Seconds = Field(default=0.0, description="spread around the delay, seconds")
    distribution: Distribution = Field(default=Distribution.uniform)
    correlation: Percent = Field(default=0.0, description="netem-style correlation with the previous draw, percent")


class LossModel(str, Enum):
    bernoulli = "bernoulli"
    gilbert_elliott = "gilbert_elliott"


class Loss(_Spec):
    """Bernoulli loss (``percent``), or Gilbert–Elliott given (``percent``, ``burst_length``) or (p, r, 1−h, 1−k).

    Gilbert–Elliott, netem ``gemodel p r 1-h 1-k`` (all percent): p = P(good→bad), r = P(bad→good), 1−h = loss
    probability in the bad state, 1−k = loss probability in the good state. From (loss rate L, mean burst B) with
    simple Gilbert (1−h = 100 %, 1−k = 0): r = 1/B, p = L·r/(1−L).
    """

    model: LossModel = LossModel.bernoulli
    percent: Percent | None = Field(default=None, description="mean loss rate, percent")
    correlation: Percent = Field(default=0.0, description="Bernoulli only: netem correlation, percent")
    burst_length: float | None = Field(default=None, ge=1.0, allow_inf_nan=False, description="mean burst, messages")
    p: Percent | None = None
    r: Percent | None = None
    one_minus_h: Percent | None = Field(default=None, description="loss probability in the bad state, percent")
    one_minus_k: Percent | None = Field(default=None, description="loss probability in the good state, percent")

    @model_validator(mode="after")
    def _consistent(self) -> Loss:
        if self.model == LossModel.bernoulli.value:
            if self.percent is None:
                raise ValueError("loss.percent is required for model bernoulli")
            if any(x is not None for x in (self.burst_length, self.p, self.r, self.one_minus_h, self.one_minus_k)):
                raise ValueError("burst_length, p, r, one_minus_h, one_minus_k apply to model gilbert_elliott only")
            return self
        by_rate = self.percent is not None or self.burst_length is not None
        by_chain = self.p is not None or self.r is not None
        if by_rate == by_chain:
            raise ValueError("gilbert_elliott needs either (percent, burst_length) "
                             "or (p, r[, one_minus_h, one_minus_k])")
        if by_rate:
            if self.percent is None or self.burst_length is None:
                raise ValueError("gilbert_elliott by rate needs both percent and burst_length")
            if self.percent >= 100.0:
                raise ValueError("gilbert_elliott percent must be < 100")
        else:
            if self.p is None or self.r is None:
                raise ValueError("gilbert_elliott by chain needs both p and r")
            if self.r <= 0.0:
                raise ValueError("gilbert_elliott r must be > 0 (else the bad state never ends)")
        return self

    def gilbert_elliott(self) -> tuple[float, float, float, float]:
        """(p, r, 1−h, 1−k) as probabilities in [0, 1]."""
        if self.model != LossModel.gilbert_elliott.value:
            raise ValueError("loss model is not gilbert_elliott")
        if self.p is not None:
            h1 = 1.0 if self.one_minus_h is None else self.one_minus_h / 100.0
            k1 = 0.0 if self.one_minus_k is None else self.one_minus_k / 100.0
            return self.p / 100.0, self.r / 100.0, h1, k1  # type: ignore[operator]
        loss = self.percent / 100.0  # type: ignore[operator]
        r = 1.0 / self.burst_length  # type: ignore[operator]
        p = loss * r / (1.0 - loss)
        if p > 1.0:
            raise ValueError(f"loss {self.percent}% with mean burst {self.burst_length} needs p = {p:.3f} > 1")
        return p, r, 1.0, 0.0


class Duplicate(_Spec):
    percent: Percent
    correlation: Percent = 0.0


class Reorder(_Spec):
    """netem ``reorder PERCENT [CORRELATION] [gap N]``: a reordered message skips the configured latency."""

    percent: Percent
    correlation: Percent = 0.0
    gap: int = Field(default=1, ge=1)


class PartitionDirection(str, Enum):
    to = "to"  # messages from `from_agents` to `to_agents` are dropped
    from_ = "from"  # messages from `to_agents` to `from_agents` are dropped
    both = "both"


class Partition(_Spec):
    """Chaos Mesh ``partition``: cut the links between two agent sets in one or both directions."""

    from_agents: list[AgentRef] = Field(min_length=1)
    to_agents: list[AgentRef] = Field(min_length=1)
    direction: PartitionDirection = PartitionDirection.both

    @field_validator("from_agents", "to_agents")
    @classmethod
    def _agents(cls, value: list[AgentRef]) -> list[AgentRef]:
        return _normalize_agents(value)  # type: ignore[return-value]

    def cuts(self, sender: AgentRef, receiver: AgentRef) -> bool:
        fwd = sender in self.from_agents and receiver in self.to_agents
        back = sender in self.to_agents and receiver in self.from_agents
        if self.direction == PartitionDirection.to.value:
            return fwd
        if self.direction == PartitionDirection.from_.value:
            return back
        return fwd or back


class CrashSignal(str, Enum):
    kill = "kill"  # SIGKILL; the supervisor restarts the agent
    pause = "pause"  # SIGSTOP, then SIGCONT after `pause_for`


class Crash(_Spec):
    """Kill or pause an agent at a tick, every k ticks, or a random agent (seeded)."""

    agent: int | None = Field(default=None, ge=0, description="robot id; None = a random agent")
    at_tick: int | None = Field(default=None, ge=0)
    every: int | None = Field(default=None, ge=1, description="repeat every this many ticks")
    signal: CrashSignal = CrashSignal.kill
    pause_for: Seconds | None = None
    cold_restart: bool = False

    @model_validator(mode="after")
    def _when(self) -> Crash:
        if self.at_tick is None and self.every is None:
            raise ValueError("crash needs at_tick or every")
        if self.signal == CrashSignal.pause.value and self.pause_for is None:
            raise ValueError("crash.pause_for is required with signal pause")
        return self


class Scope(_Spec):
    """Which messages a fault applies to: key expression (relative to ``morph/<run>/``) and agent ids."""

    key_expr: str = Field(default="**", description="relative to morph/<run>/, e.g. 'agent/*/ack'")
    agents: list[AgentRef] | None = Field(default=None, description="senders or receivers; None = every agent")

    @field_validator("key_expr")
    @classmethod
    def _key(cls, value: str) -> str:
        return validate_key_expr(value)

    @field_validator("agents")
    @classmethod
    def _agents(cls, value: list[AgentRef] | None) -> list[AgentRef] | None:
        return _normalize_agents(value)


class Airtime(_Spec):
    """The shared air's access points get this airtime (netem ``rate RATE limit N`` on each access point's queue)
    while the fault is in force: a run whose network profile gives access points a budget (``ap_rate``,
    ``ap_uplink_rate``, ``ap_downlink_rate``), judged by its air process (docs/faults.md)."""

    rate: float = Field(gt=0.0, allow_inf_nan=False, description="bytes per second, each access point and direction")
    limit: int = Field(default=1000, ge=1, le=1_000_000, description="queue capacity, messages")


class FaultSpec(_Spec):
    """One fault: any combination of network effects (or a crash, or the shared air's airtime), a scope, an optional
    duration, a seed."""

    id: str | None = Field(default=None, pattern=r"^[A-Za-z0-9_.\-]{1,64}$")
    latency: Latency | None = None
    loss: Loss | None = None
    duplicate: Duplicate | None = None
    reorder: Reorder | None = None
    partition: Partition | None = None
    crash: Crash | None = None
    rate: Airtime | None = Field(default=None, description="the shared air: every access point's airtime")
    scope: Scope = Field(default_factory=Scope)
    duration: Seconds | None = Field(default=None, description="auto-heal after this long; None = until reset")
    seed: int | None = Field(default=None, ge=0, lt=2**63)

    @model_validator(mode="after")
    def _some_fault(self) -> FaultSpec:
        effects = (self.latency, self.loss, self.duplicate, self.reorder, self.partition, self.crash)
        if all(x is None for x in effects) and self.rate is None:
            raise ValueError("a fault spec needs at least one of latency, loss, duplicate, reorder, partition, crash, "
                             "rate")
        if self.rate is not None and (any(x is not None for x in effects) or self.scope != Scope()):
            raise ValueError("rate changes every access point's airtime for the whole run's radio: give it alone, "
                             "without other effects or a scope")
        if self.reorder is not None and self.latency is None:
            raise ValueError("reorder needs latency (as in netem: reordered messages skip the delay)")
        if self.duration is not None and not math.isfinite(self.duration):
            raise ValueError("duration must be finite")
        return self


FaultOp = Literal["set", "list", "reset"]
