"""The public policy interface: what a robot's coordination policy sees, decides, learns, takes as parameters, and
saves for a crash restore. MORPH (both presets, every ablation) and every baseline shipped are written against it,
and so is a policy from outside (``--policy package.module:Class`` or an entry point of the group
``morph_sim.policies``; docs/policies.md).

Two classes make a policy:

* a :class:`CoordinationPolicy` is the stateless, named description: its :attr:`~CoordinationPolicy.Params` (a
  pydantic model of its parameters, validated, with defaults and help) and :meth:`~CoordinationPolicy.brains`,
  which builds the state;
* a :class:`Coordinator` (the *brains*) holds the coordination state of the robots in ``owners``: one robot in an
  agent process, the whole fleet in the lab (one brain per robot too when robots hold views of their own). Each
  owned robot has its own state and its own seeded random stream (:meth:`Coordinator.draw`); nothing may be read
  across robots except through the view, and nothing from outside the arguments (no globals, no clocks).

What a robot's brain is handed, at each of its decision points, in order:

1. ``learn(view)`` — a new fleet view (a :class:`~schemas.tick.TickObservation`: every robot's cell, mission,
   target, who is free, the step's deliveries and events), once per view that reached the robot; a late view is
   learnt from late, a lost one never;
2. an AGV that needs a picker and has no request outstanding: :meth:`Coordinator.candidate` (which picker to ask)
   and :meth:`Coordinator.probability` (with what probability; ``draws`` policies compare one uniform draw of the
   robot's own stream, the others ask iff P = 1); a ``broadcast`` policy asks every free picker at once;
3. a picker with requests delivered: :meth:`Coordinator.choose` — which requesting AGV it commits to (the others
   are declined);
4. every ``state_every`` ticks its state is published (:meth:`Coordinator.save`), so a restarted robot resumes
   from it (:meth:`Coordinator.restore`).

The view handed to an AGV holds its own cell and target from on board (always fresh) and the others' as the view
last reported them; :attr:`~schemas.tick.TickObservation.t` says which tick the view describes. The conformance
kit (``morph-sim policy check``, :func:`morph_sim.testing.check_policy`) checks a policy against these rules.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from schemas.tick import TickObservation


class PolicyParams(BaseModel):
    """A policy's parameters: subclass it with one pydantic field per parameter (a default and a ``description``,
    which ``morph-sim policy show`` and ``--help`` print). Values given on the command line arrive as strings and are
    converted by the field's type; an unknown name is refused."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass(frozen=True)
class Fleet:
    """The fleet an agent belongs to: sizes (AGVs first) and the scale name (for d_exp)."""

    n_agvs: int
    n_pickers: int
    scale: str | None = None

    @property
    def n(self) -> int:
        return self.n_agvs + self.n_pickers

    def is_agv(self, robot: int) -> bool:
        return 0 <= robot < self.n_agvs


def agent_rng(seed: int, agent: int) -> np.random.Generator:
    """Agent ``agent``'s own gate stream: independent of the warehouse's and of the other agents'."""
    return np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=(agent,)))


@dataclass(frozen=True)
class SavedState:
    """What a brain publishes of one robot for a crash restore (the monitor keeps the latest of each robot): named
    scalars and named rows of fleet length, beside the W and A rows every brain has (:meth:`Coordinator.weight_rows`,
    :meth:`Coordinator.link_rows`). The plasticity fields are MORPH's; another policy leaves them at zero and uses
    ``scalars`` and ``rows``."""

    theta_row: Sequence[float] | None = None
    age_row: Sequence[int] | None = None
    h: float = 0.0
    eta: float = 0.0
    d_hat: float = 0.0
    scalars: Mapping[str, float] | None = None
    rows: Mapping[str, Sequence[float]] | None = None


@dataclass(frozen=True)
class Mail:
    """A policy message that reached a robot: from whom, sent at which tick, what (the mapping its sender sent)."""

    sender: int
    t: int
    data: Mapping[str, Any]


