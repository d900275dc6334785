"""Network profiles: a warehouse's Wi-Fi as data (docs/faults.md, "Network profiles").

A profile describes the radio side of the fleet: where the access points are, how a robot roams between them
(hysteresis, hand-over outage), where the racks fade the signal (dead zones), the per-leg latency and loss, and the
bandwidth of each robot's radio and of each access point (netem ``rate`` / ``limit``). The model that applies it is
:mod:`services.faults.network`; named profiles live in ``services/faults/profiles/<name>.toml`` (loaded by :func:`services.faults.network.load_profile`).

Units: times in seconds of sim time, probabilities in percent (as in ``tc netem``), distances in grid cells,
rates in bytes per second, queue limits in messages (netem ``limit`` counts packets).
"""

from __future__ import annotations

import re
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schemas.errors import message
from schemas.faults import Latency

Percent = Annotated[float, Field(ge=0.0, le=100.0, allow_inf_nan=False)]
Seconds = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]

PROFILE_NAME = re.compile(r"^[a-z0-9][a-z0-9_\-]{0,63}$")
#: Closest spacing of the default access-point grid, in cells: one access point per cell is already denser than any
#: deployment, and the grid has ceil(W/spacing) × ceil(H/spacing) points, so a spacing of 1e-6 would ask for 10^14
#: of them before the first tick.
MIN_AP_SPACING = 1.0
#: Most access points an explicit ``cells`` list may place: more than the largest warehouse (extralarge, 30 × 45)
#: has cells. Every robot's move is compared with every access point.
MAX_ACCESS_POINTS = 4096


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, use_enum_values=True, validate_default=True)


class Placement(_Spec):
    """Where the access points are: an explicit list of cells, else a regular grid with ``spacing`` cells between
    neighbours, centred in the tiles it cuts the warehouse into (so every scale gets its own default placement).
    An empty list means no access points: the robots are as if wired, nobody roams."""

    spacing: float = Field(default=12.0, allow_inf_nan=False, description="cells between neighbouring APs")
    cells: list[tuple[float, float]] | None = Field(
        default=None, description="explicit AP positions (x, y); overrides spacing; [] = no radio cells (wired)")

    @field_validator("spacing")
    @classmethod
    def _spacing(cls, value: float) -> float:
        if not value >= MIN_AP_SPACING:
            raise ValueError(f"{value:g} cells is closer than one access point per cell (at least {MIN_AP_SPACING:g})")
        return value

    @field_validator("cells", mode="before")
    @classmethod
    def _count(cls, value):  # counted before each entry is built
        if isinstance(value, list) and len(value) > MAX_ACCESS_POINTS:
            raise ValueError(f"{len(value):,} access points, at most {MAX_ACCESS_POINTS:,}")
        return value


class Handover(_Spec):
    """Roaming: a robot stays with its access point until another is nearer by more than ``hysteresis`` cells; the
    hand-over then silences its radio for an outage drawn from ``outage`` (a latency-style distribution: mean
    ``delay``, spread ``jitter``). During the outage its messages are lost (``during = "lost"``) or wait until the
    radio is back (``"delayed"``: buffered by the driver)."""

    hysteresis: float = Field(default=2.0, ge=0.0, allow_inf_nan=False, description="cells")
    outage: Latency = Field(default_factory=lambda: Latency(delay=0.0))
    during: Literal["lost", "delayed"] = "lost"


class DeadZone(_Spec):
    """Cells with extra loss and latency: ``region = "racks"`` (every rack cell: a robot under a shelf is boxed in
    by metal) or explicit ``cells``."""

    region: Literal["racks", "cells"] = "racks"
    cells: list[tuple[int, int]] | None = None
    loss: Percent = Field(default=0.0, description="extra Bernoulli loss in the zone, percent")
    delay: Seconds = Field(default=0.0, description="extra latency in the zone (link-layer retries), seconds")

    @model_validator(mode="after")
    def _cells(self) -> DeadZone:
        if (self.region == "cells") != (self.cells is not None):
            raise ValueError("dead zone: give cells exactly when region = \"cells\"")
        return self


class Rate(_Spec):
    """A bandwidth limit with a finite FIFO queue (netem ``rate RATE limit N``): a message waits while the queue
    ahead of it drains at ``rate`` bytes/s; one that finds ``limit`` messages queued is dropped."""

    rate: float = Field(gt=0.0, allow_inf_nan=False, description="bytes per second")
    limit: int = Field(default=1000, ge=1, description="queue capacity, messages (the one in transmission included)")


class NetworkProfile(_Spec):
    """One network: radio legs robot ↔ access point; the wired side (sim, monitor, AP backbone) is ideal."""

    name: str = Field(pattern=PROFILE_NAME.pattern)
    description: str = ""
    latency: Latency = Field(default_factory=lambda: Latency(delay=0.0),
                             description="per radio leg (one for robot→sim, two for robot→robot)")
    loss: Percent = Field(default=0.0, description="Bernoulli loss per radio leg, percent")
    access_points: Placement = Field(default_factory=Placement)
    handover: Handover = Field(default_factory=Handover)
    dead_zones: list[DeadZone] = Field(default_factory=list)
    link_rate: Rate | None = Field(default=None, description="each robot's radio (uplink and downlink each)")
    ap_rate: Rate | None = Field(default=None, description="each access point's shared medium, both directions")
    ap_uplink_rate: Rate | None = Field(
        default=None, description="each access point's airtime for its robots' uplink (robots → AP), shared by every "
        "robot associated with it, apart from its downlink; instead of ap_rate")
    ap_downlink_rate: Rate | None = Field(
        default=None, description="each access point's airtime for its downlink (AP → its robots), apart from its "
        "uplink; instead of ap_rate")
    silence_stop: Seconds | None = Field(
        default=None, description="AGV software's safety stop: a robot whose radio has been silent this long (in a "
        "hand-over outage) stands still until it hears again; None = robots never stop")

    @model_validator(mode="after")
    def _one_ap_budget(self) -> NetworkProfile:
        if self.ap_rate is not None and (self.ap_uplink_rate is not None or self.ap_downlink_rate is not None):
            raise ValueError("ap_rate shares one queue between both directions; give it or ap_uplink_rate/"
                             "ap_downlink_rate, not both")
        return self

    @property
    def shared_capacity(self) -> bool:
        """Whether a message's fate depends on other robots' traffic (a rate-limited queue anywhere)."""
        return any(r is not None for r in (self.link_rate, self.ap_rate, self.ap_uplink_rate, self.ap_downlink_rate))


def _explain(exc: ValidationError, where: str) -> ValueError:
    parts = []
    for err in exc.errors(include_url=False):
        loc = "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in err["loc"]).lstrip(".")
        parts.append(f"{loc or '<root>'}: {message(err)}")
    return ValueError(f"{where}: " + "; ".join(parts))


def parse_profile(data: dict, where: str = "network profile") -> NetworkProfile:
    try:
        return NetworkProfile.model_validate(data)
    except ValidationError as exc:
        raise _explain(exc, where) from None
