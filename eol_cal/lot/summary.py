"""The lot's statistics as one document: what ``eol-cal lot stats`` prints and writes as JSON.

One definition for the command and the lot page: :func:`quantity_stats` and
:func:`lot_summary` take a :class:`eol_cal.lot.runs.Lot` (the runs column-wise, from the
database's columns or from parsed records) and apply :mod:`eol_cal.lot.stats` (the
definitions) to the quantities :data:`eol_cal.lot.runs.QUANTITIES` in their display units.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eol_cal.infra.atomic import atomic_write
from eol_cal.lot import spc_stats
from eol_cal.lot.baseline import Baseline
from eol_cal.lot.runs import CHARTED, QUANTITIES, Lot
from eol_cal.lot.spc import CIRCULAR, DEFAULT_MIN_N
from eol_cal.lot.stats import Capability, Summary, capability, first_pass_yield_of, pareto_of, summary
from eol_cal.records.tables import COLUMN_NAMES, runs
from eol_cal.records.query import read_rows, select_runs

#: the ``schema`` of the document ``eol-cal lot stats --json`` prints
LOT_STATS_SCHEMA = "eol-cal/lot-stats/2"
QUANTITY = {q.key: q for q in QUANTITIES}


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


def lot_summary(lot: Lot, refusals: Lot | None = None, min_n: int = DEFAULT_MIN_N, baseline: Baseline | None = None,
                judged: Sequence[str] = CHARTED) -> dict[str, Any]:
    """The lot's figures (display units, NaN as None).

    Keys: ``min_n``, ``runs``, ``verdicts`` (counts), ``first_pass_yield`` and ``motors``,
    ``quantities`` (per quantity: unit, count, mean, sd, min, max, percentiles - a phase's mean
    and sd on the circle, with its histogram -, the limit, Cp/Cpk/Ppk of a one-variant lot and
    ``capability`` per variant and station, each index None below ``min_n`` with its reason),
    ``pareto`` (cause, runs, cumulative share), ``control`` (per station, per charted quantity:
    the individuals / moving-range limits, None below ``min_n``), and with a ``baseline`` the
    lines ``judged`` against and Nelson's rules' ``violations``; with ``refusals``
    (the refused runs of the same selection) ``refusals`` (:func:`refusal_summary`). Documented
    in ``docs/json.md``; the definitions in ``docs/spc.md``.
    """
    fpy, motors = first_pass_yield_of(lot.serial, lot.verdict)
    quantities = []
    for q in quantity_stats(lot):
        s = q.summary
        quantity = QUANTITY[q.key]
        circular = q.key in CIRCULAR
        groups = spc_stats.capability_groups(lot, quantity, min_n)
        item: dict[str, Any] = {
            "key": q.key, "title": q.title, "unit": q.unit, "circular": circular, "count": s.count,
            "mean": s.mean, "sd": s.sd, "min": s.minimum, "max": s.maximum,
            "percentiles": {f"p{p:g}": v for p, v in s.percentiles.items()},
            "limit_key": q.limit_key, "limit": q.limit, **spc_stats.lot_capability(groups, lot), "note": q.note,
            "capability": groups,
        }
        if circular:
            item.update(min=None, max=None, percentiles={k: None for k in item["percentiles"]},
                        note="a phase: circular mean and sd (docs/spc.md); no min, max or percentiles on the circle",
                        **spc_stats.circular_figures(lot, quantity))
        quantities.append(item)
    charted = [QUANTITY[key] for key in CHARTED]
    doc: dict[str, Any] = {
        "min_n": min_n, "runs": len(lot),
        "verdicts": {v: int(np.count_nonzero(lot.verdict == v)) for v in ("pass", "fail", "error")},
        "first_pass_yield": fpy, "motors": motors,
        "quantities": quantities,
        "pareto": _pareto(lot.causes),
        "control": spc_stats.control_limits(lot, charted, min_n),
        "baseline": None, "judged": [], "violations": [],
        **({} if refusals is None else {"refusals": refusal_summary(refusals)}),
    }
    if baseline is not None:
        violations, lines = spc_stats.judge_lot(lot, baseline, [QUANTITY[key] for key in judged])
        doc.update(baseline={"name": baseline.name, "created_at": baseline.created_at, "filters": baseline.filters,
                             "min_n": baseline.min_n, "runs": baseline.runs, "rules": spc_stats.rule_texts()},
                   judged=lines, violations=[{k: v for k, v in x.items() if k != "index"} for x in violations])
    return _clean(doc)


def write_runs_csv(path: str | Path, db: str | Path, rules: dict[str, list[str]] | None = None,
                   **filters: Any) -> int:
    """Write the selected runs' columns (the database's, without the JSON documents) as CSV,
    atomically, oldest first; returns the number of runs. ``filters`` as
    :func:`eol_cal.records.query.select_runs`. Each header names its unit (``k6 [mN*m/A]``);
    the measured quantities are in their display units (:mod:`eol_cal.rendering.display`). With ``rules``
    (run id -> ``QUANTITY:RULE`` tags, :func:`eol_cal.lot.spc_stats.rules_by_run`) a last column
    ``rules`` lists the run rules each run is part of, ``;``-separated."""
    shown = {q.key: q for q in QUANTITIES}
    cols = [c for c in COLUMN_NAMES if c not in ("fit_json", "record_json")]
    rows = read_rows(db, select_runs(**filters).with_only_columns(*(runs.c[c] for c in cols)))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([f"{c} [{shown[c].unit}]" if c in shown else c for c in cols] + (["rules"] if rules is not None else []))
    for r in rows:
        extra = [";".join(rules.get(r["run_id"], []))] if rules is not None else []
        w.writerow(["" if r.get(c) is None else (r[c] * shown[c].scale if c in shown else r[c]) for c in cols] + extra)
    atomic_write(Path(path), buf.getvalue())
    return len(rows)