def pack_mail(data: Mapping[str, Any]) -> bytes:
    """A policy message's content on the wire; ValueError naming the problem when it cannot go."""
    import msgpack

    from schemas.fields import MAX_POLICY_DATA

    if not isinstance(data, Mapping):
        raise ValueError(f"policy message: the content must be a mapping, got {type(data).__name__}")
    try:
        packed = msgpack.packb(dict(data), use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"policy message: cannot pack its content: {exc}") from None
    if len(packed) > MAX_POLICY_DATA:
        raise ValueError(f"policy message: {len(packed)} bytes of content, at most {MAX_POLICY_DATA}")
    return packed


def unpack_mail(data: bytes) -> dict[str, Any]:
    import msgpack

    out = msgpack.unpackb(data, raw=False, strict_map_key=True)
    if not isinstance(out, dict):
        raise ValueError("policy message: its content is not a mapping")
    return out


class Coordinator(ABC):
    """Coordination state and decisions of the robots in ``owners`` (indices into the fleet): one robot in an agent
    service, the whole team in the lab."""

    #: whether the gate consumes a uniform draw per request
    draws: ClassVar[bool] = True
    #: whether links are recomputed from the current tick (no memory): then the links of step t are
    #: known after ``learn(obs_t)``; for plastic policies they are known after ``learn(obs_{t+1})``
    memoryless: ClassVar[bool] = True
    #: whether an AGV asks every free picker at once (services.protocol.dispatch.gate) instead of one
    broadcast: ClassVar[bool] = False

    def __init__(self, fleet: Fleet, owners, seed: int) -> None:
        self.fleet = fleet
        self.owners = np.asarray(list(owners), dtype=int)
        if self.owners.size and (self.owners.min() < 0 or self.owners.max() >= fleet.n):
            raise ValueError(f"owners: agent indices must lie in 0..{fleet.n - 1}")
        self._slot = {int(a): k for k, a in enumerate(self.owners)}
        self._owners_in_order = bool(np.array_equal(self.owners, np.arange(fleet.n)))  # row k is agent k
        self._rngs = [agent_rng(seed, int(a)) for a in self.owners]

    def slot(self, agent: int) -> int:
        try:
            return self._slot[agent]
        except KeyError:
            raise ValueError(f"agent: {agent} is not owned by these brains") from None

    def draw(self, agent: int) -> float:
        """One uniform draw from the agent's own gate stream."""
        return float(self._rngs[self.slot(agent)].random())

    # -- learning ---------------------------------------------------------------------------------------------------
    def learn(self, obs: TickObservation) -> None:  # noqa: B027 - memoryless default
        """Apply the update for step ``obs.t - 1`` (and refresh per-tick topology)."""

    def learn_for(self, obs: TickObservation, agents: Sequence[int]) -> None:
        """:meth:`learn` for the owned ``agents`` only, from ``obs`` (the view they hold): the other owned robots'
        state is untouched. Brains that implement it let the lab keep one brain for a fleet whose robots hold
        views of different ticks (:meth:`CoordinationPolicy.fleet_brains`); each robot's state must then evolve
        exactly as it would in a brain of its own fed its own views."""
        raise NotImplementedError(f"{type(self).__name__} learns the whole team at once")

    # -- an AGV's decision ------------------------------------------------------------------------------------------
    def candidate(self, agv: int, obs: TickObservation, free: np.ndarray | None = None) -> int:
        """The picker this AGV asks (-1: none): the nearest free one to its target (the reference's rule)."""
        return obs.nearest_free_picker(agv, free)

    @abstractmethod
    def probability(self, agv: int, picker: int, obs: TickObservation) -> float:
        """P(respond) for this AGV asking this picker at this tick."""

    # -- a picker's decision ----------------------------------------------------------------------------------------
    def choose(self, picker: int, agvs: Sequence[int], obs: TickObservation | None) -> int:
        """Which of the requesting ``agvs`` picker ``picker`` commits to: an index into ``agvs``, or -1 to commit to
        none. ``agvs`` come in delivery order, ties in the fleet's mission order as the picker's view ``obs`` has it
        (None before its first view); the default takes the first, as the reference's pickers do."""
        return 0

    # -- policy messages ----------------------------------------------------------------------------------------------
    def send(self, agent: int, to: int | None, data: Mapping[str, Any]) -> None:
        """Owned robot ``agent`` sends ``data`` (a mapping msgpack can pack, at most
        :data:`~schemas.fields.MAX_POLICY_DATA` bytes packed) to robot ``to`` (None: every other robot). It leaves
        at the end of the robot's decision point of this tick and reaches the receiver's policy (:meth:`receive`)
        at its first decision point of a later tick by which the network delivered it; it may be lost."""
        from schemas.fields import MAX_POLICY_MESSAGES

        if to is not None and not (0 <= int(to) < self.fleet.n and int(to) != agent):
            raise ValueError(f"policy message: robot {agent} cannot send to {to!r} (another robot's id, or None)")
        box = self.__dict__.setdefault("_outbox", {}).setdefault(self.slot(agent), [])
        if len(box) >= MAX_POLICY_MESSAGES:
            raise ValueError(f"policy message: robot {agent} sent more than {MAX_POLICY_MESSAGES} in one tick")
        box.append((None if to is None else int(to), pack_mail(data)))

    def take_outbox(self, agent: int) -> list[tuple[int | None, bytes]]:
        """What owned robot ``agent`` sent since the last call (its driver sends it)."""
        box = self.__dict__.get("_outbox")
        if not box:
            return []
        return box.pop(self.slot(agent), [])

    def receive(self, agent: int, mail: Sequence[Mail]) -> None:  # noqa: B027 - a silent policy ignores mail
        """The policy messages that reached owned robot ``agent`` by this decision point, in delivery order (ties:
        sender, then the sender's order); called after :meth:`learn` and before the robot decides."""

    # -- what the record and the restore read -----------------------------------------------------------------------
    @abstractmethod
    def link_rows(self) -> np.ndarray:
        """(B, n) 0/1 out-links of the owned agents (row k is agent owners[k])."""

    def out_links(self, agent: int) -> list[int]:
        """The robot ids owned agent ``agent`` links to (what its ack reports every tick)."""
        return np.flatnonzero(self.link_rows()[self.slot(agent)]).tolist()

    def weight_rows(self) -> np.ndarray:
        """(B, n) preference weights of the owned agents (the gate's W)."""
        return self.link_rows().astype(float)

    def save(self, agent: int) -> SavedState:
        """Owned robot ``agent``'s state for a crash restore, beyond its W and A rows (nothing for a memoryless
        policy)."""
        return SavedState()

    def restore(self, agent: int, states: Mapping[int, Any]) -> int | None:
        """Load owned robot ``agent``'s state from the latest published states of the fleet (robot id →
        :class:`~schemas.messages.AgentState`); returns the tick restored, None when ``states`` has none of this
        robot. The default (a memoryless policy) has nothing to load."""
        own = states.get(agent)
        return None if own is None else int(own.t)

    # metrics helpers for a bank that owns the whole fleet
    def team_links(self) -> np.ndarray:
        """(n, n) the fleet's link matrix, row i from agent i's own state (needs all agents owned)."""
        return self._team(self.link_rows())

    def team_weights(self) -> np.ndarray:
        return self._team(self.weight_rows())

    def _team(self, rows: np.ndarray) -> np.ndarray:
        n = self.fleet.n
        if len(self.owners) != n:
            raise ValueError("owners: the team view needs every agent of the fleet")
        if getattr(self, "_owners_in_order", False):  # (a subclass may set owners itself)
            return np.array(rows, dtype=float)  # the rows in agent order already (a team brain): as they are
        out = np.zeros((n, n))
        out[self.owners] = rows
        return out

    def extra_metrics(self) -> dict[str, float]:
        return {}


