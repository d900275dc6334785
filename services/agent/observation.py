"""What an agent sees at one tick: the plain-array content of the sim's ``Tick`` message.

An agent's brain learns only from a sequence of :class:`TickObservation` objects and decides dispatch
requests from the latest one; it never reads the warehouse or another agent's memory. The sim's
controller (``services.sim.world.cta``) produces one observation per tick, and the distributed
services carry exactly these fields.

Timing (docs/services.md): the observation for tick ``t`` is taken *after* the controller has assigned items
and advanced the AGV missions for step ``t`` and *before* pickers are dispatched. It carries two blocks:

* the ``prev_*`` block and ``delivered``/``reward``/``loader`` describe step ``t-1`` as it was executed
  (missions after dispatch and release, deliveries and rewards of that environment step). An agent
  applies its plasticity update for step ``t-1`` from this block. At ``t == 0`` there is no previous
  step and ``has_previous`` is false.
* ``mission``/``target``/``task``/``needs_picker``/``free_picker``/``request_order`` describe step ``t``
  before dispatch: the AGVs' missions and what a dispatch decision needs.

``cells`` are the robots' cells at the start of tick ``t``, i.e. after step ``t-1`` moved them: the
positions the reference's update for step ``t-1`` reads, and the positions Proximity uses at step ``t``.

Agent index convention: ``0 .. n_agvs-1`` are AGVs, ``n_agvs .. n-1`` are pickers (TA-RWARE's order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# One mission vocabulary for the wire and the core; re-exported here for the controller and the brains.
from schemas.messages import MissionType as MissionType


#: Missions whose rack-cell target needs a picker standing on it (load or unload).
NEEDS_PICKER = (MissionType.PICKING, MissionType.RETURNING)

NO_CELL = -1  # coordinate used for "no target"


@dataclass(frozen=True, eq=False)
class TickObservation:
    """One tick's world snapshot as seen by every agent (arrays are indexed by agent)."""

    #: the tick index (the step about to be decided)
    t: int
    #: number of AGVs (agents ``0 .. n_agvs-1``)
    n_agvs: int
    #: number of pickers (agents ``n_agvs .. n-1``)
    n_pickers: int
    #: (rows, cols) of the grid: used by the reference's normalised positions x/cols, y/rows
    grid_shape: tuple[int, int]
    #: (n, 2) int, (x, y) cell of each robot at the start of the tick
    cells: np.ndarray
    #: (n,) int8 MissionType of each robot at tick t before dispatch (pickers: PICKING if assigned)
    mission: np.ndarray
    #: (n, 2) int, (x, y) of each robot's mission target at tick t before dispatch, NO_CELL if none
    target: np.ndarray
    #: (n,) int, task id (1-based requested-shelf id) each robot works on at tick t, 0 if none;
    #: a picker's task is that of the AGV it is serving
    task: np.ndarray
    #: (n,) bool, AGVs whose mission needs a picker at its target and none is assigned there
    needs_picker: np.ndarray
    #: (n,) bool, pickers with no assignment (candidates for dispatch)
    free_picker: np.ndarray
    #: (k,) int, the AGVs that hold a mission, in the sim's mission order (order of first assignment);
    #: requests are resolved in this order
    request_order: np.ndarray
    #: whether the ``prev_*`` block describes a real step (false at t == 0)
    has_previous: bool
    #: (n,) int8 MissionType of each robot during step t-1 (after dispatch and release)
    prev_mission: np.ndarray
    #: (n, 2) int, mission targets during step t-1: the co-assignment signal J^{t-1}
    prev_target: np.ndarray
    #: (n,) int, task ids during step t-1
    prev_task: np.ndarray
    #: (n,) bool, AGVs that received TA-RWARE's +1 delivery reward in step t-1
    delivered: np.ndarray
    #: (n,) float, each robot's individual TA-RWARE reward in step t-1
    reward: np.ndarray
    #: (n,) int, for an AGV that delivered in step t-1: the picker that loaded the delivered shelf
    #: (-1 if unknown or not delivered)
    loader: np.ndarray
    #: (n,) bool, robots that took part in a load or unload in step t-1 (the AGV and the picker on its cell)
    handled: np.ndarray
    #: true for the observation after the last step: agents learn from it, nothing is dispatched
    final: bool = False

    @property
    def n(self) -> int:
        return self.n_agvs + self.n_pickers

    @property
    def deliveries(self) -> int:
        """Deliveries in step t-1 (the reference's ``delivery`` argument)."""
        return int(np.count_nonzero(self.delivered))

    def requesters(self) -> np.ndarray:
        """AGVs that ask for a picker at this tick, in mission order."""
        order = self.request_order
        return order[self.needs_picker[order]]

    def coassignment(self, previous: bool = True) -> np.ndarray:
        """J: (n, n) 0/1, pairs whose mission targets are the same cell (zero diagonal).

        This is the reference's "Jaccard" of singleton target sets.
        """
        tgt = self.prev_target if previous else self.target
        # one integer per target cell (y < 65536 on the wire); a robot without a target gets a code of its own,
        # equal to nobody else's: then one comparison gives J
        code = tgt[:, 0] * 65536 + tgt[:, 1]
        none = tgt[:, 0] == NO_CELL
        if none.any():
            code = np.where(none, -(2**40) - np.arange(len(code)), code)  # below every cell code x·65536 + y ≥ −1
        j = code[:, None] == code[None, :]
        np.fill_diagonal(j, False)
        return j.astype(float)

    def task_overlap(self, previous: bool = True) -> np.ndarray:
        """(n, n) 0/1 Jaccard of the singleton task sets (same task id, both non-zero)."""
        task = self.prev_task if previous else self.task
        j = (task[:, None] == task[None, :]) & (task[:, None] > 0)
        np.fill_diagonal(j, False)
        return j.astype(float)

    def nearest_free_picker(self, agv: int, free: np.ndarray | None = None) -> int:
        """The free picker nearest (Manhattan, from its cell) to ``agv``'s target; -1 if none.

        Ties go to the lowest index, as in the reference. ``free`` overrides ``free_picker``
        (the sequential dispatch removes pickers taken earlier in the same tick).
        """
        free = self.free_picker if free is None else free
        pickers = np.flatnonzero(free)
        if pickers.size == 0:
            return -1
        tx, ty = self.target[agv]
        d = np.abs(self.cells[pickers, 0] - tx) + np.abs(self.cells[pickers, 1] - ty)
        return int(pickers[int(np.argmin(d))])
