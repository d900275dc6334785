"""One formatter of validation errors: pydantic's errors as one line that names each bad field.

Every place that validates user or wire input (run configuration, CLI values, presets, fault specs and schedules,
decoded messages) reports through :func:`one_line`, so an error always reads ``field: what is wrong`` — never
pydantic's multi-line report, its documentation URL, its ``Value error,`` prefix, or a field named twice
(``spec: spec: …``) when a validator's own message already starts with the field.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

_PREFIXES = ("Value error, ", "Assertion failed, ")


def error_field(err: dict[str, Any]) -> str:
    """``a.b[0].c`` for pydantic's ``loc`` (a model validator's error may name its field in ``ctx``)."""
    loc = err.get("loc", ())
    if not loc:
        return str((err.get("ctx") or {}).get("field", ""))
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")


def error_message(err: dict[str, Any]) -> str:
    msg = str(err.get("msg", "invalid"))
    for prefix in _PREFIXES:
        msg = msg.removeprefix(prefix)
    return msg


def _under(where: str, line: str) -> str:
    return f"{where}: {line}" if where and not line.startswith((f"{where}:", f"{where}.")) else line


def describe(err: dict[str, Any], where: str = "") -> str:
    """One error as ``where: field: message``, without naming a field twice."""
    field = error_field(err)
    msg = error_message(err)
    if field and msg.startswith(f"{field}: "):  # the validator's own message already names the field
        msg = msg[len(field) + 2:]
    elif field and msg.startswith(f"{field}."):  # … or one of its sub-fields
        field = ""
    return _under(where, f"{field}: {msg}" if field else msg)


def one_line(exc: ValidationError | ValueError, where: str = "") -> str:
    """Every error of ``exc`` as ``where: field: message``, joined by ``; ``; a plain ValueError keeps its text."""
    if isinstance(exc, ValidationError):
        return "; ".join(describe(err, where) for err in exc.errors(include_url=False))
    return _under(where, str(exc))


def invalid(exc: ValidationError | ValueError, where: str = "") -> ValueError:
    """``raise invalid(exc, "spec") from None``: the one-line ValueError of :func:`one_line`."""
    return ValueError(one_line(exc, where))
