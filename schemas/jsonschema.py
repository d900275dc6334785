"""JSON Schema of every wire message, for non-Python clients (written to ``schemas/json/``).

Each file describes the msgpack map of one message kind: the model's fields plus the ``k`` kind tag.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from schemas.codec import KIND_FIELD
from schemas.messages import MESSAGE_TYPES

JSON_DIR = Path(__file__).with_name("json")


def message_schemas() -> dict[str, dict[str, Any]]:
    """{file name: JSON Schema} for every message kind."""
    out: dict[str, dict[str, Any]] = {}
    for cls in MESSAGE_TYPES:
        schema = cls.model_json_schema(mode="validation")
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"https://morph-sim.invalid/schemas/{cls.KIND}.v{cls.VERSION}.json"
        props = schema.setdefault("properties", {})
        props[KIND_FIELD] = {"const": cls.KIND, "description": "message kind tag (msgpack envelope)"}
        props["v"] = {**props.get("v", {}), "const": cls.VERSION}
        schema["required"] = sorted(set(schema.get("required", [])) | {KIND_FIELD, "v"})
        schema["x-msgpack"] = "one msgpack map; tuples are arrays; enums are their values"
        out[f"{cls.KIND}.json"] = schema
    return out


def render(schema: dict[str, Any]) -> str:
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def export(directory: Path | str = JSON_DIR) -> list[Path]:
    """Write one ``<kind>.json`` per message into ``directory``; return the paths written."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, schema in message_schemas().items():
        path = directory / name
        path.write_text(render(schema), encoding="utf-8")
        written.append(path)
    return written
