"""The bus: one async interface (:class:`Bus`) with an in-process (:class:`LocalBus`) and a Zenoh
(:class:`ZenohBus`, imported from :mod:`services.bus.zenoh_bus`) implementation of the same semantics.

``zenoh_bus`` is not imported here on purpose: importing it sets the Zenoh runtime environment and loads the native
library, which in-process runs do not need.
"""

from services.bus.base import (
    Bus,
    BusCounters,
    Declared,
    Interposer,
    LivelinessEvent,
    Query,
    Reply,
    Sample,
    Subscription,
)
from services.bus.local import LocalBus, LocalNetwork
from services.bus.readiness import wait_for_alive

__all__ = [
    "Bus", "BusCounters", "Declared", "Interposer", "LivelinessEvent", "LocalBus", "LocalNetwork", "Query", "Reply",
    "Sample", "Subscription", "wait_for_alive",
]
