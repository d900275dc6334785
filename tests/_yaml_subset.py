"""A strict parser for the small YAML subset docker-compose.yml is written in, plus Compose's ``${VAR:-default}``.

Why not PyYAML: it is not a dependency of the project, and the compose file does not need more than this. The
subset is strict — anything outside it raises ``YamlSubsetError`` with the line number instead of being guessed —
so a construct that real YAML would read differently cannot slip through:

* block mappings ``key: value`` / ``key:`` + an indented block; keys are plain words or quoted; duplicate keys fail;
* block sequences ``- scalar`` or ``- [flow list]`` (no mappings inside sequences);
* flow sequences of scalars on one line: ``["a", "b", c]``;
* scalars: double-quoted (JSON escapes), single-quoted (``''`` escape) or plain; plain scalars are typed by the YAML
  1.2 core schema (null, true/false, integers, floats, else a string); YAML 1.1's ``yes/no/on/off`` are rejected
  unquoted because YAML 1.1 parsers (and Compose's own history) read them as booleans;
* anchors on a block (``key: &name``) and aliases as a whole value (``key: *name``); no merge keys, tags, block
  scalars (``|``, ``>``), multi-documents or tabs.
"""

from __future__ import annotations

import json
import re
from typing import Any


class YamlSubsetError(ValueError):
    pass


_INT = re.compile(r"^[-+]?(0|[1-9][0-9]*)$")
_FLOAT = re.compile(r"^[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?$")
_KEY = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_YAML11_BOOLS = {"yes", "no", "on", "off", "y", "n"}


def _strip_comment(line: str) -> str:
    """Drop a ``#`` comment that starts the line or follows whitespace, outside quotes."""
    quote = None
    i = 0
    while i < len(line):
        c = line[i]
        if quote:
            if c == "\\" and quote == '"':
                i += 2
                continue
            if c == quote:
                if quote == "'" and line[i + 1:i + 2] == "'":
                    i += 2
                    continue
                quote = None
        elif c in "\"'":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i].rstrip()
        i += 1
    if quote:
        raise YamlSubsetError(f"unterminated {quote} quote")
    return line.rstrip()


def _scalar(text: str) -> Any:
    text = text.strip()
    if not text:
        raise YamlSubsetError("empty scalar")
    if text[0] == '"':
        if not text.endswith('"') or len(text) < 2:
            raise YamlSubsetError(f"bad double-quoted scalar {text!r}")
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise YamlSubsetError(f"bad double-quoted scalar {text!r}: {exc}") from None
    if text[0] == "'":
        body = text[1:-1]
        if not text.endswith("'") or len(text) < 2 or re.search(r"(?<!')'(?!')", body.replace("''", "")):
            raise YamlSubsetError(f"bad single-quoted scalar {text!r}")
        return body.replace("''", "'")
    if text[0] in "&*!|>%@`{}[],\"'" or text.startswith("- ") or text == "-":
        raise YamlSubsetError(f"unsupported plain scalar {text!r}")
    if ": " in text or text.endswith(":") or " #" in text:
        raise YamlSubsetError(f"ambiguous plain scalar {text!r}: quote it")
    if text in ("null", "~", "Null", "NULL"):
        return None
    if text in ("true", "True", "TRUE"):
        return True
    if text in ("false", "False", "FALSE"):
        return False
    if text.lower() in _YAML11_BOOLS:
        raise YamlSubsetError(f"plain {text!r} is a boolean in YAML 1.1: quote it")
    if _INT.match(text):
        return int(text)
    if _FLOAT.match(text):
        return float(text)
    return text


def _flow_sequence(text: str) -> list[Any]:
    if not (text.startswith("[") and text.endswith("]")):
        raise YamlSubsetError(f"bad flow sequence {text!r}")
    inner = text[1:-1].strip()
    items: list[str] = []
    buf, quote, i = "", None, 0
    while i < len(inner):
        c = inner[i]
        if quote:
            buf += c
            if c == "\\" and quote == '"':
                buf += inner[i + 1]
                i += 2
                continue
            if c == quote:
                quote = None
        elif c in "\"'":
            quote = c
            buf += c
        elif c == ",":
            items.append(buf)
            buf = ""
        elif c in "[]{}":
            raise YamlSubsetError(f"nested flow collections are not supported: {text!r}")
        else:
            buf += c
        i += 1
    if buf.strip() or items:
        items.append(buf)
    if any(not item.strip() for item in items):
        raise YamlSubsetError(f"empty item in flow sequence {text!r}")
    return [_scalar(item) for item in items]


def _value(text: str, anchors: dict[str, Any]) -> Any:
    text = text.strip()
    if text.startswith("*"):
        name = text[1:]
        if name not in anchors:
            raise YamlSubsetError(f"unknown alias *{name}")
        return anchors[name]
    if text.startswith("["):
        return _flow_sequence(text)
    return _scalar(text)


