"""The lockstep tick of the warehouse, written once: the sim's side of step ``t`` as a pure state machine.

Step ``t`` (Δ sim seconds), as the sim service and the lab both drive it:

1. :meth:`TickStep.begin` — the demand phase of ``t`` takes effect (a demand-shift episode), the fleet's base
   controller gives AGVs their missions, and the observation of tick ``t`` comes out (what the sim publishes: each
   robot's on-board state and the fleet broadcast);
2. the robots learn and gate at ``t·Δ``, the pickers decide at ``t·Δ + Δ/2`` (:mod:`services.protocol.dispatch`);
   which pickers owe a decision at the picker's decision point is :meth:`TickStep.decision_plan`;
3. :meth:`TickStep.settle` — at the boundary ``(t+1)·Δ`` the commitments delivered by then are applied in delivery
   order (ties: mission order), each only if still valid; the rest come back as refusals for both sides;
4. :meth:`TickStep.finish` — robots whose agent is absent take no new target, robots whose radio has been silent for
   the profile's ``silence_stop`` stand still (an AGV's safety stop), and the world moves one step;
5. after the last step, :meth:`TickStep.final` is the observation the robots learn their last update from.

No I/O and no clock: a driver adds what it needs around these calls (the sim service: publishing, collecting the
robots' answers, pacing, presence; the lab: its in-process event network). The reference's sequential dispatch
(:func:`sequential_commits`), kept for per-seed equality with the reference code, is the other mode of step 2–3:
AGVs in mission order, each committing at once, with no messages.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from services.protocol.dispatch import Commitment, CommitmentDesk, Outcomes, Refusal, gate


@dataclass(frozen=True)
class DemandShift:
    """A demand-shift episode: the side of the warehouse each consecutive ``steps``-long phase draws its demand from.

    ``mode``: ``requests`` draws new requests from the active half (the paper), ``assignment`` assigns queued items
    of the active half first (the reference's variant), ``none`` only marks the phases (the no-shift control)."""

    sides: tuple[Literal["left", "right"], ...]
    steps: int
    mode: Literal["requests", "assignment", "none"] = "requests"

    def side_at(self, t: int) -> str | None:
        """The side that takes effect at the start of step ``t`` (None between phase boundaries)."""
        return self.sides[t // self.steps] if t % self.steps == 0 and t // self.steps < len(self.sides) else None


class TickStep:
    """The sim's side of every lockstep tick over one fleet controller (``services.world.cta.CTAController``).

    Counts what the run's summary reports: ``network_stops`` (robot-steps held by a network profile's silence stop)
    and ``commits_applied``.
    """

    def __init__(self, ctl, *, dt: float, demand: DemandShift | None = None):
        self.ctl = ctl
        self.dt = dt
        self.demand = demand
        self.network_stops = 0
        self.commits_applied = 0

    # -- 1. the tick goes out ------------------------------------------------------------------------------------
    def begin(self):
        """Tick ``t``: its demand phase, the controller's missions, and the observation of the tick."""
        if self.demand is not None:
            side = self.demand.side_at(self.ctl.t)
            if side is not None:
                if self.demand.mode == "requests":
                    self.ctl.wh.set_demand_side(side)
                elif self.demand.mode == "assignment":
                    self.ctl.assignment_side = side
        return self.ctl.begin_tick()

    # -- 2. who decides at the picker's decision point ------------------------------------------------------------
    @staticmethod
    def decision_plan(obs, requests: Mapping[int, Iterable[int]], more: Iterable[int] = ()) -> dict[int, list[int]]:
        """picker -> the AGVs whose requests of this tick it decides over, in mission order; ``more``: pickers that
        decide whether or not a request of this tick reached them (a request of an earlier tick, a commitment in
        flight)."""
        plan: dict[int, list[int]] = {picker: [] for picker in more}
        for agv in obs.request_order:
            for picker in requests.get(int(agv), ()):
                plan.setdefault(picker, []).append(int(agv))
        return plan

    # -- 3. the step boundary: commitments -------------------------------------------------------------------------
    def settle(self, obs, desk: CommitmentDesk, outcomes: Outcomes) -> tuple[list[tuple[int, int]], list[Refusal]]:
        """Apply the commitments delivered by ``(t+1)·Δ`` to the world; returns (applied (picker, AGV) pairs, the
        refusals to send to both sides)."""
        rank = {int(a): i for i, a in enumerate(obs.request_order)}
        wanted = {int(a): (int(obs.target[a, 0]), int(obs.target[a, 1])) for a in np.flatnonzero(obs.needs_picker)}
        # a commitment that did not say its cell is checked against the AGV's current one
        for i, (due, c) in enumerate(desk.inbox):
            if c.cell is None:
                desk.inbox[i] = (due, Commitment(c.picker, c.agv, wanted.get(c.agv, (-1, -1)), c.sent_at, c.seq))
        applied, refusals = desk.settle((obs.t + 1) * self.dt, rank, wanted, self.ctl.commit, outcomes)
        self.commits_applied += len(applied)
        return applied, refusals

    def commit_now(self, commits: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """The sequential mode's step boundary: ``commits`` (picker, AGV) take effect as they are."""
        applied = self.ctl.commit(commits)
        self.commits_applied += len(applied)
        return applied

    # -- 4. the world moves ----------------------------------------------------------------------------------------
    def finish(self, idle: Iterable[int] = (), radio=None) -> int:
        """The step: ``idle`` robots (their agent is absent) take no new target, silent robots stand still, the world
        moves. ``radio``: the run's network model (``services.faults.network.NetworkModel``), if it has one. Returns
        the deliveries of this step."""
        ctl = self.ctl
        ctl.idle = set(idle)
        if radio is not None and radio.profile.silence_stop is not None:
            # AGV software stops a robot that has heard nothing for silence_stop seconds: a robot whose radio is in a
            # hand-over outage that long at the step's start stands still for the step (its path kept)
            ctl.held = radio.silenced(ctl.t * self.dt, radio.profile.silence_stop)
            self.network_stops += len(ctl.held)
        before = ctl.deliveries
        ctl.finish_tick()
        return ctl.deliveries - before

    # -- 5. after the last step -------------------------------------------------------------------------------------
    def final(self):
        """The observation after the last step: the robots learn their last update from it; nobody dispatches."""
        return self.ctl.final_observation()


# ---------------------------------------------------------------------------------------------------------------
# the reference's sequential dispatch, and the comparison of the two modes
# ---------------------------------------------------------------------------------------------------------------
def sequential_commits(obs, coordinator, draw: Callable[[int], float], count=None) -> list[tuple[int, int]]:
    """The reference's sequential dispatch: AGVs in mission order, each asking the nearest picker still free after
    those taken earlier in the step; one picker per cell. ``count(ask, p)`` sees every gate decision."""
    free = obs.free_picker.copy()
    free_left = int(np.count_nonzero(free))
    targets = obs.target_list
    cells: set[tuple[int, int]] = set()
    commits = []
    for agv in obs.requesters().tolist():
        cell = tuple(targets[agv])
        if cell in cells or not free_left:
            continue
        g = gate(coordinator, agv, obs, lambda agv=agv: draw(agv), free)
        if g.picker < 0:
            continue
        if count is not None:
            count(g.ask, g.p)
        if g.ask:
            commits.append((g.picker, agv))
            free_left -= bool(free[g.picker])
            free[g.picker] = False
            cells.add(cell)
    return commits


def first_in_mission_order(requests: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """The picker's rule at zero latency: each picker takes the first request in mission order and declines the others.

    ``requests``: (AGV, picker) pairs in the fleet's mission order. Returns (picker, AGV) commitments."""
    taken: set[int] = set()
    commits = []
    for agv, picker in requests:
        if picker in taken:
            continue
        taken.add(picker)
        commits.append((picker, agv))
    return commits


def concurrent_commits(obs, coordinator, draw: Callable[[int], float]) -> list[tuple[int, int]]:
    """What the protocol commits at zero latency (every AGV asks at once, each picker takes the first requester in
    mission order), replayed with given draws: the other mode, for the comparison the sequential switch reports."""
    requests = []
    for agv in obs.requesters().tolist():
        g = gate(coordinator, agv, obs, lambda agv=agv: draw(agv))
        if g.ask:
            requests.append((agv, g.picker))
    return first_in_mission_order(requests)


def distinct_cells(obs, commits: Iterable[tuple[int, int]]) -> set[tuple[int, int]]:
    """The commitments that take effect, one per cell (the first in the given order): what two modes are compared by."""
    seen, out = set(), set()
    for picker, agv in commits:
        cell = (int(obs.target[agv, 0]), int(obs.target[agv, 1]))
        if cell in seen:
            continue
        seen.add(cell)
        out.add((picker, agv))
    return out
