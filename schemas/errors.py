"""One way to turn a pydantic ``ValidationError`` into the line a user reads: ``field.path: what is wrong``.

Pydantic words its messages for developers (``Value error, …``, ``Assertion failed, …``); a user needs the field and
the reason, once. Every command-line and config error path goes through :func:`explain`.
"""

from __future__ import annotations

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
    text = "; ".join(f"{field_path(e)}: {message(e)}" for e in shown)
    if first_only and len(errors) > 1:
        text += f" (+{len(errors) - 1} more)"
    return f"{where}: {text}" if where else text
