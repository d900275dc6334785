"""A (re)starting agent's crash restore: its plasticity state from the monitor's latest states (``state/agent/*``).

A first start finds none and starts from zero; a restart under way resumes from the row the monitor last recorded,
or starts cold (with the reason on the record) when it cannot. ``restore=False`` on the service is the cold restart.
"""

from __future__ import annotations

import logging
import time

from schemas import Event

log = logging.getLogger("morph_sim.agent")

RESTORE_TIMEOUT = 5.0  # seconds a (re)starting agent waits for the monitor's latest states


async def restore_state(agent) -> Event | None:
    """Load the monitor's latest states into ``agent``'s brain; the event to publish: ``agent.restored`` (with the
    tick), or ``agent.cold_start`` (with the reason) when the run is under way and this agent starts from zero.

    ``agent`` is the calling :class:`~services.agent.service.AgentService` (not imported: the service imports this
    module)."""
    from services.faults.restore import fetch_states, restore_brains

    def cold(reason: str) -> Event:
        log.warning("agent %d: starts cold: %s", agent.id, reason)
        return Event(kind="agent.cold_start", source=agent.id, details={"reason": reason})

    started = time.monotonic()
    try:
        # the monitor answers at once (its queries do not queue behind its samples); the timeout only matters
        # when no monitor is there
        states = await fetch_states(agent.bus, agent.config.run_id, timeout=RESTORE_TIMEOUT)
    except Exception as exc:
        agent.intake.refuse("state/agent", f"restore failed: {exc}")
        return cold(f"restore failed: {exc}")
    under_way = bool(states)  # the monitor holds states: the run has started, this is a restart
    if not agent.restore:
        return cold("cold restart requested") if under_way else None
    if not states:
        if time.monotonic() - started >= RESTORE_TIMEOUT:
            return cold(f"no answer from the monitor's state within {RESTORE_TIMEOUT:.0f} s")
        return None  # a first start: nothing recorded yet
    try:
        restored = restore_brains(agent.brains, agent.id, states)
        agent.restored_from = states.get(agent.id)
    except Exception as exc:  # a failed restore is a cold start, never a crash
        agent.intake.refuse("state/agent", f"restore failed: {exc}")
        return cold(f"restore failed: {exc}")
    if restored is None:
        return cold("the monitor holds no state of this agent")
    log.info("agent %d: restored state of tick %d", agent.id, restored)
    return Event(
        kind="agent.restored", source=agent.id, t=restored,
        # the row the brain holds now (read back from it, not copied from the state): the record can show that a
        # restarted agent resumed with the W row last published
        details={"from_t": restored, "w_row": agent.state_message(restored).w_row})
