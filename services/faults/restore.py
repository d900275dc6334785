"""A restarted agent restores its plasticity state from the monitor's latest states (after a process fault).

The monitor answers ``get morph/<run>/state/agent/*`` with the latest :class:`AgentState` of every agent (its
latest-state queryable). :func:`fetch_states` asks for them; :func:`restore_brains` loads them into a fresh brain,
which loads what its policy saved (:meth:`services.policies.interface.Coordinator.restore`; MORPH: its rows of W,
A, BCM thresholds and link ages, h, η and d̂). What the state message does not carry (the reference's previous
co-assignment J^{t−1}, the paper preset's co-assignment history window) restarts empty and refills within a
window; with ``--cold-restart`` nothing is restored at all. Memoryless policies have nothing to restore.
"""

from __future__ import annotations

from schemas.keys import RunKeys
from schemas.messages import AgentState
from services.bus.base import Bus
from services.policies.interface import Coordinator


async def fetch_states(bus: Bus, run: str, *, timeout: float = 2.0) -> dict[int, AgentState]:
    """The monitor's latest state of every agent, by id (empty if no monitor answered)."""
    keys = RunKeys(run)
    replies = await bus.get(f"{keys.prefix}/state/agent/*", timeout=timeout)
    out: dict[int, AgentState] = {}
    for reply in replies:
        if not reply.ok:
            continue
        try:
            state = reply.decode(AgentState)
        except ValueError:
            continue
        prev = out.get(state.agent)
        if prev is None or state.t >= prev.t:
            out[state.agent] = state
    return out


def restore_brains(brains: Coordinator, agent_id: int, states: dict[int, AgentState]) -> int | None:
    """Load ``states`` into the brain of ``agent_id`` (its policy's :meth:`~Coordinator.restore`); returns the tick
    restored, None without an own state. Rows of another fleet size are refused before anything is loaded."""
    if agent_id not in states:
        return None
    n = brains.fleet.n
    for st in states.values():
        if len(st.w_row) != n:
            raise ValueError(f"w_row: state of agent {st.agent} has {len(st.w_row)} entries, the fleet has {n}")
    return brains.restore(agent_id, states)
