"""Two lots side by side (``eol-cal lot diff --lot A --lot B``): what-if lots simulated with two
spreads or two limits files, or any two stations' runs.

Each lot's figures are :func:`eol_cal.lot.summary.lot_summary`'s (yield, the quantities with their
capability, the failure causes); the motors are matched by their number in a simulated lot
(motor ``i`` of two lots drawn with the same seed is the same motor as built), else by serial,
and those whose verdict or failed limits differ are listed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from eol_cal.errors import InputError
from eol_cal.lot.runs import from_records
from eol_cal.lot.summary import lot_summary
from eol_cal.records.record import RunRecord
from eol_cal.records.query import query_records

#: the schema of ``lot diff --lot A --lot B --json``
LOT_COMPARE_SCHEMA = "eol-cal/lot-compare/1"
#: the quantities shown per lot (keys of eol_cal.lot.summary's quantities)
SHOWN = ("k6", "pp_before_pct", "pp_after_pct", "improvement_pct")


def motor_key(rec: RunRecord) -> str:
    """A run's motor across lots: its number in a simulated lot, else its serial."""
    sim = rec.station.extra.get("simulated") if isinstance(rec.station.extra, dict) else None
    if isinstance(sim, dict) and isinstance(sim.get("spread_seed"), int):
        return f"seed {sim['spread_seed']}"
    return rec.serial


def _latest(records: Sequence[RunRecord]) -> dict[str, RunRecord]:
    out: dict[str, RunRecord] = {}
    for r in sorted(records, key=lambda r: (r.started_at, r.run_id)):
        out[motor_key(r)] = r
    return out


def _lot_doc(station: str, records: Sequence[RunRecord]) -> dict[str, Any]:
    doc = lot_summary(from_records(records))
    v = doc["verdicts"]
    judged = v["pass"] + v["fail"]
    return {"station": station, "runs": doc["runs"], "verdicts": v,
            "yield": v["pass"] / judged if judged else None,
            "quantities": {q["key"]: {"unit": q["unit"], "count": q["count"], "p50": q["percentiles"].get("p50"),
                                      "limit": q["limit"], "cpk": q["cpk"]}
                           for q in doc["quantities"] if q["key"] in SHOWN},
            "pareto": doc["pareto"]}


def compare_lots(db: str | Path, stations: Sequence[str], kind: str = "simulated") -> dict[str, Any]:
    """Two lots of ``db`` (their records' station, e.g. ``sim:A``) of ``kind``: each lot's figures
    and the motors whose verdict or failed limits differ (``docs/json.md``, lot-compare)."""
    if len(stations) != 2:
        raise InputError(None, "--lot", f"give two lots to compare, got {len(stations)}")
    records = query_records(db, kind=kind)
    lots = [[r for r in records if r.station_name == s] for s in stations]
    for s, recs in zip(stations, lots, strict=True):
        if not recs:
            raise InputError(str(db), "--lot", f"no {kind} runs of station {s!r} in the database")
    a, b = (_latest(recs) for recs in lots)
    changes = []
    for key in sorted(set(a) & set(b)):
        ra, rb = a[key], b[key]
        ca, cb = ra.causes(), rb.causes()
        if ra.verdict != rb.verdict or ca != cb:
            changes.append({"motor": key, "serials": [ra.serial, rb.serial], "verdicts": [ra.verdict, rb.verdict],
                            "newly_failing": [c for c in cb if c not in ca],
                            "no_longer_failing": [c for c in ca if c not in cb],
                            "pp_after_pct": [_num(ra.value("pp_after_pct")), _num(rb.value("pp_after_pct"))]})
    return {"lots": [_lot_doc(s, recs) for s, recs in zip(stations, lots, strict=True)], "compared": len(set(a) & set(b)),
            "only_in_one": len(set(a) ^ set(b)), "changes": changes}


def _num(x: float) -> float | None:
    return None if x != x else float(x)
