"""``eol-cal lot diff``: which motors a refit judges otherwise than their latest recorded run.

A refit (:mod:`eol_cal.lot.refit`) fits a run's calibration capture again and judges the fit's
limits (the ``fit`` stage of :data:`eol_cal.records.limits.LIMITS`); it makes no compensated
capture, so it judges no ripple limit. The comparison is therefore of like with like: the
refit's verdict and failed limit keys against the *fit-stage checks the record carries* (read,
never judged again here) of each serial's latest run of the kind asked (``production`` unless
asked). A record whose fit stage was not judged (the run ended before a usable fit) and a refit
row that could not be fitted are counted, not compared.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from eol_cal.rendering.display import display_unit
from eol_cal.records.record import MEASURED_KIND, RunRecord
from eol_cal.records.query import latest_per_serial

#: the schema of the document ``eol-cal lot diff --json`` prints
LOT_DIFF_SCHEMA = "eol-cal/lot-diff/1"


def fit_stage(rec: RunRecord) -> tuple[str | None, set[str]]:
    """The record's fit-stage verdict (``pass``/``fail``; None: not judged) and its failed keys
    (``fit STATUS`` for a fit that was not usable)."""
    if rec.fit is None:
        return None, set()
    if not rec.fit.usable:
        return "fail", {f"fit {rec.fit.status}"}
    checks = [c for c in rec.checks if c.stage == "fit"]
    if not checks or any(c.passed is None for c in checks):
        return None, set()
    failed = {c.key for c in checks if c.passed is False}
    return ("fail" if failed else "pass"), failed


def _k6(x: Any) -> float | None:
    unit, factor = display_unit("N*m/A")
    return None if x is None or not math.isfinite(float(x)) else float(x) * factor


def verdict_changes(records: Sequence[RunRecord], rows: Sequence[dict[str, Any]],
                    kind: str = MEASURED_KIND) -> dict[str, Any]:
    """The refit rows that differ from the fit-stage checks of their serial's latest ``kind`` run.

    Returns
    -------
    dict
        ``rows``, ``compared``, ``not_compared`` (no record of the kind, its fit stage not
        judged, or the row has no verdict: no limits given), ``errors`` (rows that could not be
        fitted), ``k6_unit`` and ``changes``: per motor ``serial``, ``run_id``, ``recorded``,
        ``refit`` (fit-stage verdicts), ``newly_failing``, ``no_longer_failing`` (limit keys),
        ``k6_recorded``, ``k6_refit`` (display unit), ``reasons`` (the refit's).
    """
    latest = latest_per_serial(records, kind)
    out: list[dict[str, Any]] = []
    compared = errors = 0
    for row in rows:
        if row.get("error") or row.get("verdict") == "error":
            errors += 1
            continue
        rec = latest.get(row.get("serial") or "")
        recorded, rec_failed = fit_stage(rec) if rec is not None else (None, set())
        if rec is None or recorded is None or row.get("verdict") is None:  # no record: recorded is None too
            continue
        compared += 1
        if row.get("failed_checks") is not None:
            refit_failed = set(row["failed_checks"])
            if row.get("status") not in (None, "ok"):
                refit_failed.add(f"fit {row['status']}")
        else:  # rows written before failed_checks: the verdicts alone
            refit_failed = rec_failed if row["verdict"] == recorded else set()
        if recorded == row["verdict"] and rec_failed == refit_failed:
            continue
        e = rec.fit.estimates if rec.fit is not None else None
        out.append({"serial": row["serial"], "run_id": rec.run_id, "recorded": recorded, "refit": row["verdict"],
                    "newly_failing": sorted(refit_failed - rec_failed),
                    "no_longer_failing": sorted(rec_failed - refit_failed),
                    "k6_recorded": _k6(e.k6.value if e is not None else None), "k6_refit": _k6(row.get("k6")),
                    "reasons": list(row.get("reasons") or [])})
    return {"rows": len(rows), "compared": compared, "not_compared": len(rows) - compared - errors, "errors": errors,
            "k6_unit": display_unit("N*m/A")[0], "changes": out}