def loads(source: str) -> Any:
    """Parse ``source`` (the subset above) into dicts, lists and scalars."""
    lines: list[tuple[int, int, str]] = []  # (line number, indent, content)
    for number, raw in enumerate(source.splitlines(), 1):
        if "\t" in raw[: len(raw) - len(raw.lstrip())]:
            raise YamlSubsetError(f"line {number}: tab in indentation")
        try:
            content = _strip_comment(raw)
        except YamlSubsetError as exc:
            raise YamlSubsetError(f"line {number}: {exc}") from None
        if not content.strip():
            continue
        if content.strip() in ("---", "..."):
            raise YamlSubsetError(f"line {number}: document markers are not supported")
        lines.append((number, len(content) - len(content.lstrip(" ")), content.strip()))
    anchors: dict[str, Any] = {}
    pos = 0

    def block(indent: int) -> Any:
        nonlocal pos
        number, ind, text = lines[pos]
        if ind != indent:
            raise YamlSubsetError(f"line {number}: expected indentation {indent}, got {ind}")
        if text.startswith("- ") or text == "-":
            return sequence(indent)
        return mapping(indent)

    def nested(parent_indent: int, number: int) -> Any:
        nonlocal pos
        if pos >= len(lines) or lines[pos][1] <= parent_indent:
            return None  # "key:" with nothing under it is null, as in YAML
        return block(lines[pos][1])

    def sequence(indent: int) -> list[Any]:
        nonlocal pos
        out = []
        while pos < len(lines) and lines[pos][1] == indent and (lines[pos][2].startswith("- ")):
            number, _, text = lines[pos]
            item = text[2:].strip()
            if re.match(r"^[^\"'\[]*:( |$)", item):
                raise YamlSubsetError(f"line {number}: mappings inside sequences are not supported")
            try:
                out.append(_value(item, anchors))
            except YamlSubsetError as exc:
                raise YamlSubsetError(f"line {number}: {exc}") from None
            pos += 1
        if pos < len(lines) and lines[pos][1] > indent:
            raise YamlSubsetError(f"line {lines[pos][0]}: unexpected indentation")
        return out

    def mapping(indent: int) -> dict[str, Any]:
        nonlocal pos
        out: dict[str, Any] = {}
        while pos < len(lines) and lines[pos][1] == indent:
            number, _, text = lines[pos]
            if text.startswith("- "):
                raise YamlSubsetError(f"line {number}: a sequence item where a key was expected")
            m = re.match(r'^("(?:[^"\\]|\\.)*"|\'(?:[^\']|\'\')*\'|[^\s:"\'][^:]*?):(?: (.*))?$', text)
            if not m:
                raise YamlSubsetError(f"line {number}: expected 'key: value', got {text!r}")
            raw_key, rest = m.group(1), (m.group(2) or "").strip()
            key = _scalar(raw_key) if raw_key[0] in "\"'" else raw_key
            if raw_key[0] not in "\"'" and not _KEY.match(raw_key):
                raise YamlSubsetError(f"line {number}: unsupported key {raw_key!r}")
            if key == "<<":
                raise YamlSubsetError(f"line {number}: merge keys are not supported")
            if key in out:
                raise YamlSubsetError(f"line {number}: duplicate key {key!r}")
            pos += 1
            anchor = None
            if rest.startswith("&"):
                anchor, _, rest = rest[1:].partition(" ")
                if not re.match(r"^[A-Za-z0-9_\-]+$", anchor):
                    raise YamlSubsetError(f"line {number}: bad anchor name {anchor!r}")
                rest = rest.strip()
            try:
                value = _value(rest, anchors) if rest else nested(indent, number)
            except YamlSubsetError as exc:
                if str(exc).startswith("line "):
                    raise
                raise YamlSubsetError(f"line {number}: {exc}") from None
            if anchor is not None:
                anchors[anchor] = value
            out[key] = value
        if pos < len(lines) and lines[pos][1] > indent:
            raise YamlSubsetError(f"line {lines[pos][0]}: unexpected indentation")
        return out

    if not lines:
        return None
    result = block(lines[0][1])
    if pos != len(lines):
        raise YamlSubsetError(f"line {lines[pos][0]}: unexpected content at indentation {lines[pos][1]}")
    return result


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
        raise YamlSubsetError(f"unsupported interpolation in {value!r}")
    return out


def defaults_of(value: str) -> list[tuple[str, str | None]]:
    """The ``(variable, default)`` pairs a string interpolates (default None when it has none)."""
    return [(m.group(1) or m.group(4), m.group(3)) for m in _VAR.finditer(value) if m.group(0) != "$$"]
