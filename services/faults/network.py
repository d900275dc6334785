"""A warehouse's Wi-Fi as pure code: access points on the layout, roaming with hand-over outages, dead zones among
the racks, and bandwidth-limited queues (docs/faults.md, "Network profiles"). No I/O, no clock: time is whatever the
caller passes (sim seconds in virtual time).

A message crosses at most two radio legs: the sender robot's uplink to its access point and the receiver robot's
downlink from its own; the sim, the monitor and the AP backbone are wired and ideal. Each leg, in order:

1. **hand-over outage** — the robot's radio is silent in ``[start, start + D)`` after it roams; the message is lost
   (cause ``handover``) or waits until the radio is back (``during = "delayed"``);
2. **queues** — the robot's radio (``link_rate``, one queue per direction) and then its access point's shared medium
   (``ap_rate`` for both directions, or ``ap_uplink_rate`` and ``ap_downlink_rate`` apart): FIFO at ``rate`` bytes/s
   with room for ``limit`` messages, shared by every robot associated with the access point; a full queue drops
   (``link_queue``, ``ap_queue``); waiting is latency that grows with load;
3. **loss** — the leg's Bernoulli loss (``loss``) and, in a dead zone, the zone's extra loss (``dead_zone``);
4. **latency** — the leg's latency distribution plus the dead zone's extra delay.

Determinism without a shared random stream: every per-message draw is a hash of (seed, robot, leg, message id,
purpose), so a decision does not depend on the order in which messages are judged nor on which process judges them;
a hand-over's outage is a hash of (seed, robot, hand-over number). Only the queues depend on order, as real queues do:
feed each queue its messages in send-time order (ties broken by the message id), which a discrete-event driver does.

Roaming: a robot is attached to the nearest access point when first seen, and moves to another only when that one is
nearer by more than ``hysteresis`` cells — a robot driving along the bisector of two APs would otherwise hand over at
every step (real clients roam on an RSSI margin, not on the first stronger beacon).
"""

from __future__ import annotations

import bisect
import hashlib
import math
import tomllib
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import numpy as np

from schemas.faults import Latency
from schemas.network import NetworkProfile, Rate, parse_profile
from services.faults.distributions import latency_quantile
from services.inputs import read_text
from services.world.layout import Layout

CAUSES = ("handover", "link_queue", "ap_queue", "loss", "dead_zone")


def uniform(*parts: object) -> float:
    """A uniform draw in [0, 1) that is a pure function of ``parts`` (a counter-based stream)."""
    return _uniform_of("|".join(map(str, parts)).encode())


def _uniform_of(data: bytes, _hash=hashlib.blake2b, _int=int.from_bytes) -> float:
    """:func:`uniform` of the parts whose joined text is ``data``: a message's draws share all but their head, so the
    model joins them once (see :meth:`NetworkModel._draw`)."""
    return (_int(_hash(data, digest_size=8).digest(), "big") >> 11) * (1.0 / (1 << 53))


def _has_spread(lat: Latency) -> bool:
    """Whether a delay from ``lat`` is drawn: only where it has a spread, so a message's parts are hashed only then
    (the hashes are most of the radio model's cost)."""
    return lat.delay > 0.0 or lat.jitter > 0.0


def draw_for(lat: Latency, *parts: object) -> float:
    """A delay from ``lat`` at the quantile ``uniform(*parts)`` (0 where it has no spread: :func:`_has_spread`)."""
    return latency_quantile(lat, uniform(*parts)) if _has_spread(lat) else 0.0


def default_access_points(layout: Layout, spacing: float) -> np.ndarray:
    """A regular grid of APs, one in the centre of each tile of about ``spacing`` × ``spacing`` cells."""
    nx = max(1, math.ceil(layout.W / spacing))
    ny = max(1, math.ceil(layout.H / spacing))
    xs = (np.arange(nx) + 0.5) * layout.W / nx - 0.5
    ys = (np.arange(ny) + 0.5) * layout.H / ny - 0.5
    return np.array([(x, y) for y in ys for x in xs], dtype=float)


