"""A single-item auction over policy messages (the communication-aware family: auctions, consensus-based bundles).

Every tick each free picker bids for the waiting AGVs nearest to it: a message to each with its bid, the Manhattan
distance from its cell to the AGV's target (lower is better). An AGV asks the best bidder among the pickers that are
still free in its view and whose bid is at most ``max_age`` ticks old; without a bid it waits. A picker asked by
several AGVs commits to the one it bid lowest for. Bids travel as real messages: late, lost or congested like every
message on the radio, so the auction pays for talking where the air is shared.

State (for a restart): each AGV's bids, one per picker (its distance and the tick it was made).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from services.policies.interface import CoordinationPolicy, Coordinator, PolicyParams, SavedState


class AuctionParams(PolicyParams):
    max_age: int = Field(default=3, ge=0, description="ticks a bid stays valid after it was made")
    max_bids: int = Field(default=4, ge=1, le=64, description="AGVs a free picker bids for each tick (nearest first)")


class AuctionBrains(Coordinator):
    draws = False  # an AGV asks its best bidder for sure: the auction decides, not a coin
    memoryless = False

    def __init__(self, fleet, owners, seed, params: AuctionParams):
        super().__init__(fleet, owners, seed)
        self.p = params
        b = len(self.owners)
        self.bid = np.full((b, fleet.n), -1.0)  # an owned AGV's bid from each picker (distance), -1: none
        self.bid_t = np.full((b, fleet.n), -1.0)  # the tick it was made
        self.now = 0

    def learn(self, obs):
        self.now = int(obs.t)
        if obs.final:
            return
        waiting = np.flatnonzero(obs.needs_picker[: obs.n_agvs])
        for robot in self.owners.tolist():
            if self.fleet.is_agv(robot) or not obs.free_picker[robot] or waiting.size == 0:
                continue
            cx, cy = obs.cells[robot]
            distance = np.abs(obs.target[waiting, 0] - cx) + np.abs(obs.target[waiting, 1] - cy)
            for j in np.lexsort((waiting, distance))[: self.p.max_bids]:
                self.send(robot, int(waiting[j]), {"bid": int(distance[j])})

    def receive(self, agent, mail):
        k = self.slot(agent)
        for m in mail:
            bid = m.data.get("bid")
            if isinstance(bid, int) and bid >= 0 and not self.fleet.is_agv(m.sender):
                self.bid[k, m.sender], self.bid_t[k, m.sender] = bid, m.t

    def _valid(self, agv, free):
        k = self.slot(agv)
        ok = (self.bid[k] >= 0) & (self.now - self.bid_t[k] <= self.p.max_age) & free
        return k, np.flatnonzero(ok)

    def candidate(self, agv, obs, free=None):
        k, pickers = self._valid(agv, obs.free_picker if free is None else free)
        if pickers.size == 0:
            return -1
        return int(pickers[np.lexsort((pickers, self.bid[k, pickers]))[0]])  # lowest bid, then lowest id

    def probability(self, agv, picker, obs):
        return 1.0

    def choose(self, picker, agvs, obs):
        if obs is None:
            return 0
        cx, cy = obs.cells[picker]
        return int(np.argmin([abs(int(obs.target[a][0]) - int(cx)) + abs(int(obs.target[a][1]) - int(cy))
                              for a in agvs]))

    def link_rows(self):
        # a link: a valid bid between the pair (what the record's links show of the auction)
        valid = (self.bid >= 0) & (self.now - self.bid_t <= self.p.max_age)
        return valid.astype(float)

    def save(self, agent):
        k = self.slot(agent)
        return SavedState(scalars={"now": float(self.now)},
                          rows={"bid": self.bid[k].tolist(), "bid_t": self.bid_t[k].tolist()})

    def restore(self, agent, states):
        own = states.get(agent)
        if own is None:
            return None
        k = self.slot(agent)
        if "bid" in own.rows and "bid_t" in own.rows:
            self.bid[k], self.bid_t[k] = own.rows["bid"], own.rows["bid_t"]
        self.now = int(own.scalars.get("now", own.t))
        return own.t


class AuctionPolicy(CoordinationPolicy):
    """Single-item auction: free pickers bid (their distance) for waiting AGVs; an AGV asks its best bidder."""

    name = "auction"
    Params = AuctionParams

    def brains(self, fleet, owners, seed):
        return AuctionBrains(fleet, owners, seed, self.params)
