"""JSON Schema files of the tool's JSON documents (``docs/json.md`` points at each)."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any


def load_schema(name: str) -> dict[str, Any]:
    """The JSON Schema ``NAME.schema.json`` shipped in this package (e.g. ``fit-result``)."""
    return json.loads(resources.files(__name__).joinpath(f"{name}.schema.json").read_text(encoding="utf-8"))


def validator(name: str) -> Any:
    """A ``jsonschema`` validator for ``NAME.schema.json`` that resolves references to the other files here.

    ``jsonschema`` and ``referencing`` come with the test extra; only tests and tools call this.
    """
    import jsonschema
    from referencing import Registry, Resource

    names = [p.name.removesuffix(".schema.json") for p in resources.files(__name__).iterdir()
             if p.name.endswith(".schema.json")]
    registry = Registry().with_resources(
        (f"{n}.schema.json", Resource.from_contents(load_schema(n))) for n in names)
    schema = load_schema(name)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema, registry=registry)