class Queue:
    """A FIFO server at ``rate`` bytes/s holding at most ``limit`` messages (the one in transmission included)."""

    def __init__(self, spec: Rate):
        self.rate = spec.rate
        self.limit = spec.limit
        self._finish: deque[float] = deque()
        self._last_arrival = -math.inf

    def admit(self, at: float, size: int) -> float | None:
        """Time the message has left the queue, or None if the queue was full. Calls must come in arrival order;
        an earlier arrival than the last one is treated as arriving with it."""
        at = max(at, self._last_arrival)
        self._last_arrival = at
        finish = self._finish
        while finish and finish[0] <= at:
            finish.popleft()
        if len(finish) >= self.limit:
            return None
        start = finish[-1] if finish else at
        done = max(start, at) + size / self.rate
        finish.append(done)
        return done

    def depth(self, at: float) -> int:
        return sum(1 for f in self._finish if f > at)


@dataclass
class HandoverEvent:
    robot: int
    time: float
    from_ap: int
    to_ap: int
    outage: float  # seconds

    @property
    def end(self) -> float:
        return self.time + self.outage


@dataclass
class _Radio:
    ap: int = -1  # the access point now (after the latest move)
    cell: tuple[int, int] | None = None
    seen_at: float = -math.inf
    # the track, so a message is judged by where the robot was when it was sent, whatever was reported since
    times: list[float] = field(default_factory=list)
    cells: list[tuple[int, int]] = field(default_factory=list)
    aps: list[int] = field(default_factory=list)
    handovers: int = 0
    starts: list[float] = field(default_factory=list)  # outage windows, sorted by start
    ends: list[float] = field(default_factory=list)
    longest: float = 0.0  # longest outage so far (bounds the backward scan)
    up: Queue | None = None
    down: Queue | None = None

    def outage_end(self, at: float) -> float | None:
        """End of the outage window holding ``at``, if any."""
        i = bisect.bisect_right(self.starts, at) - 1
        while i >= 0 and self.starts[i] + self.longest > at:  # only windows that could still be open at ``at``
            if self.ends[i] > at:
                return self.ends[i]
            i -= 1
        return None

    def at(self, time: float) -> tuple[tuple[int, int] | None, int]:
        """(cell, access point) at ``time``; (None, -1) before the robot was first seen."""
        i = bisect.bisect_right(self.times, time) - 1
        return (self.cells[i], self.aps[i]) if i >= 0 else (None, -1)


class Fate(NamedTuple):
    """What happens to one message: delivered at ``delivered_at`` (sim seconds), or lost with a ``cause``. (A tuple:
    the model makes one for every copy of every message.)"""

    delivered_at: float | None
    cause: str | None = None

    @property
    def lost(self) -> bool:
        return self.delivered_at is None


@dataclass
class NetworkStats:
    seen: int = 0
    delivered: int = 0
    delayed: int = 0  # delivered later than sent
    lost: dict[str, int] = field(default_factory=lambda: {c: 0 for c in CAUSES})
    handovers: int = 0
    outage_seconds: float = 0.0


