"""msgpack codec with versioning.

Wire form of every message: one msgpack map ``{"k": <KIND>, "v": <version>, <field>: <value>, …}``. Enums travel as
their values, tuples as arrays. ``decode`` checks the kind, upgrades older versions through registered upgraders
(none yet: every message is at version 1), refuses newer ones, and validates every field; any failure is a
:class:`DecodeError` that names the field, so a service can count the reject, log it and carry on.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, overload

import msgpack
from pydantic import ValidationError

from schemas.base import DecodeError, Message
from schemas.errors import error_field, error_message

M = TypeVar("M", bound=Message)
KIND_FIELD = "k"
VERSION_FIELD = "v"
MAX_PAYLOAD = 16 * 1024 * 1024  # refuse absurd payloads before unpacking them

# (kind, version) -> function turning a version-`version` field map into a version+1 field map.
Upgrader = Callable[[dict[str, Any]], dict[str, Any]]
_UPGRADES: dict[tuple[str, int], Upgrader] = {}
# kind -> message class that ``decode`` reads; filled by :mod:`schemas.messages` (which imports the Tick module, whose
# fast decoder falls back to ``decode``: the contract hands its classes over instead of being imported here).
_KINDS: dict[str, type[Message]] = {}


def register_kinds(*classes: type[Message]) -> None:
    """Teach the decoder the wire kinds of ``classes`` (each class's ``KIND``)."""
    for cls in classes:
        _KINDS[cls.KIND] = cls


def register_upgrade(kind: str, from_version: int, upgrade: Upgrader) -> None:
    """Teach the decoder to read ``kind`` at ``from_version`` by converting it to ``from_version + 1``."""
    _UPGRADES[(kind, from_version)] = upgrade


def encode(msg: Message) -> bytes:
    """The msgpack bytes of ``msg``."""
    if not isinstance(msg, Message) or not msg.KIND:
        raise TypeError(f"encode() needs a wire message, got {type(msg).__name__}")
    body = msg.model_dump()
    body[KIND_FIELD] = msg.KIND
    try:
        return msgpack.packb(body, use_bin_type=True)
    except (OverflowError, TypeError, ValueError) as exc:  # e.g. an int beyond msgpack's 64-bit range
        raise ValueError(f"cannot encode {msg.KIND} message: {exc}") from None


def encode_fields(cls: type[Message], **fields: Any) -> bytes:
    """The bytes ``encode(cls(**fields))`` decodes to the same message from, without building the model.

    For the tick protocol's hot path (an agent acks every tick): the caller passes the fields as plain Python values
    (ints, floats, bools, lists; enums as their values) that its own state guarantees valid, so the model's validation
    and dump would only cost time. Tests check ``decode(encode_fields(cls, **f), cls) == cls(**f)`` for each use.
    """
    fields[VERSION_FIELD] = cls.VERSION
    fields[KIND_FIELD] = cls.KIND
    return msgpack.packb(fields, use_bin_type=True)


def unpack_envelope(data: bytes | bytearray | memoryview) -> tuple[str, dict[str, Any]]:
    """Unpack bytes into (kind, field map) without validating the fields."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise DecodeError("<payload>", f"expected bytes, got {type(data).__name__}")
    if len(data) > MAX_PAYLOAD:
        raise DecodeError("<payload>", f"payload of {len(data)} bytes exceeds {MAX_PAYLOAD}")
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types (ExtraData, ValueError, TypeError …)
        raise DecodeError("<payload>", f"not msgpack: {type(exc).__name__}: {exc}") from None
    if not isinstance(body, dict):
        raise DecodeError("<root>", f"expected a map, got {type(body).__name__}")
    kind = body.pop(KIND_FIELD, None)
    if not isinstance(kind, str):
        raise DecodeError(KIND_FIELD, "missing or not a string message kind")
    return kind, body


@overload
def decode(data: bytes | bytearray | memoryview, expect: type[M]) -> M: ...
@overload
def decode(data: bytes | bytearray | memoryview, expect: None = None) -> Message: ...


def decode(data, expect=None):
    """Decode bytes into a message; with ``expect``, the message must be of that type.

    Raises :class:`DecodeError` (a ValueError) naming the bad field.
    """
    kind, body = unpack_envelope(data)
    cls = _KINDS.get(kind)
    if cls is None:
        raise DecodeError(KIND_FIELD, f"unknown message kind {kind[:64]!r}")
    if expect is not None and cls is not expect:
        raise DecodeError(KIND_FIELD, f"expected a {expect.KIND!r} message, got {kind!r}", kind=kind)
    version = body.get(VERSION_FIELD)
    if not isinstance(version, int) or isinstance(version, bool):
        raise DecodeError(VERSION_FIELD, f"missing or non-integer schema version {version!r}", kind=kind)
    if version > cls.VERSION:
        raise DecodeError(VERSION_FIELD, f"schema version {version} is newer than this build reads "
                                         f"({cls.VERSION}); upgrade morph-sim", kind=kind)
    while version < cls.VERSION:
        upgrade = _UPGRADES.get((kind, version))
        if upgrade is None:
            raise DecodeError(VERSION_FIELD, f"schema version {version} is no longer supported "
                                             f"(this build reads {cls.VERSION})", kind=kind)
        try:
            body = upgrade(dict(body))
        except Exception as exc:
            raise DecodeError(VERSION_FIELD, f"cannot upgrade from version {version}: {exc}", kind=kind) from None
        version += 1
        body[VERSION_FIELD] = version
    try:
        return cls.model_validate(body)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        first = errors[0]
        more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
        raise DecodeError(error_field(first) or "<root>", f"{error_message(first)}{more}", kind=kind) from None
    except (TypeError, ValueError, RecursionError) as exc:  # defensive: never let garbage crash a service
        raise DecodeError("<root>", f"{type(exc).__name__}: {exc}", kind=kind) from None


def to_payload(message_or_bytes: Message | bytes | bytearray | memoryview) -> bytes:
    """Bytes to put on the wire: encoded messages, raw bytes passed through."""
    if type(message_or_bytes) is bytes:  # the hot path first (isinstance on a pydantic model class is slow)
        return message_or_bytes
    if isinstance(message_or_bytes, (bytes, bytearray, memoryview)):
        return bytes(message_or_bytes)
    if isinstance(message_or_bytes, Message):
        return encode(message_or_bytes)
    raise TypeError(f"payload must be a Message or bytes, got {type(message_or_bytes).__name__}")
