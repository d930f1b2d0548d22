"""A run record as the database holds it: its ``runs`` row, and a stored ``record_json`` read back."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from eol_cal.infra.inputs import loads_json
from eol_cal.records.connect import db_key, is_url
from eol_cal.records.record import RunRecord


def row_of(record: RunRecord) -> dict[str, Any]:
    """The ``runs`` row of a record: :func:`row_values` plus the record (and its fit) as JSON."""
    doc = record.to_json()
    fit = doc["fit"]
    return {**row_values(record),
            "fit_json": json.dumps(fit, allow_nan=False) if fit is not None else None,
            "record_json": json.dumps(doc, allow_nan=False)}


def _num(x: float) -> float | None:
    return None if x != x else x  # NaN: NULL


def row_values(record: RunRecord) -> dict[str, Any]:
    """The columns of a record's row, except the JSON documents ``fit_json`` and ``record_json``.

    The one mapping from a record to its columns: the insert, the migrations and the lot
    statistics of parsed records (:mod:`eol_cal.lot.runs`) all use it.
    """
    cal = record.block("calibrated")
    cap = record.captures
    lim = record.limits
    limits_doc = None if lim is None else {**lim.to_dict(), "sha256": record.limits_sha256}
    return {
        "run_id": record.run_id,
        "serial": record.serial,
        "variant": None if lim is None else lim.variant,
        "started_at": record.started_at,
        "ended_at": record.ended_at,
        "verdict": record.verdict,
        "reasons": json.dumps(list(record.reasons)),
        **{q: _num(record.value(q)) for q in ("k6", "phase_k6", "c6", "pp_before_pct", "pp_after_pct",
                                             "improvement_pct", "phase_c6", "fit_r2", "fit_rms_nm")},
        "capture_before": cap["before"].path if "before" in cap else None,
        "sha256_before": cap["before"].sha256 if "before" in cap else None,
        "capture_after": cap["after"].path if "after" in cap else None,
        "sha256_after": cap["after"].sha256 if "after" in cap else None,
        "block_crc32": None if cal is None else cal.crc32,
        "block_sequence": None if cal is None else cal.sequence,
        "tool_version": record.tool_version,
        "layout_version": record.layout_version,
        "report_dir": record.report_dir,
        "station": record.station_name,
        "operator": record.operator,
        "limits_json": None if limits_doc is None else json.dumps(limits_doc, sort_keys=True, allow_nan=False),
        "error_step": None if record.error is None else record.error.step,
        "kind": record.kind,
        "causes": json.dumps(record.causes()),
    }


def parse_record(db: str | Path, run_id: str, text: str) -> RunRecord:
    """The record of one row's ``record_json``; :class:`InputError` naming the database and the run."""
    where = f"run {run_id} record_json"
    name = db_key(db) if is_url(db) else str(db)  # the file as given; a URL without its password
    doc = loads_json(str(text), name, where)
    return RunRecord.from_json(doc, f"{name}, {where}")
