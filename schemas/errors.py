"""One way to turn a pydantic ``ValidationError`` into the line a user reads: ``field.path: what is wrong``.

Pydantic words its messages for developers (``Value error, …``, ``Assertion failed, …``); a user needs the field and
the reason, once. Every command-line and config error path goes through :func:`explain`.
"""

from __future__ import annotations

import re
from typing import Any

from pydantic import ValidationError

_PREFIXES = ("Value error, ", "Assertion failed, ")


def message(err: dict[str, Any]) -> str:
    """The reason of one pydantic error, without pydantic's own prefixes."""
    if err.get("type") == "extra_forbidden":
        return "not a known field"
    text = str(err.get("msg", "invalid"))
    for prefix in _PREFIXES:
        text = text.removeprefix(prefix)
    return text


def field_path(err: dict[str, Any]) -> str:
    """``at[0].spec.loss.percent``: the error's location, list indices in brackets."""
    loc = "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in err.get("loc", ())).lstrip(".")
    return loc or "config"


def explain(exc: ValidationError, *, where: str | None = None, first_only: bool = False) -> str:
    """``[where: ]field: reason[; field: reason …]`` (``first_only``: the first error and a count of the rest)."""
    errors = exc.errors(include_url=False)
    shown = errors[:1] if first_only else errors
    text = "; ".join(_named(e) for e in shown)
    if first_only and len(errors) > 1:
        text += f" (+{len(errors) - 1} more)"
    return f"{where}: {text}" if where else text


def error_field(err: dict[str, Any]) -> str:
    """:func:`field_path` of one error, or the field a model validator names in its context ('' if none)."""
    if err.get("loc"):
        return field_path(err)
    return str((err.get("ctx") or {}).get("field", ""))


error_message = message


def _under(where: str, line: str) -> str:
    return f"{where}: {line}" if where and not line.startswith((f"{where}:", f"{where}.")) else line


def describe(err: dict[str, Any], where: str = "") -> str:
    """One error as ``where: field: reason``, without naming a field twice when the validator's reason does."""
    field = error_field(err)
    msg = message(err)
    if field and msg.startswith(f"{field}: "):
        msg = msg[len(field) + 2:]
    elif field == "policy_options" and msg.startswith("policy-option"):  # names the flag and the option itself
        field = ""
    elif field and msg.startswith(f"{field}."):
        field = ""
    return _under(where, f"{field}: {msg}" if field else msg)


def one_line(exc: ValidationError | ValueError, where: str = "") -> str:
    """Every error of ``exc`` as ``where: field: reason``, joined by ``; ``; a plain ValueError keeps its text."""
    if isinstance(exc, ValidationError):
        return "; ".join(describe(err, where) for err in exc.errors(include_url=False))
    return _under(where, str(exc))


def invalid(exc: ValidationError | ValueError, where: str = "") -> ValueError:
    """``raise invalid(exc, "preset x") from None``: the one-line ValueError of :func:`one_line`."""
    return ValueError(one_line(exc, where))


def _named(err: dict[str, Any]) -> str:
    """:func:`describe`, with ``config`` as the field of an error that names none (a whole-model check)."""
    line = describe(err)
    return line if error_field(err) or re.match(r"^[\w.\[\]-]+( [\w.\[\]]+)?: ", line) else f"config: {line}"
