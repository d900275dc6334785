"""The dispatch protocol as pure code: messages and sim time in, messages and decisions out (no I/O, no bus).

Driven by the lab's in-process discrete-event network (:mod:`morph_sim.lab.network`) and meant to be driven by the
services; see docs/faults.md ("Late, not lost") for the semantics.
"""

from services.protocol.dispatch import (  # noqa: F401
    DEFAULT_REQUEST_TIMEOUT,
    AgvEndpoint,
    Commitment,
    CommitmentDesk,
    Gate,
    Outcomes,
    PickerEndpoint,
    Refusal,
    Reply,
    Request,
    gate,
)