def state_message(brains: Coordinator, agent: int, role: str, t: int, seq: int = 0):
    """Owned robot ``agent``'s :class:`~schemas.messages.AgentState` at tick ``t``: its W and A rows and what its
    policy saves (:meth:`Coordinator.save`) — what an agent publishes and a restarted one restores from."""
    from schemas.messages import AgentState

    k = brains.slot(agent)
    w = brains.weight_rows()[k]
    a = brains.link_rows()[k]
    n = len(w)
    saved = brains.save(agent)
    theta = saved.theta_row if saved.theta_row is not None else np.zeros(n)
    age = saved.age_row if saved.age_row is not None else np.zeros(n, dtype=int)
    return AgentState(
        agent=agent, role=role, t=t, w_row=[float(v) for v in w], a_row=[bool(v) for v in a],
        theta_row=[float(v) for v in theta], age_row=[int(v) for v in age], h=saved.h, eta=saved.eta,
        d_hat=saved.d_hat, scalars=dict(saved.scalars or {}),
        rows={name: [v if isinstance(v, int) else float(v) for v in row] for name, row in (saved.rows or {}).items()},
        seq=seq)


def policy_choice(brains: Coordinator, picker: int, view: TickObservation | None):
    """The ``choose`` a picker's endpoint takes (services.protocol.dispatch.PickerEndpoint.decide): the brain's own
    when its policy has one, None (the first request: the reference's rule) otherwise."""
    if type(brains).choose is Coordinator.choose:
        return None
    return lambda agvs: brains.choose(picker, agvs, view)


