"""JSON Schema files of the tool's JSON documents (``docs/json.md`` points at each)."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any


def load_schema(name: str) -> dict[str, Any]:
    """The JSON Schema ``NAME.schema.json`` shipped in this package (e.g. ``fit-result``)."""
    return json.loads(resources.files(__name__).joinpath(f"{name}.schema.json").read_text(encoding="utf-8"))
