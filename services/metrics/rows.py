"""The per-tick rows of a run's record (``metrics.csv``) from its messages, as pure code: no bus, no clock, no files.

:class:`RowReducer` takes what the monitor receives — the sim's ticks, the agents' acks (requests, link reports, η,
view ages, dispatch outcome counts), commits and state rows — and gives back the rows that became final, each with
its link matrix, and the W/A snapshots that became complete. The monitor service feeds it live; ``replay`` feeds the
same monitor from a bus record, so both write the same rows from the same messages.

Row ``t`` is due once tick t+2 arrives (the lockstep sim cannot publish tick t+2 before every message of tick t was
sent), but acks travel on other paths than the ticks: a row that still misses an agent's report waits up to
:data:`ROW_GRACE_TICKS` more ticks, and is then closed without it (an absent agent). Per-agent floats are summed in
agent-id order, whatever order the acks came in: a float sum in arrival order would differ between two runs of the
same seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from schemas import Ack, AgentState
from services.metrics import catalogue, measures as M
from services.protocol.dispatch import OutcomeTally, view_age_stats

ROW_GRACE_TICKS = 8


def _by_id(values: dict[int, float]) -> list[float]:
    """Per-agent values in agent-id order, whatever order their acks came in."""
    return [values[a] for a in sorted(values)]


@dataclass
class Row:
    """A row still open: what its tick's messages said so far."""
    t: int
    sim_time: float = 0.0
    deliveries: int | None = None
    requests: int = 0
    commits: int = 0
    ackers: set[int] = field(default_factory=set)
    links: dict[int, list[int]] = field(default_factory=dict)
    # per agent, summed in id order: a float sum in arrival order would differ between two runs of the same seed
    etas: dict[int, float] = field(default_factory=dict)
    # dispatch outcomes by the end of step t: each robot's counts (its ack of t+1), the sim's (its tick t+1)
    outcomes: dict[int, dict[str, int]] = field(default_factory=dict)
    sim_outcomes: dict[str, int] | None = None
    view_ages: dict[int, float] = field(default_factory=dict)


class ClosedRow(NamedTuple):
    """A final row: its ``metrics.csv`` values (catalogue names) and its directed link matrix."""
    values: dict
    links: np.ndarray


class Snapshot(NamedTuple):
    """The fleet's W and A at tick ``t`` (rows of agents whose state never came: NaN in W)."""
    t: int
    W: np.ndarray
    A: np.ndarray


def summary_of_rows(rows: list[dict[str, str]]) -> dict:
    """The summary's totals computed from the record's rows (strings, as read back from metrics.csv)."""
    links = [int(r["links"] or 0) for r in rows]
    return {"steps": len(rows), "deliveries_total": int(rows[-1]["deliveries_total"] or 0) if rows else 0,
            "mean_links": sum(links) / max(1, len(links)), "final_links": links[-1] if links else None,
            "rows_missing": (int(rows[-1]["t"]) + 1 - len(rows)) if rows else 0}