class CoordinationPolicy(ABC):
    """A named coordination policy; ``brains`` builds the per-agent state.

    A policy from outside subclasses it with a ``name``, a ``Params`` model and ``brains``; it is built from its
    parameters by :meth:`from_params` (the default stores them as :attr:`params`)."""

    name: ClassVar[str] | str = ""
    #: its parameters (validated; ``--policy-option KEY=VALUE`` sets them)
    Params: ClassVar[type[PolicyParams]] = PolicyParams
    #: its AGVs send a request to every free picker at once (the sim then takes several requests per AGV a tick)
    broadcast: ClassVar[bool] = False

    def __init__(self, params: PolicyParams | None = None) -> None:
        self.params = params if params is not None else self.Params()

    @classmethod
    def from_params(cls, params: PolicyParams) -> CoordinationPolicy:
        """The policy with these (validated) parameters."""
        return cls(params)

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None = None) -> CoordinationPolicy:
        """The policy from option values (strings from a command line are converted by each field's type);
        ValueError with one line naming the option on a bad one."""
        return cls.from_params(validate_options(cls, options or {}))

    def memoryless(self, fleet: Fleet) -> bool:
        """Whether its brains recompute their links from each tick (then a report at tick t is of step t; a policy
        with memory reports the state its update for step t−1 left)."""
        return bool(self.brains(fleet, [0], 0).memoryless)

    def options(self) -> dict[str, Any]:
        """The values of its parameters (what ``from_options`` takes back)."""
        params = getattr(self, "params", None)
        return params.model_dump(mode="json") if isinstance(params, PolicyParams) else {}

    @abstractmethod
    def brains(self, fleet: Fleet, owners, seed: int) -> Coordinator: ...

    def fleet_brains(self, fleet: Fleet, seed: int) -> Coordinator | None:
        """Brains owning every robot of ``fleet`` whose :meth:`Coordinator.learn_for` updates each robot from its
        own view, exactly as one brain per robot would: the lab then runs a fleet of robots with views of their
        own (late or lost broadcasts, a network profile) in one brain, vectorised across robots, instead of one
        brain per robot. None (the default): the lab builds one brain per robot."""
        return None

    def describe(self) -> dict:
        return {"name": self.name, **self.options()}


def validate_options(cls: type[CoordinationPolicy], options: Mapping[str, Any]) -> PolicyParams:
    """``options`` as ``cls.Params``; ValueError ``policy-option KEY: why`` (the first problem) on a bad one."""
    from pydantic import ValidationError

    try:
        return cls.Params.model_validate(dict(options))
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ())) or "?"
        if err.get("type") == "extra_forbidden":
            known = ", ".join(cls.Params.model_fields) or "none"
            raise ValueError(f"policy-option {where}: policy {cls.name!r} has no such option "
                             f"(its options: {known})") from None
        msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
        raise ValueError(f"policy-option {where}: {msg}, got {err.get('input')!r}") from None
