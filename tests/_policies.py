"""Policies the tests load by import path (``_policies:Name``): three that break a rule of the conformance kit on
purpose, and one that decides a picker's choice itself."""

import random

import numpy as np

from services.policies.interface import CoordinationPolicy, Coordinator

_ASKED: dict[int, int] = {}


class _Base(Coordinator):
    def link_rows(self):
        return np.zeros((len(self.owners), self.fleet.n))


class _Global(_Base):
    def probability(self, agv, picker, obs):
        _ASKED[picker] = _ASKED.get(picker, 0) + 1  # shared by every robot in the process
        return 1.0 if _ASKED[picker] % 3 else 0.0


class ReadsGlobal(CoordinationPolicy):
    name = "reads-global"

    def brains(self, fleet, owners, seed):
        return _Global(fleet, owners, seed)


class _Random(_Base):
    def probability(self, agv, picker, obs):
        return random.random()


class NonDeterministic(CoordinationPolicy):
    name = "non-deterministic"

    def brains(self, fleet, owners, seed):
        return _Random(fleet, owners, seed)


class _Forgets(_Base):
    memoryless = False

    def __init__(self, fleet, owners, seed):
        super().__init__(fleet, owners, seed)
        self.asked = np.zeros((len(self.owners), fleet.n))

    def learn(self, obs):
        for k, a in enumerate(self.owners):
            if a < obs.n_agvs and obs.needs_picker[a]:
                self.asked[k] += 1

    def probability(self, agv, picker, obs):
        return 1.0 / (1.0 + self.asked[self.slot(agv)].sum() / 10.0)


class CannotRestore(CoordinationPolicy):
    name = "cannot-restore"

    def brains(self, fleet, owners, seed):
        return _Forgets(fleet, owners, seed)


class _Closest(_Base):
    """Asks the nearest free picker always; a picker commits to the requesting AGV whose target is nearest to it."""

    def probability(self, agv, picker, obs):
        return 1.0

    def choose(self, picker, agvs, obs):
        if obs is None:
            return 0
        px, py = obs.cells[picker]
        return int(
            np.argmin([abs(int(obs.target[a][0]) - int(px)) + abs(int(obs.target[a][1]) - int(py)) for a in agvs])
        )


class ClosestRequest(CoordinationPolicy):
    name = "closest-request"

    def brains(self, fleet, owners, seed):
        return _Closest(fleet, owners, seed)


class _Raises(_Base):
    def probability(self, agv, picker, obs):
        if obs.t >= 5:
            raise KeyError(picker)
        return 1.0


class Raises(CoordinationPolicy):
    name = "raises"

    def brains(self, fleet, owners, seed):
        return _Raises(fleet, owners, seed)
