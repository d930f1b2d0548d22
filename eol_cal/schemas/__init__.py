"""JSON Schema files of the tool's JSON documents (``docs/json.md`` points at each).

Every document a command prints with ``--json`` (and every run record) carries a ``schema`` key,
``eol-cal/NAME/VERSION``; :data:`SCHEMA_FILES` maps each to its file here. :func:`validator`
checks a document against one: ``jsonschema`` is a runtime dependency of eol-cal, so a plant's
tools can validate what the station wrote without the test extras.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

#: a document's ``schema`` key -> the schema file (``NAME.schema.json``) it validates against
SCHEMA_FILES: dict[str, str] = {
    "eol-cal/index/1": "index",
    "eol-cal/analyze/1": "analyze",
    "eol-cal/fit-result/1": "fit-result",
    "eol-cal/table/1": "block",
    "eol-cal/block-show/1": "block",
    "eol-cal/block-check/1": "block-check",
    "eol-cal/capture-info/1": "capture-info",
    "eol-cal/simulate/1": "simulate",
    "eol-cal/acquire/1": "acquire",
    "eol-cal/flash/1": "flash",
    "eol-cal/ecu-info/1": "ecu-info",
    "eol-cal/ecu-restore/1": "ecu-restore",
    "eol-cal/run/1": "run",
    "eol-cal/run-record/2": "run-record",
    "eol-cal/records/2": "records",
    "eol-cal/lot-stats/2": "lot-stats",
    "eol-cal/lot-baseline/1": "lot-baseline",
    "eol-cal/msa-type1/1": "msa-type1",
    "eol-cal/lot-diff/1": "lot-diff",
    "eol-cal/lot-simulate/1": "lot-simulate",
    "eol-cal/lot-compare/1": "lot-compare",
    "eol-cal/gate/1": "gate",
    "eol-cal/gate-admitted/1": "gate-admitted",
}


def schema_names() -> list[str]:
    """The names of the schema files shipped here."""
    return sorted(p.name.removesuffix(".schema.json") for p in resources.files(__name__).iterdir()
                  if p.name.endswith(".schema.json"))


def load_schema(name: str) -> dict[str, Any]:
    """The JSON Schema ``NAME.schema.json`` shipped in this package (e.g. ``fit-result``)."""
    return json.loads(resources.files(__name__).joinpath(f"{name}.schema.json").read_text(encoding="utf-8"))


def validator(name: str) -> Any:
    """A ``jsonschema`` validator for ``NAME.schema.json`` that resolves references to the other files here.

    Raises
    ------
    EolCalError
        ``jsonschema`` (or ``referencing``) is not installed: says which and how to install it.
    """
    try:
        import jsonschema
        from referencing import Registry, Resource
    except ImportError as exc:
        from eol_cal.errors import EolCalError

        raise EolCalError(f"validating against the schemas needs the packages jsonschema and referencing ({exc}); "
                          "they are dependencies of eol-cal: pip install 'jsonschema>=4.18'") from None
    registry = Registry().with_resources(
        (f"{n}.schema.json", Resource.from_contents(load_schema(n))) for n in schema_names())
    schema = load_schema(name)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema, registry=registry)
