"""The sim's side of the shared air (a network profile with rate-limited queues, services/faults/air.py): it tells
the air process what was published at each instant, so the air judges an instant once all of it has reached it.

The sim knows every radio publication of a run without seeing the robots' traffic: its own (the fleet broadcast of
each tick, its refusals at each step boundary) and the robots', which their acks list (the requests an AGV sent and
the policy messages any robot sent, in the tick's phase; a picker's commitment and replies, in the resolve phase).
Each instant has two parts, judged in this order: the sim's (before the robots act on the Tick) and the robots'
(announced once every present robot has answered).
"""

from __future__ import annotations

from collections.abc import Iterable

from schemas import AirPart, RunKeys
from schemas.keys import FLEET
from schemas.messages import AIR_CHUNK
from services.faults.air import ROBOTS_PART, SIM_PART


def tick_publications(keys: RunKeys, agent: int, requests_sent: Iterable[int], policy_to: Iterable[int], n: int,
                      counts: dict[tuple[int | str, str], int]) -> None:
    """Count what robot ``agent``'s ack of a tick's phase says it published: a request to each picker it asked and
    each policy message (to one robot, or ``-1``: to every other)."""
    for picker in requests_sent:
        if 0 <= picker < n:
            _add(counts, agent, keys.local(keys.request(agent, picker)))
    for to in policy_to:
        if to == -1 or 0 <= to < n:
            _add(counts, agent, keys.local(keys.policy(agent, None if to == -1 else to)))


def resolve_publications(keys: RunKeys, picker: int, committed_to: int | None, replied_to: Iterable[int], n: int,
                         counts: dict[tuple[int | str, str], int]) -> None:
    """Count what a picker's ack of the resolve phase says it published: its commitment and its replies."""
    if committed_to is not None:
        _add(counts, picker, keys.local(keys.commit(picker)))
    for agv in replied_to:
        if 0 <= agv < n:
            _add(counts, picker, keys.local(keys.reply(picker, agv)))


def refusal_publications(keys: RunKeys, robots: Iterable[int], counts: dict[tuple[int | str, str], int]) -> None:
    for robot in robots:
        _add(counts, "sim", keys.local(keys.refusal(robot)))


def _add(counts: dict[tuple[int | str, str], int], publisher: int | str, key: str) -> None:
    counts[(publisher, key)] = counts.get((publisher, key), 0) + 1


def announcements(sent_at: float, part: int, counts: dict[tuple[int | str, str], int]) -> list[AirPart]:
    """The part as air messages of at most AIR_CHUNK entries each (a broadcasting policy's requests at 128 robots
    are thousands of keys): every one but the last says ``more``."""
    items = sorted(counts.items(), key=lambda kv: (-1 if kv[0][0] == "sim" else kv[0][0], kv[0][1]))
    chunks = [items[i:i + AIR_CHUNK] for i in range(0, len(items), AIR_CHUNK)] or [[]]
    return [AirPart(sent_at=sent_at, part=part, more=i < len(chunks) - 1,
                    publishers=[-1 if p == "sim" else p for (p, _), _ in chunk], keys=[key for (_, key), _ in chunk],
                    counts=[c for _, c in chunk]) for i, chunk in enumerate(chunks)]


class AirAnnouncements:
    """The sim's announcements to the air (a mixin of :class:`services.sim.service.SimService`, which sets
    ``shared_air`` and ``_air_refusals``)."""

    def _air_count(self, ph, msg) -> None:
        """With ``ph.lock`` held: what an ack of ``ph`` says its robot published (phase TICK: requests and policy
        messages; RESOLVE: a commitment and replies)."""
        from schemas import Phase

        if ph.phase == Phase.TICK:
            tick_publications(self.keys, msg.agent, msg.requests_sent, msg.policy_to, self.n, ph.air)
        else:
            resolve_publications(self.keys, msg.agent, msg.committed_to, msg.replied_to, self.n, ph.air)

    def _announce_sim(self, obs) -> None:
        """The sim's part of tick ``obs.t``'s instant: its fleet broadcast and the refusals of the boundary before."""
        counts, self._air_refusals = self._air_refusals, {}
        counts[("sim", FLEET)] = 1
        for msg in announcements(obs.t * self.config.dt, SIM_PART, counts):
            self.bus.put(self.keys.air_parts, msg)

    def _announce_robots(self, ph, sent_at: float) -> None:
        """The robots' part of an instant, as their acks of ``ph`` listed it."""
        if self.shared_air:
            with ph.lock:
                counts = dict(ph.air)
            for msg in announcements(sent_at, ROBOTS_PART, counts) if counts else ():
                self.bus.put(self.keys.air_parts, msg)


__all__ = ["ROBOTS_PART", "SIM_PART", "AirAnnouncements", "announcements", "refusal_publications", "resolve_publications",
           "tick_publications"]