class NetworkModel:
    """The radio network of one run. Robots are ints; anything else (``"sim"``, ``"monitor"``) is wired.

    ``move(robot, time, cell)`` tells the model where a robot is from ``time`` on (the driver calls it when the robot
    reaches a cell: every robot knows its own position on board); ``fate(...)`` decides one message. ``fate`` may be
    given the robots' cells directly, which moves them first.
    """

    def __init__(self, profile: NetworkProfile, layout: Layout, *, seed: int = 0):
        self.profile = profile
        self.layout = layout
        self.seed = int(seed)
        placement = profile.access_points
        if placement.cells is not None:
            aps = np.asarray(placement.cells, dtype=float).reshape(-1, 2)
            bad = [(x, y) for x, y in placement.cells if not (0 <= x < layout.W and 0 <= y < layout.H)]
            if bad:
                raise ValueError(f"network.access_points.cells: {bad[0]} is outside the {layout.W}×{layout.H} grid")
        else:
            aps = default_access_points(layout, placement.spacing)
        self.access_points = aps
        # extra (loss, delay) per cell; zones add up (loss combines as independent draws)
        self.zone_keep = np.ones((layout.H, layout.W))
        self.zone_delay = np.zeros((layout.H, layout.W))
        for zone in profile.dead_zones:
            mask = np.zeros((layout.H, layout.W), dtype=bool)
            if zone.region == "racks":
                mask = ~np.asarray(layout.highway)
            else:
                for x, y in zone.cells or ():
                    if not (0 <= x < layout.W and 0 <= y < layout.H):
                        raise ValueError(f"network.dead_zones.cells: {(x, y)} is outside the "
                                         f"{layout.W}×{layout.H} grid")
                    mask[y, x] = True
            self.zone_keep[mask] *= 1.0 - zone.loss / 100.0
            self.zone_delay[mask] += zone.delay
        self.dead = self.zone_keep < 1.0
        # the same per cell as plain floats, row by row: read for every radio leg of every message
        self._zones = [list(zip(keep, delay)) for keep, delay in zip(self.zone_keep.tolist(), self.zone_delay.tolist())]
        # each access point's airtime: one queue for both directions (ap_rate), or one per direction
        # (ap_uplink_rate / ap_downlink_rate: a direction without a budget is not limited)
        self._ap_queues = [Queue(profile.ap_rate) if profile.ap_rate else None for _ in range(len(aps))]
        up, down = profile.ap_uplink_rate, profile.ap_downlink_rate
        self._ap_up = [Queue(up) if up else None for _ in range(len(aps))] if up or down else None
        self._ap_down = [Queue(down) if down else None for _ in range(len(aps))] if up or down else None
        # airtime faults (schemas.faults.Airtime) in force over windows of sim time: (start, end or None, rate, limit),
        # judged by a message's time at the access point, so they depend on nothing but the messages' own times
        self._airtime: list[tuple[float, float | None, float, int, str | None]] = []
        self._airtime_now: tuple[float, int] | None = None
        # per access point: bytes its shared medium took in and messages it dropped with a full queue
        self.ap_bytes = [0] * len(aps)
        self.ap_drops = [0] * len(aps)
        self._radios: dict[int, _Radio] = {}
        self._nearest: dict[tuple[int, int], tuple[int, np.ndarray]] = {}
        # the heads of the per-message draws, "<seed>|<purpose>|<robot>|<leg>|", as bytes: one per robot and leg
        self._heads: dict[tuple[str, int, str], bytes] = {}
        self.events: list[HandoverEvent] = []  # every hand-over, in the order they happened
        self.stats = NetworkStats()

    # -- positions and roaming ------------------------------------------------------------------------------------
    def nearest(self, cell: tuple[int, int]) -> tuple[int, np.ndarray]:
        """(the nearest access point, every access point's distance) from ``cell``; kept per cell, as robots come
        back to the same cells all run long (read-only arrays: they are shared)."""
        hit = self._nearest.get(cell)
        if hit is None:
            d = np.hypot(self.access_points[:, 0] - cell[0], self.access_points[:, 1] - cell[1])
            d.flags.writeable = False
            hit = self._nearest[cell] = (int(np.argmin(d)), d)
        return hit

    def _radio(self, robot: int) -> _Radio:
        radio = self._radios.get(robot)
        if radio is None:
            rate = self.profile.link_rate
            radio = self._radios[robot] = _Radio(up=Queue(rate) if rate else None,
                                                 down=Queue(rate) if rate else None)
        return radio

    def move(self, robot: int, time: float, cell: tuple[int, int]) -> HandoverEvent | None:
        """Robot ``robot`` is at ``cell`` from ``time`` on; returns the hand-over it caused, if any. Positions of one
        robot must come in time order (an older report is ignored)."""
        radio = self._radio(robot)
        cell = (int(cell[0]), int(cell[1]))
        if time < radio.seen_at or cell == radio.cell:
            return None
        radio.cell, radio.seen_at = cell, time
        if not len(self.access_points):  # wired: nobody to roam between
            self._track(radio, time)
            return None
        best, dist = self.nearest(cell)
        if radio.ap >= 0 and (best == radio.ap or dist[radio.ap] - dist[best] <= self.profile.handover.hysteresis):
            self._track(radio, time)
            return None
        if radio.ap < 0:
            radio.ap = best
            self._track(radio, time)
            return None
        outage = draw_for(self.profile.handover.outage, self.seed, "handover", robot, radio.handovers)
        event = HandoverEvent(robot, time, radio.ap, best, outage)
        radio.ap = best
        self._track(radio, time)
        radio.handovers += 1
        if outage > 0.0:
            radio.starts.append(time)
            radio.ends.append(time + outage)
            radio.longest = max(radio.longest, outage)
        self.events.append(event)
        self.stats.handovers += 1
        self.stats.outage_seconds += outage
        return event

    @staticmethod
    def _track(radio: _Radio, time: float) -> None:
        if radio.times and radio.times[-1] == time:  # two reports at one instant: the later one stands
            radio.cells[-1], radio.aps[-1] = radio.cell, radio.ap  # type: ignore[assignment]
            return
        radio.times.append(time)
        radio.cells.append(radio.cell)  # type: ignore[arg-type]
        radio.aps.append(radio.ap)

    def observe_tick(self, t: int, dt: float, cells) -> list[HandoverEvent]:
        """Every robot's cell as a Tick reports it (robot i at ``cells[i]``). Convention of every driver: the radio
        follows the robot one step behind — the cells of tick ``t`` take effect at ``(t + 1)·Δ``. A client roams on
        signal strength averaged over beacons, and a step (Δ = 1 s by default) is the order of that averaging; and
        it keeps distributed runs deterministic: every process has seen tick t−1's Tick before any message of tick t
        reaches it, but not necessarily tick t's."""
        at = (t + 1) * dt
        events = []
        for robot, cell in enumerate(cells):
            event = self.move(robot, at, (int(cell[0]), int(cell[1])))
            if event is not None:
                events.append(event)
        return events

    def silenced(self, at: float, after: float) -> set[int]:
        """Robots whose radio has been silent for at least ``after`` seconds at sim time ``at`` (inside a hand-over
        outage [s, e) with s + after <= at < e): the safety stop of AGV software that hears nothing."""
        out = set()
        for robot, radio in self._radios.items():
            i = bisect.bisect_right(radio.starts, at - after) - 1
            while i >= 0 and radio.starts[i] + radio.longest > at:
                if radio.ends[i] > at:
                    out.add(robot)
                    break
                i -= 1
        return out

    def ap_of(self, robot: int) -> int:
        return self._radio(robot).ap

    def in_outage(self, robot: int, at: float) -> bool:
        return self._radio(robot).outage_end(at) is not None

    # -- one message ------------------------------------------------------------------------------------------------
    def _draw(self, purpose: str, robot: int, direction: str, msg: bytes) -> float:
        """``uniform(seed, purpose, robot, direction, msg)``, with the message's text already encoded."""
        head = self._heads.get((purpose, robot, direction))
        if head is None:
            head = self._heads[(purpose, robot, direction)] = f"{self.seed}|{purpose}|{robot}|{direction}|".encode()
        return _uniform_of(head + msg)

    def _leg(self, robot: int, direction: str, at: float, msg: bytes, size: int) -> tuple[float | None, str | None]:
        radio = self._radio(robot)
        if radio.starts:  # (no window to be in before the robot's first outage)
            end = radio.outage_end(at)
            if end is not None:
                if self.profile.handover.during == "lost":
                    return None, "handover"
                at = end
        queue = radio.up if direction == "up" else radio.down
        if queue is not None:
            out = queue.admit(at, size)
            if out is None:
                return None, "link_queue"
            at = out
        cell, ap = radio.at(at)
        ap_queues = self._ap_queues if self._ap_up is None else self._ap_up if direction == "up" else self._ap_down
        if self._airtime or self._airtime_now is not None:
            self._airtime_at(at)
        if ap >= 0 and ap_queues[ap] is not None:  # type: ignore[index]
            out = ap_queues[ap].admit(at, size)  # type: ignore[index,union-attr]
            if out is None:
                self.ap_drops[ap] += 1
                return None, "ap_queue"
            self.ap_bytes[ap] += size
            at = out
        p = self.profile
        if p.loss > 0.0 and self._draw("loss", robot, direction, msg) < p.loss / 100.0:
            return None, "loss"
        keep, extra = 1.0, 0.0
        if cell is not None:
            x, y = cell
            keep, extra = self._zones[y][x]
        if keep < 1.0 and self._draw("zone", robot, direction, msg) >= keep:
            return None, "dead_zone"
        lat = p.latency
        delay = latency_quantile(lat, self._draw("latency", robot, direction, msg)) if _has_spread(lat) else 0.0
        return at + delay + extra, None

    def fate(self, sent_at: float, sender: object, receiver: object, msg: object, *, size: int = 0,
             sender_cell: tuple[int, int] | None = None,
             receiver_cell: tuple[int, int] | None = None) -> Fate:
        """Decide one message sent at ``sent_at`` (sim seconds) from ``sender`` to ``receiver``. ``msg`` identifies
        it (e.g. ``(publisher, key, seq)``): the draws are a function of it. ``size``: bytes, for the rate limits."""
        self.stats.seen += 1
        # its identity as each draw hashes it (str(str(m)) == str(m)): once, not once a draw
        text = str(msg).encode()
        if sender_cell is not None and isinstance(sender, int):
            self.move(sender, sent_at, sender_cell)
        at: float | None = sent_at
        cause = None
        if isinstance(sender, int):
            at, cause = self._leg(sender, "up", sent_at, text, size)
        if at is not None and isinstance(receiver, int):
            if receiver_cell is not None:
                self.move(receiver, at, receiver_cell)
            at, cause = self._leg(receiver, "down", at, text, size)
        return self._verdict(sent_at, at, cause)

    def _verdict(self, sent_at: float, at: float | None, cause: str | None) -> Fate:
        """The fate of a message sent at ``sent_at`` whose legs ended at ``at`` (None: lost for ``cause``), counted."""
        if at is None:
            self.stats.lost[cause or "loss"] += 1
            return Fate(None, cause)
        self.stats.delivered += 1
        if at > sent_at:
            self.stats.delayed += 1
        return Fate(at, None)

    def fate_copies(self, sent_at: float, sender: object, receivers: Sequence[object], msg: object, *,
                    size: int = 0) -> list[Fate]:
        """:meth:`fate` of one publication's copy to each of ``receivers``, judged in that order (the same verdicts,
        counts and queue states as one call per copy), the message's identity encoded once for them all."""
        if isinstance(sender, int):  # every copy crosses the sender's uplink on its own
            return [self.fate(sent_at, sender, receiver, msg, size=size) for receiver in receivers]
        text = str(msg).encode()
        out = []
        for receiver in receivers:
            self.stats.seen += 1
            at, cause = (self._leg(receiver, "down", sent_at, text, size) if isinstance(receiver, int)
                         else (sent_at, None))
            out.append(self._verdict(sent_at, at, cause))
        return out

    @property
    def has_ap_budget(self) -> bool:
        """Whether access points have an airtime budget an airtime fault can change."""
        p = self.profile
        return len(self.access_points) > 0 and any(r is not None for r in (p.ap_rate, p.ap_uplink_rate,
                                                                            p.ap_downlink_rate))

    def set_airtime(self, rate: float, limit: int, start: float, end: float | None = None,
                    fault_id: str | None = None) -> None:
        """Every access point's budget is ``rate`` bytes/s with room for ``limit`` messages in [start, end) (a
        fault set again under its id replaces its window from ``start`` on)."""
        if fault_id is not None:
            self.end_airtime(start, fault_id)
        self._airtime.append((start, end, float(rate), int(limit), fault_id))

    def end_airtime(self, at: float, fault_id: str | None = None) -> None:
        """The airtime faults in force (the one of ``fault_id``, or all) end at ``at`` (a reset)."""
        kept = []
        for s, e, r, n, fid in self._airtime:
            if fault_id is None or fid == fault_id:
                if s >= at:
                    continue  # not begun: gone
                e = at if e is None or e > at else e
            kept.append((s, e, r, n, fid))
        self._airtime = kept

    def _airtime_at(self, at: float) -> None:
        """Set the access points' queues to the budget in force at ``at`` (the newest fault in force, else the
        profile's)."""
        now = None
        for start, end, rate, limit, _ in self._airtime:
            if start <= at and (end is None or at < end):
                now = (rate, limit)
        if now == self._airtime_now:
            return
        self._airtime_now = now
        p = self.profile
        for group, spec in ((self._ap_queues, p.ap_rate), (self._ap_up, p.ap_uplink_rate),
                            (self._ap_down, p.ap_downlink_rate)):
            for q in group or ():
                if q is not None:
                    q.rate, q.limit = (now if now is not None else (spec.rate, spec.limit))

    def ap_queue_depths(self, at: float) -> list[int]:
        """Messages in each access point's queue at sim time ``at`` (0 without shared capacity)."""
        out = [q.depth(at) if q is not None else 0 for q in self._ap_queues]
        for queues in (self._ap_up, self._ap_down):
            for i, q in enumerate(queues or ()):
                out[i] += q.depth(at) if q is not None else 0
        return out

    # -- what a monitor shows --------------------------------------------------------------------------------------
    def counters(self, at: float) -> dict[str, float]:
        """The network as of sim time ``at`` (hand-overs started by then, robots in an outage then, robots stopped by
        the profile's silence_stop then) and the messages judged so far, for metric streams ``net/<name>``."""
        started = [e for e in self.events if e.time <= at]
        stop = self.profile.silence_stop
        out: dict[str, float] = {
            "stopped": float(len(self.silenced(at, stop))) if stop is not None else 0.0,
            "handovers": float(len(started)),
            "outage_seconds": float(sum(e.outage for e in started)),
            "in_outage": float(sum(1 for r in self._radios.values() if r.outage_end(at) is not None)),
            "seen": float(self.stats.seen),
            "delivered": float(self.stats.delivered),
        }
        for cause, n in self.stats.lost.items():
            out[f"lost/{cause}"] = float(n)
        return out


# Named profiles are data shipped beside this module (profiles/<name>.toml); a path to a .toml file works too.
def _profile_dir():
    return resources.files("services.faults").joinpath("profiles")


@lru_cache(maxsize=1)
def profile_names() -> tuple[str, ...]:
    """The named profiles shipped in services/faults/profiles/."""
    return tuple(sorted(p.name[:-5] for p in _profile_dir().iterdir() if p.name.endswith(".toml")))


@lru_cache(maxsize=32)
def load_profile(name_or_path: str) -> NetworkProfile:
    """A named profile (``wifi-legacy-roaming``) or a TOML file path; ValueError naming the profile and field."""
    if name_or_path.endswith(".toml"):
        path = Path(name_or_path)
        text = read_text(path, "network")
        where = f"network {path}"
    else:
        if name_or_path not in profile_names():
            raise ValueError(f"network: unknown profile {name_or_path!r}; choose one of "
                             f"{', '.join(profile_names())} or give a .toml file")
        text = _profile_dir().joinpath(name_or_path + ".toml").read_text(encoding="utf-8")
        where = f"network profile {name_or_path}"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not valid TOML: {exc}") from None
    return parse_profile(data, where)
