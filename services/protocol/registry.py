"""Robot-id registration: agents started without ``--id`` claim one from the sim.

Why: ``docker compose up --scale agent=8`` starts eight identical containers and Compose gives a container no replica
index, so an agent cannot know which robot it drives. It asks the sim instead, on the registry queryable
``morph/<run>/registry`` (:attr:`RunKeys.registry`), sending a :class:`RegistrationRequest` that names an
*instance* (``--instance``/``MORPH_INSTANCE``, else host name and pid, so processes on one host differ). The sim answers with the robot id and its role.

Allocation rules (:class:`IdAllocator`, pure, no clock and no I/O; the caller passes ``now`` and the live ids; the
exchange over a bus, both sides, is :mod:`services.bus.registry`):

* an id is *taken* while its liveliness token ``morph/<run>/alive/<id>`` exists, and for ``hold`` seconds after it
  was granted (the grantee has not declared its token yet; without this two quick claims could get the same id);
* an instance that was granted an id before gets the same id back (a restarted container keeps its robot); if that
  id is still taken (its old session's token has not expired yet, or another process uses the same instance name),
  the request is refused as ``busy`` and the agent retries until the token is gone;
* otherwise the lowest free id, ids never granted to anybody first and ids remembered for a departed instance last,
  so a fleet fills AGVs first (ids 0..A-1) then pickers, and a departed robot's id goes to a newcomer only when no
  fresh id is left (it stays reserved for its own instance while others exist);
* ``want_id`` (an agent asking for a specific id) is granted if that id is free or already this instance's;
  ``want_role`` restricts the choice to that role's ids.

Refusals carry a reason that starts with a code word (``busy:``, ``full:``, ``invalid:``): ``busy`` and ``full``
are worth retrying (an id may free up), ``invalid`` is not. :func:`services.bus.registry.claim_id` is the agent side of the exchange; it
retries with a bounded back-off until its deadline and raises :class:`RegistrationError` naming the last reason.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

BUSY = "busy"  # the id is held by a live token or a fresh grant; retry
FULL = "full"  # every id of the fleet (or of the wanted role) is taken; retry, one may free up
INVALID = "invalid"  # the request can never be granted (id out of range, bad role)
RETRYABLE = (BUSY, FULL)

DEFAULT_HOLD = 30.0  # s a granted id stays reserved until its token shows up (an agent opens, claims, then declares)


class RegistrationError(RuntimeError):
    """Claiming an id failed; the message names the reason (and the registry key)."""


def reason_code(reason: str | None) -> str:
    """The code word of a refusal reason (``busy``, ``full``, ``invalid``)."""
    return (reason or "").partition(":")[0].strip()


@dataclass(frozen=True)
class Grant:
    agent_id: int
    role: str  # "agv" | "picker"
    returning: bool  # the instance had this id before


class Refusal(Exception):
    """The allocator cannot grant the request now (``code`` is one of BUSY, FULL, INVALID)."""

    def __init__(self, code: str, detail: str):
        super().__init__(f"{code}: {detail}")
        self.code = code
        self.detail = detail


@dataclass
class IdAllocator:
    """Pure id allocation for a fleet of ``n_agvs`` AGVs (ids 0..A-1) and ``n_pickers`` pickers (ids A..A+P-1)."""

    n_agvs: int
    n_pickers: int
    hold: float = DEFAULT_HOLD
    by_instance: dict[str, int] = field(default_factory=dict)  # instance -> id it was granted last
    owner: dict[int, str] = field(default_factory=dict)  # id -> instance it was granted to last
    granted_at: dict[int, float] = field(default_factory=dict)  # id -> time of its last grant

    def __post_init__(self) -> None:
        if self.n_agvs < 0 or self.n_pickers < 0 or self.n_agvs + self.n_pickers == 0:
            raise ValueError(f"fleet: need at least one robot, got {self.n_agvs} AGVs and {self.n_pickers} pickers")
        if self.hold < 0:
            raise ValueError(f"hold: must be >= 0 s, got {self.hold}")

    @property
    def n_agents(self) -> int:
        return self.n_agvs + self.n_pickers

    def role_of(self, agent_id: int) -> str:
        if not 0 <= agent_id < self.n_agents:
            raise ValueError(f"agent_id: {agent_id} outside 0..{self.n_agents - 1}")
        return "agv" if agent_id < self.n_agvs else "picker"

    def ids_of(self, role: str | None) -> range:
        if role is None:
            return range(self.n_agents)
        if role == "agv":
            return range(0, self.n_agvs)
        if role == "picker":
            return range(self.n_agvs, self.n_agents)
        raise Refusal(INVALID, f"want_role {role!r} is not agv or picker")

    def taken(self, agent_id: int, alive: set[int], now: float) -> bool:
        """Held by a live token, or granted less than ``hold`` seconds ago (its token may not be up yet)."""
        if agent_id in alive:
            return True
        at = self.granted_at.get(agent_id)
        return at is not None and now - at < self.hold

    def seen_alive(self, agent_id: int) -> None:
        """The grantee's token appeared: the liveliness token now holds the id, the grant hold is over."""
        self.granted_at.pop(agent_id, None)

    def allocate(self, instance: str, alive: Iterable[int], now: float, *, want_id: int | None = None,
                 want_role: str | None = None) -> Grant:
        """Grant an id to ``instance`` or raise :class:`Refusal`. ``alive`` = ids whose liveliness token exists."""
        if not instance:
            raise Refusal(INVALID, "instance name is empty")
        alive = set(alive)
        candidates = self.ids_of(want_role)
        if want_id is not None:
            if want_id not in candidates:
                raise Refusal(INVALID, f"want_id {want_id} is not a{' ' + want_role if want_role else ''} robot id of "
                                       f"this fleet (0..{self.n_agents - 1}, AGVs 0..{self.n_agvs - 1})")
            mine = self.owner.get(want_id) == instance  # a retry of this instance's own grant is no conflict
            if want_id in alive or (not mine and self.taken(want_id, alive, now)):
                raise Refusal(BUSY, f"id {want_id} is held by {self.owner.get(want_id, 'a live agent')!r}")
            return self._grant(instance, want_id, now)
        previous = self.by_instance.get(instance)
        if previous is not None and previous in candidates:
            if self.owner.get(previous) == instance:
                if previous in alive:
                    raise Refusal(BUSY, f"id {previous} of instance {instance!r} still has a live token (an old "
                                        "session not expired yet, or two agents share this instance name)")
                return self._grant(instance, previous, now)
        free = [i for i in candidates if not self.taken(i, alive, now)]
        if not free:
            what = f"{want_role} " if want_role else ""
            raise Refusal(FULL, f"all {len(candidates)} {what}ids are taken")
        fresh = [i for i in free if i not in self.owner]
        chosen = fresh[0] if fresh else free[0]
        return self._grant(instance, chosen, now)

    def _grant(self, instance: str, agent_id: int, now: float) -> Grant:
        returning = self.by_instance.get(instance) == agent_id
        former = self.owner.get(agent_id)
        if former is not None and former != instance:
            self.by_instance.pop(former, None)  # the departed instance's robot now belongs to someone else
        old = self.by_instance.get(instance)
        if old is not None and old != agent_id and self.owner.get(old) == instance:
            del self.owner[old]
        self.by_instance[instance] = agent_id
        self.owner[agent_id] = instance
        self.granted_at[agent_id] = now
        return Grant(agent_id, self.role_of(agent_id), returning)


def policy_mismatch(own, announced) -> str | None:
    """Why an agent whose policy is ``own`` may not join a run whose sim announced ``announced`` (both
    :class:`~schemas.messages.PolicyAnnouncement`), or None when they agree: the same name and the same values of
    every parameter."""
    if own.policy == announced.policy and _canonical(own.options) == _canonical(announced.options):
        return None
    return (f"policy: this agent runs {_shown(own)}, the run's sim announces {_shown(announced)}; start the agent "
            "with the run's --policy and --policy-option values")


def _canonical(options) -> str:
    import json

    return json.dumps(options, sort_keys=True, default=str)


def _shown(a) -> str:
    options = ", ".join(f"{k}={v}" for k, v in sorted(a.options.items()))
    return f"{a.policy!r} ({options})" if options else repr(a.policy)
