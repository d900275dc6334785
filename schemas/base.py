"""Base class of every wire message and the typed decode error.

Every message carries a schema version ``v``. A message class declares ``KIND`` (its wire tag, written next to the
fields by the codec) and ``VERSION`` (the schema version this build writes and reads).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import BaseModel, ConfigDict, Field, field_validator


class DecodeError(ValueError):
    """A payload that is not a valid message: garbage bytes, wrong kind, wrong version or a bad field.

    ``field`` names the offending field as a dotted path (``heading.3``, ``spec.loss.percent``); ``<payload>`` when
    the bytes are not msgpack at all and ``<root>`` when they are msgpack but not a map.
    """

    def __init__(self, field: str, reason: str, kind: str | None = None):
        self.field = field
        self.reason = reason
        self.kind = kind
        what = f"{kind} message" if kind else "message"
        super().__init__(f"bad {what}: field {field!r}: {reason}")


class Message(BaseModel):
    """A wire message. Subclasses set ``KIND`` (and ``VERSION`` when a schema changes)."""

    # extra="forbid": a misspelt or foreign field is a reject, not silently ignored data.
    # use_enum_values: enum fields hold plain ints/strs, so msgpack packs them without a custom hook.
    model_config = ConfigDict(extra="forbid", frozen=True, use_enum_values=True, validate_default=True)

    KIND: ClassVar[str] = ""
    # A subclass that bumps VERSION also redeclares ``v`` with the new default (a test checks they agree).
    VERSION: ClassVar[int] = 1

    v: int = Field(default=1, description="schema version of this message kind")

    @field_validator("v")
    @classmethod
    def _check_version(cls, value: int) -> int:
        if value != cls.VERSION:
            raise ValueError(f"schema version {value} is not supported (this build reads version {cls.VERSION})")
        return value
