"""Form fields generated from a procedure's parameter schema (pydantic's JSON schema), for
the console's start page. The browser sends what the operator typed; the server's own
validation (``POST /runs``) stays the judge, and its message is shown on refusal."""

from __future__ import annotations

import json
from typing import Any


def _kind(prop: dict[str, Any]) -> tuple[str, bool]:
    """(input kind, nullable): number, integer, boolean, string, enum, array or json."""
    options = prop.get("anyOf") or [prop]
    types = [o.get("type") for o in options]
    nullable = "null" in types
    concrete = [o for o in options if o.get("type") != "null"]
    first = concrete[0] if concrete else {}
    if "enum" in first:
        return "enum", nullable
    kind = first.get("type")
    if kind == "array" and (first.get("items") or {}).get("type") in ("number", "integer"):
        return "array", nullable
    if kind in ("number", "integer", "boolean", "string"):
        return kind, nullable
    return "json", nullable


def _text(value: Any, kind: str) -> str:
    if value is None:
        return ""
    if kind == "array":
        return ", ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
    if kind == "json":
        return json.dumps(value)
    return str(value)


def form_fields(schema: dict[str, Any], configured: dict[str, Any] | None = None,
                defaults: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """One field per property: name, label, kind, nullable, the value to show (the rig
    file's ``procedures.<name>`` setting, else the schema default, else ``defaults``:
    what the model itself fills in, for fields with a default factory, which the JSON
    schema leaves out), bounds, help text."""
    configured, defaults = configured or {}, defaults or {}
    fields = []
    for name, prop in schema.get("properties", {}).items():
        kind, nullable = _kind(prop)
        concrete = next((o for o in prop.get("anyOf") or [prop] if o.get("type") != "null"),
                        {})
        value = configured.get(name, prop.get("default", defaults.get(name)))
        fields.append({
            "name": name, "label": prop.get("title") or name.replace("_", " "),
            "kind": kind, "nullable": nullable, "value": _text(value, kind),
            "checked": bool(value) if kind == "boolean" else False,
            "options": concrete.get("enum", []),
            "min": concrete.get("minimum", concrete.get("exclusiveMinimum")),
            "max": concrete.get("maximum", concrete.get("exclusiveMaximum")),
            "help": prop.get("description", ""),
            "from_rig_file": name in configured,
        })
    return fields
