"""A restarted agent restores its plasticity state from the monitor's latest states (after a process fault).

The monitor answers ``get morph/<run>/state/agent/*`` with the latest :class:`AgentState` of every agent (its
latest-state queryable). :func:`fetch_states` asks for them; :func:`restore_brains` loads them into a fresh brain:

* paper preset (directed rows): the agent's own row of W, A, BCM thresholds and link ages, its h, η, d̂;
* reference preset (each agent holds a replica of the symmetric state): every agent's row from that agent's latest
  state (rows may come from different ticks — the replica is as fresh as the monitor's record), the own row last so
  it wins where the symmetric halves disagree; the fleet-level d̂ and η from the own state.

The step counter is set to the state's tick, so structural updates (every k steps) stay in phase. What the state
message does not carry (the reference's previous co-assignment J^{t−1}, the paper preset's co-assignment history
window) restarts empty and refills within a window; with ``--cold-restart`` nothing is restored at all.
Memoryless policies have nothing to restore.
"""

from __future__ import annotations

import numpy as np

from schemas.keys import RunKeys
from schemas.messages import AgentState
from services.bus.base import Bus
from services.policies.coordinators import Coordinator, MorphBrains


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
    """Load ``states`` into the brain of ``agent_id``; returns the tick restored, None without an own state."""
    own = states.get(agent_id)
    if own is None:
        return None
    if not isinstance(brains, MorphBrains):
        return own.t
    s = brains.state
    n = s.W.shape[-1]
    for st in states.values():
        if len(st.w_row) != n:
            raise ValueError(f"w_row: state of agent {st.agent} has {len(st.w_row)} entries, the fleet has {n}")
    if brains.preset == "reference":
        r = brains._rep[brains.slot(agent_id)]
        for j, st in sorted(states.items(), key=lambda kv: kv[0] == agent_id):  # own row last
            s.W[r, j] = st.w_row
            s.A[r, j] = np.asarray(st.a_row, dtype=float)
            s.theta_bcm[r, j] = st.theta_row
            s.age[r, j] = st.age_row
            s.h[r, j] = st.h
    else:
        k = brains.slot(agent_id)
        s.W[k] = own.w_row
        s.A[k] = np.asarray(own.a_row, dtype=float)
        s.theta_bcm[k] = own.theta_row
        s.age[k] = own.age_row
        s.h[k] = own.h
    s.dhat = own.d_hat
    s.eta = own.eta
    s.t = own.t
    return own.t
