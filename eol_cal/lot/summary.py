"""The lot's statistics as one document: what ``eol-cal lot stats`` prints and writes as JSON.

One definition for the command and the lot page: :func:`quantity_stats` and
:func:`lot_summary` take a :class:`eol_cal.lot.columns.Lot` (the runs column-wise, from the
database's columns or from parsed records) and apply :mod:`eol_cal.lot.stats` (the
definitions) to the quantities :data:`eol_cal.lot.columns.QUANTITIES` in their display units.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eol_cal.lot.columns import CHARTED, QUANTITIES, Lot
from eol_cal.lot.stats import Capability, Summary, capability, first_pass_yield_of, imr_limits, pareto_of, summary

#: the ``schema`` of the document ``eol-cal lot stats --json`` prints
LOT_STATS_SCHEMA = "eol-cal/lot-stats/1"


@dataclass(frozen=True)
class QuantityStats:
    """One quantity of the lot in display units: summary, the limit and the capability."""

    key: str
    title: str
    unit: str
    summary: Summary
    limit_key: str | None
    limit: float | None
    capability: Capability | None
    note: str

    @property
    def line(self) -> str:
        """One line for the histogram's title."""
        s = self.summary
        text = f"mean {s.mean:.4g}, sd {s.sd:.3g}"
        if self.capability is not None:
            text += f"; Cpk {self.capability.cpk:.2f}, Ppk {self.capability.ppk:.2f}"
        return text


def quantity_stats(lot: Lot) -> list[QuantityStats]:
    """:data:`QUANTITIES` of the lot (time order): summary and, where the quantity has a limit
    and the lot one value of it, the capability against it."""
    out = []
    for q in QUANTITIES:
        x = lot.display(q)
        limits = lot.limit_values(q)
        cap, limit, note = None, None, ""
        if len(limits) == 1:
            limit = limits[0]
            cap = capability(x, usl=limit) if q.sense == "max" else capability(x, lsl=limit)
        elif len(limits) > 1:
            note = f"{q.limit_key} differs between the lot's variants: no capability (choose a variant)"
        out.append(QuantityStats(q.key, q.title, q.unit, summary(x), q.limit_key, limit, cap, note))
    return out


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


def _pareto(causes: list[list[str]]) -> list[dict[str, Any]]:
    return [{"cause": c, "runs": n, "cumulative": acc} for c, n, acc in pareto_of(causes)]


def refusal_summary(refusals: Lot) -> dict[str, Any]:
    """The refused runs (nothing written, nothing measured): how many, of how many serials, and
    their reasons as a Pareto (refusal codes)."""
    return {"runs": len(refusals), "serials": len(set(refusals.serial.tolist())), "pareto": _pareto(refusals.causes)}


def lot_summary(lot: Lot, refusals: Lot | None = None) -> dict[str, Any]:
    """The lot's figures (display units, NaN as None).

    Keys: ``runs``, ``verdicts`` (counts), ``first_pass_yield`` and ``motors``, ``quantities``
    (per quantity: unit, count, mean, sd, min, max, percentiles, the limit and Cp/Cpk/Ppk
    against it), ``pareto`` (cause, runs, cumulative share) and ``control`` (per station, per
    charted quantity: the individuals / moving-range limits); with ``refusals`` (the refused
    runs of the same selection) ``refusals`` (:func:`refusal_summary`). Documented in
    ``docs/json.md``.
    """
    fpy, motors = first_pass_yield_of(lot.serial, lot.verdict)
    quantities = []
    for q in quantity_stats(lot):
        s = q.summary
        cap = q.capability
        quantities.append({
            "key": q.key, "title": q.title, "unit": q.unit, "count": s.count, "mean": s.mean, "sd": s.sd,
            "min": s.minimum, "max": s.maximum, "percentiles": {f"p{p:g}": v for p, v in s.percentiles.items()},
            "limit_key": q.limit_key, "limit": q.limit,
            "cp": cap.cp if cap else None, "cpk": cap.cpk if cap else None, "ppk": cap.ppk if cap else None,
            "note": q.note,
        })
    charted = [q for key in CHARTED for q in QUANTITIES if q.key == key]
    values = {q.key: lot.display(q) for q in charted}
    control = {}
    for station, idx in lot.stations():
        control[station] = {q.key: {"runs": len(idx), **dataclasses.asdict(imr_limits(values[q.key][idx]))}
                            for q in charted}
    return _clean({
        "runs": len(lot),
        "verdicts": {v: int(np.count_nonzero(lot.verdict == v)) for v in ("pass", "fail", "error")},
        "first_pass_yield": fpy, "motors": motors,
        "quantities": quantities,
        "pareto": _pareto(lot.causes),
        "control": control,
        **({} if refusals is None else {"refusals": refusal_summary(refusals)}),
    })


def write_runs_csv(path: str | Path, db: str | Path, **filters: Any) -> int:
    """Write the selected runs' columns (the database's, without the JSON documents) as CSV,
    atomically, oldest first; returns the number of runs. ``filters`` as
    :func:`eol_cal.station.records_query.select_runs`. Each header names its unit (``k6 [mN*m/A]``);
    the measured quantities are in their display units (:mod:`eol_cal.display`)."""
    import csv
    import io

    from eol_cal.atomic import atomic_write
    from eol_cal.station.records import COLUMN_NAMES, runs
    from eol_cal.station.records_query import read_rows, select_runs

    shown = {q.key: q for q in QUANTITIES}
    cols = [c for c in COLUMN_NAMES if c not in ("fit_json", "record_json")]
    rows = read_rows(db, select_runs(**filters).with_only_columns(*(runs.c[c] for c in cols)))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([f"{c} [{shown[c].unit}]" if c in shown else c for c in cols])
    for r in rows:
        w.writerow(["" if r.get(c) is None else (r[c] * shown[c].scale if c in shown else r[c]) for c in cols])
    atomic_write(Path(path), buf.getvalue())
    return len(rows)
