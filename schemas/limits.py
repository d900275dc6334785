"""Upper bounds on the size of every message kind, checked on arrival before anything is decoded.

``MAX_MESSAGE_BYTES`` is the hard bound of the run's transport: the embedded endpoint drops larger messages on
arrival (services/credentials.py explains why 32 KiB). Each kind has its own, tighter bound where its content is
small by construction (an ack names a few pickers and its links), so a receiver refuses an oversized one at the cost
of a ``len()``, before unpacking it.
"""

from __future__ import annotations

MAX_MESSAGE_BYTES = 32 * 1024

# key chunks after morph/<run>/ -> bound in bytes; the first matching rule wins
_AGENT_KIND = {
    "ack": 8 * 1024, "skip": 8 * 1024, "request": 4 * 1024, "reply": 4 * 1024, "commit": 4 * 1024,
    "policy": 2 * 1024,
    "state": MAX_MESSAGE_BYTES,
}
_HEAD = {"events": 16 * 1024, "ctl": 16 * 1024, "registry": 4 * 1024, "alive": 1024}


def max_payload(rel: list[str]) -> int:
    """The bound for a key given as its chunks after ``morph/<run>/`` (``["agent", "3", "ack"]``)."""
    if not rel:
        return MAX_MESSAGE_BYTES
    head = rel[0]
    if head == "agent" and len(rel) >= 3:
        return _AGENT_KIND.get(rel[2], MAX_MESSAGE_BYTES)
    if head == "sim" and len(rel) >= 2 and rel[1] == "@onboard":
        return 4 * 1024  # one robot's own state: a few numbers
    return _HEAD.get(head, MAX_MESSAGE_BYTES)


def max_payload_of_key(key: str) -> int:
    """The bound for a full key ``morph/<run>/…``."""
    return max_payload(key.split("/")[2:])
