"""The wire contract: message models, msgpack codec with versioning, key expressions, fault specs, JSON Schema."""

from schemas.base import DecodeError, Message
from schemas.codec import decode, encode, register_upgrade, to_payload
from schemas.faults import (
    Crash,
    Distribution,
    Duplicate,
    FaultSpec,
    Latency,
    Loss,
    LossModel,
    Partition,
    PartitionDirection,
    Reorder,
    Scope,
)
from schemas.keys import RunKeys, intersects, matches, validate_key_expr, validate_run_id
from schemas.messages import (
    MESSAGE_TYPES,
    MESSAGES,
    Ack,
    AgentState,
    AirPart,
    AirStats,
    AirVerdicts,
    Commit,
    Event,
    FaultCommand,
    FaultReply,
    Heading,
    HelpReply,
    HelpRequest,
    MetricSample,
    MissionType,
    OnBoard,
    Phase,
    PolicyAnnouncement,
    PolicyMessage,
    Refusal,
    RegistrationReply,
    RegistrationRequest,
    Resolve,
    Role,
    Stop,
    Tick,
)

__all__ = [
    "Ack", "AgentState", "AirPart", "AirStats", "AirVerdicts", "Commit", "Crash", "DecodeError", "Distribution", "Duplicate", "Event", "FaultCommand",
    "FaultReply", "FaultSpec", "Heading", "HelpReply", "HelpRequest", "Latency", "Loss", "LossModel", "MESSAGES",
    "MESSAGE_TYPES", "Message", "MetricSample", "MissionType", "OnBoard", "Partition", "PartitionDirection", "Phase", "PolicyAnnouncement", "PolicyMessage",
    "Refusal",
    "RegistrationReply", "RegistrationRequest", "Reorder", "Resolve", "Role", "RunKeys", "Scope", "Stop", "Tick",
    "decode", "encode", "intersects", "matches", "register_upgrade", "to_payload", "validate_key_expr",
    "validate_run_id",
]
