"""The lot's statistics as one document: what ``eol-cal lot stats`` prints and writes as JSON.

Built from :mod:`eol_cal.lot.stats` (the definitions) over the quantities of the lot page
(:data:`eol_cal.report.lot.QUANTITIES`, in their display units), so the page and the command
give the same figures for the same records.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Sequence

from eol_cal.lot.stats import first_pass_yield, imr_limits, pareto


def _num(x: float | None) -> float | None:
    # JSON has no NaN: an undefined figure is null
    return None if x is None or not math.isfinite(x) else float(x)


def _clean(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, float):
        return _num(obj)
    return obj


def lot_summary(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The lot's figures (display units, NaN as None).

    Keys: ``runs``, ``verdicts`` (counts), ``first_pass_yield`` and ``motors``, ``quantities``
    (per quantity: unit, count, mean, sd, min, max, percentiles, the limit and Cp/Cpk/Ppk
    against it), ``pareto`` (cause, runs, cumulative share) and ``control`` (per station, per
    charted quantity: the individuals / moving-range limits).
    """
    from eol_cal.report.lot import CHARTED, QUANTITIES, quantity_stats, run_time, value_of
    from eol_cal.report.motor import station_of

    recs = sorted(records, key=run_time)
    fpy, motors = first_pass_yield(recs)
    quantities = []
    for q in quantity_stats(recs):
        s = q.summary
        cap = q.capability
        quantities.append({
            "key": q.key, "title": q.title, "unit": q.unit, "count": s.count, "mean": s.mean, "sd": s.sd,
            "min": s.minimum, "max": s.maximum, "percentiles": {f"p{p:g}": v for p, v in s.percentiles.items()},
            "limit_key": q.limit_key, "limit": q.limit,
            "cp": cap.cp if cap else None, "cpk": cap.cpk if cap else None, "ppk": cap.ppk if cap else None,
            "note": q.note,
        })
    by_station: dict[str, list[dict[str, Any]]] = {}
    for r in recs:
        by_station.setdefault(station_of(r), []).append(r)
    paths = {key: (path, scale) for key, _t, path, scale, *_ in QUANTITIES}
    control = {}
    for station, rs in sorted(by_station.items()):
        control[station] = {}
        for key in CHARTED:
            path, scale = paths[key]
            cl = imr_limits(value_of(r, path) * scale for r in rs)
            control[station][key] = {"runs": len(rs), **dataclasses.asdict(cl)}
    return _clean({
        "runs": len(recs),
        "verdicts": {v: sum(r.get("verdict") == v for r in recs) for v in ("pass", "fail", "error")},
        "first_pass_yield": fpy, "motors": motors,
        "quantities": quantities,
        "pareto": [{"cause": c, "runs": n, "cumulative": acc} for c, n, acc in pareto(recs)],
        "control": control,
    })


def write_runs_csv(path: str | Path, rows: Sequence[dict[str, Any]]) -> Path:
    """Write the runs' columns (the database's, without the JSON documents) as CSV, atomically."""
    import csv
    import io

    from eol_cal.atomic import atomic_write
    from eol_cal.station.records import COLUMN_NAMES

    cols = [c for c in COLUMN_NAMES if c not in ("fit_json", "record_json")]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow(["" if r.get(c) is None else r.get(c) for c in cols])
    atomic_write(Path(path), buf.getvalue())
    return Path(path)