class RowReducer:
    """The rows of a run of ``steps`` steps and ``n_agents`` robots (the first ``n_agvs`` AGVs) from its messages.

    ``plastic``: the policy reports links and η after its update, so a report at tick t belongs to step t−1.
    ``state_every`` / ``snapshot_every``: the ticks whose state rows are W samples / written as snapshots.
    """

    def __init__(self, n_agents: int, n_agvs: int, steps: int, *, state_every: int, snapshot_every: int,
                 plastic: bool):
        self.n = n_agents
        self.steps = steps
        self.state_every = state_every
        self.snapshot_every = snapshot_every
        self.is_agv = np.arange(n_agents) < n_agvs
        self.next_row = 0  # rows below it are final
        self.last_tick = -1  # the newest tick taken
        self.deliveries_total = 0
        self.links_sum = 0  # links over the final rows (the summary's mean)
        self.last: dict = {}  # the newest final row's values
        self._rows: dict[int, Row] = {}
        self._states: dict[int, dict[int, AgentState]] = {}  # tick -> agent -> state
        self._block: dict[int, M.BlockMeans] = {}
        self._graph: tuple[dict[int, list[int]] | None, int, float] = (None, 0, 0.0)  # (links, count, λ₂) of a row
        self._link_shift = 1 if plastic else 0
        self.outcomes = OutcomeTally()  # the robots' dispatch outcome counts, taken in row order
        self._acked: dict[int, int] = {}  # agent -> the newest tick it acked
        self._sim_outcomes: dict[str, int] = {}

    def resume(self, next_row: int, deliveries_total: int) -> None:
        """Continue a record whose rows below ``next_row`` are written elsewhere, its cumulative count at
        ``deliveries_total``."""
        self.next_row = next_row
        self.deliveries_total = deliveries_total

    # -- messages in ---------------------------------------------------------------------------------------------------
    def row(self, t: int) -> Row | None:
        """The open row ``t`` (opened now if need be); None once it is final (a late duplicate)."""
        if t < self.next_row:
            return None
        row = self._rows.get(t)
        if row is None:
            row = self._rows[t] = Row(t)
        return row

    def tick(self, t: int, sim_time: float, deliveries: int, outcomes: dict[str, int] | None
             ) -> tuple[list[ClosedRow], list[Snapshot]]:
        """The sim's tick ``t`` (the deliveries and outcome counts of step t−1); the rows and then the snapshots it
        makes final, each in order."""
        self.last_tick = t
        if t > 0:
            prev = self.row(t - 1)
            if prev is not None:
                prev.deliveries = deliveries
                prev.sim_outcomes = outcomes
        if t < self.steps:
            row = self.row(t)
            if row is not None:
                row.sim_time = sim_time
        return self._close(upto=t - 2, grace=ROW_GRACE_TICKS)

    def ack(self, ack: Ack) -> bool:
        """An agent's ack of phase TICK; True if it is the first of that agent for its open row."""
        first = False
        if ack.t > self._acked.get(ack.agent, -1):
            self._acked[ack.agent] = ack.t
        if ack.t < self.steps:
            row = self.row(ack.t)
            if row is not None and ack.agent not in row.ackers:
                first = True
                row.ackers.add(ack.agent)
                row.requests += len(ack.requests_sent)
                if ack.view_age is not None:
                    row.view_ages[ack.agent] = ack.view_age
        if ack.outcomes is not None and 0 < ack.t <= self.steps:
            # counts as they stood at the start of tick t: the end of step t−1
            row = self.row(ack.t - 1)
            if row is not None:
                row.outcomes.setdefault(ack.agent, ack.outcomes)
        self._links_from(ack.t, ack.agent, ack.links or [], ack.eta)
        return first

    def _links_from(self, t: int, agent: int, links: list[int], eta: float | None) -> None:
        # Links and η belong to the step whose update produced them: a plastic policy's report at tick t carries the
        # state after the update for step t−1 (the reference logs it as step t−1); a memoryless one's is of tick t.
        step = t - self._link_shift
        if not 0 <= step < self.steps:
            return
        row = self.row(step)
        if row is None or agent in row.links:
            return
        row.links[agent] = [j for j in links if 0 <= j < self.n]
        if eta is not None and self._link_shift:
            row.etas[agent] = float(eta)

    def commit(self, t: int) -> None:
        """A picker's commitment of tick ``t``."""
        row = self.row(t)
        if row is not None:
            row.commits += 1

    def state(self, state: AgentState) -> Snapshot | None:
        """An agent's state row; the snapshot it completes, if it completes one that is written."""
        if state.t % self.state_every != 0 and state.t < self.steps:
            return None  # a per-tick state (links only): not a W sample
        if state.t < self.next_row - ROW_GRACE_TICKS:
            return None  # its sample was written already (complete, or as it was when its row became final)
        at = self._states.setdefault(state.t, {})
        at[state.agent] = state
        if len(at) == self.n:
            return self._complete_states(state.t)
        return None

    def final_acks_missing(self) -> set[int]:
        """The agents that acked the tick before the newest one but not the newest one yet. At the end of the run the
        newest tick is the final one, whose acks carry what the last row holds (links, η, outcome counts): the sim
        has them when it ends the run, and the monitor may take them after the end's event."""
        if self.last_tick < 1:
            return set()
        before = self._rows.get(self.last_tick - 1)
        if before is None:
            return set()
        return {a for a in before.ackers if self._acked.get(a, -1) < self.last_tick}

    def finish(self) -> tuple[list[ClosedRow], list[Snapshot]]:
        """The end of the run: every row up to the last completed step (the final tick only reported that step),
        whatever is missing, and every state sample as it is."""
        rows, snapshots = self._close(upto=min(self.last_tick - 1, self.steps - 1))
        for t in sorted(self._states):
            snap = self._complete_states(t)
            if snap is not None:
                snapshots.append(snap)
        return rows, snapshots

    # -- rows out ------------------------------------------------------------------------------------------------------
    def _complete(self, row: Row) -> bool:
        return len(row.ackers) >= self.n and len(row.links) >= self.n and len(row.outcomes) >= self.n

    def _close(self, upto: int, grace: int = 0) -> tuple[list[ClosedRow], list[Snapshot]]:
        rows: list[ClosedRow] = []
        while self.next_row <= upto:
            t = self.next_row
            pending = self._rows.get(t)
            if t > upto - grace and (pending is None or not self._complete(pending)):
                break
            rows.append(self._values(self._rows.pop(t, None) or Row(t)))
            self.next_row += 1
        # A state sample that never completes (an agent was absent at that tick) is written as it is once its row is
        # final, so that the memory does not grow with the length of a run that lost an agent.
        snapshots: list[Snapshot] = []
        while self._states and min(self._states) < self.next_row - ROW_GRACE_TICKS:
            snap = self._complete_states(min(self._states))
            if snap is not None:
                snapshots.append(snap)
        return rows, snapshots

    def _values(self, row: Row) -> ClosedRow:
        A = np.zeros((self.n, self.n), dtype=bool)
        for agent, links in row.links.items():
            A[agent, links] = True
        if row.links != self._graph[0]:
            # the link graph changes only at structural steps: its count and λ₂ (an eigen-solve) are kept until then
            self._graph = (row.links, M.undirected_link_count(A), M.algebraic_connectivity(A))
        _, link_count, lambda2 = self._graph
        delivered = row.deliveries or 0
        self.deliveries_total += delivered
        block = self._block.pop(row.t, None)
        values = {
            "t": row.t, "sim_time": row.sim_time, "deliveries": row.deliveries,
            "deliveries_total": self.deliveries_total,
            "requests": row.requests, "commits": row.commits, "links": link_count,
            "lambda2": lambda2, "eta": float(np.mean(_by_id(row.etas))) if row.etas else None,
            "acks": len(row.ackers), **catalogue.w_block_values(block),
            **self._outcome_values(row),
        }
        values["view_age_mean"], values["view_age_max"] = view_age_stats(_by_id(row.view_ages))
        self.last = values
        self.links_sum += values["links"]
        return ClosedRow(values, A)

    def _outcome_values(self, row: Row) -> dict[str, int]:
        """The dispatch outcome columns of ``row``: a robot or sim whose report of this row is missing (absent, or
        joined late) counts with its latest report."""
        for agent, counts in row.outcomes.items():
            self.outcomes.report(agent, row.t, counts)
        if row.sim_outcomes is not None:
            self._sim_outcomes = row.sim_outcomes
        return catalogue.outcome_values(self.outcomes.total(self._sim_outcomes))

    # -- state samples -------------------------------------------------------------------------------------------------
    def _matrices(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        W = np.full((self.n, self.n), np.nan)
        A = np.zeros((self.n, self.n), dtype=bool)
        for agent, st in self._states.get(t, {}).items():
            W[agent] = st.w_row
            A[agent] = st.a_row
        return W, A

    def _complete_states(self, t: int) -> Snapshot | None:
        W, A = self._matrices(t)
        if not np.isnan(W).any():
            self._block[t] = M.mean_w_by_block(W, self.is_agv)
        del self._states[t]
        if t % self.snapshot_every == 0 or t >= self.steps:
            return Snapshot(t, W, A)
        return None
