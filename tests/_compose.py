"""docker-compose.yml as Compose reads it: PyYAML for the file, plus Compose's ``${VAR:-default}`` interpolation."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml


def load(path: Path) -> Any:
    return yaml.safe_load(path.read_text(encoding="utf-8"))


_VAR = re.compile(r"\$(?:\$|\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?-)([^}]*))?\}|([A-Za-z_][A-Za-z0-9_]*))")


def interpolate(value: Any, environ: dict[str, str]) -> Any:
    """Compose's variable interpolation on every string: ``$$``, ``$VAR``, ``${VAR}``, ``${VAR:-d}``, ``${VAR-d}``."""
    if isinstance(value, dict):
        return {k: interpolate(v, environ) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, environ) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name = m.group(1) or m.group(4)
        op, default = m.group(2), m.group(3)
        current = environ.get(name)
        if op == ":-":
            return current if current else default
        if op == "-":
            return default if current is None else current
        return current or ""

    out = _VAR.sub(sub, value)
    if "${" in _VAR.sub("", value.replace("$$", "")):
        raise ValueError(f"unsupported interpolation in {value!r}")
    return out


def defaults_of(value: str) -> list[tuple[str, str | None]]:
    """The ``(variable, default)`` pairs a string interpolates (default None when it has none)."""
    return [(m.group(1) or m.group(4), m.group(3)) for m in _VAR.finditer(value) if m.group(0) != "$$"]
