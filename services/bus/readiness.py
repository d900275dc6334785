"""Readiness: wait until the expected participants hold their liveliness tokens.

Declarations propagate asynchronously in Zenoh, so a process must not start the tick loop just because it opened a
session; it waits until every expected ``morph/<run>/alive/<id>`` token is visible.
"""

from __future__ import annotations

import asyncio

from services.bus.base import Bus, LivelinessEvent


async def wait_for_alive(bus: Bus, key_expr: str, n: int, timeout: float) -> set[str]:
    """Wait until at least ``n`` liveliness tokens match ``key_expr``; return their keys.

    Raises TimeoutError naming how many (and which) were present when ``timeout`` seconds passed.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    present: set[str] = set()
    enough = asyncio.Event()

    def on_change(event: LivelinessEvent) -> None:
        if event.alive:
            present.add(event.key)
        else:
            present.discard(event.key)
        if len(present) >= n:
            enough.set()
        else:
            enough.clear()

    if n == 0:
        return set()
    sub = await bus.subscribe_liveliness(key_expr, on_change, history=True)
    try:
        await asyncio.wait_for(enough.wait(), timeout)
        return set(present)
    except asyncio.TimeoutError:
        shown = ", ".join(sorted(present)[:20]) or "none"
        raise TimeoutError(f"only {len(present)} of {n} participants alive on {key_expr!r} after {timeout:.1f} s "
                           f"(present: {shown})") from None
    finally:
        await sub.close()
