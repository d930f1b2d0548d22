"""The type-1 study of a master motor's recorded runs: which runs, which quantities, which
reference and tolerance, and the document ``eol-cal msa type1 --json`` prints.

The runs are the master serial's in the records database (time order), read column-wise as a
:class:`eol_cal.lot.runs.Lot`. The quantities are :data:`TYPE1_QUANTITIES` in their display
units (mN*m/A, deg, mN*m, %). The reference is given per quantity or taken from a declared run
(which is then not one of the study's runs). The tolerance is given per quantity, or for a
quantity with only an upper limit and a natural zero (k6, the p-p figures) ``T = limit - 0``
from the variant's limit the runs were judged against.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from eol_cal.errors import InputError, naming
from eol_cal.lot.runs import LOT_COLUMNS, QUANTITIES, Lot, Quantity, from_columns
from eol_cal.lot.spc import CIRCULAR, DEFAULT_MIN_N, NATURAL_ZERO  # a magnitude: T = USL - 0
from eol_cal.msa.type1 import CAPABLE, K_DEFAULT, L_DEFAULT, Type1Study, type1_study
from eol_cal.records.connect import db_key, is_url
from eol_cal.records.tables import runs
from eol_cal.records.query import read_columns, select_runs

#: the quantities of a type-1 study of the ripple measurement
TYPE1_QUANTITIES = ("k6", "phase_k6", "c6", "pp_before_pct", "pp_after_pct")
#: the ``schema`` of ``eol-cal msa type1 --json``
TYPE1_SCHEMA = "eol-cal/msa-type1/1"


def quantity(key: str) -> Quantity:
    """The :data:`eol_cal.lot.runs.QUANTITIES` entry of ``key``."""
    for q in QUANTITIES:
        if q.key == key:
            return q
    raise KeyError(key)


#: the run kinds a study takes: the master checks, and runs of the master serial made as
#: production runs (before the station named it its master)
STUDY_KINDS = ("master", "production")


def read_runs(db: str | Path, serial: str | None = None, run_id: str | None = None, since: str | None = None,
              until: str | None = None, exclude: str | None = None,
              kind: str | tuple[str, ...] | None = STUDY_KINDS) -> Lot:
    """The runs of one serial (or the one run ``run_id``, any kind; without the run ``exclude``)
    as a :class:`Lot`, time order."""
    q = select_runs(serial=serial, since=since, until=until, kind=None if run_id else kind).order_by(None)
    if run_id is not None:
        q = q.where(runs.c.run_id == run_id)
    if exclude is not None:
        q = q.where(runs.c.run_id != exclude)
    cols, limits = read_columns(db, q.with_only_columns(*(runs.c[name] for name in LOT_COLUMNS)),
                                q.with_only_columns(runs.c.limits_json).distinct())
    with naming(db_key(db) if is_url(db) else str(db)):
        return from_columns(cols, limits["limits_json"])


def reference_of_run(run: Lot, run_id: str, serial: str | None = None) -> dict[str, float]:
    """The display values of :data:`TYPE1_QUANTITIES` in the declared reference run (a run of
    ``serial``: another motor's values are no reference of this one)."""
    if len(run) != 1:
        raise InputError(None, "--reference-run", f"{run_id}: no such run in the database")
    if serial is not None and run.serial[0] != serial:
        raise InputError(None, "--reference-run", f"{run_id} is a run of {run.serial[0]}, not of the master {serial}")
    out = {key: float(run.display(quantity(key))[0]) for key in TYPE1_QUANTITIES}
    missing = [k for k, v in out.items() if not math.isfinite(v)]
    if len(missing) == len(out):
        raise InputError(None, "--reference-run", f"{run_id}: the run has no measured values (an error run?)")
    return {k: v for k, v in out.items() if math.isfinite(v)}


def tolerance_of(lot: Lot, key: str, given: Mapping[str, float]) -> tuple[float | None, str]:
    """``(T, where it came from)`` of a quantity in display units: given, else ``limit - 0`` for a
    natural-zero quantity with one upper limit over the runs; else ``(None, why)``."""
    if key in given:
        return float(given[key]), "given"
    q = quantity(key)
    if key in NATURAL_ZERO and q.limit_key and q.sense == "max":
        limits = lot.limit_values(q)
        if len(limits) == 1:
            return limits[0], f"{q.limit_key} - 0 (natural zero)"
        if len(limits) > 1:
            return None, f"{q.limit_key} differs between the runs: give --tolerance {key}=T"
    return None, f"no tolerance: give --tolerance {key}=T"


def _display(st: Type1Study, scale: float) -> Type1Study:
    """A study computed in stored units, in display units (Cg, Cgk, t, p do not scale)."""
    def s(x: float | None) -> float | None:
        return None if x is None else x * scale

    return dataclasses.replace(st, values=tuple(v * scale for v in st.values), reference=s(st.reference),
                               tolerance=s(st.tolerance), mean=st.mean * scale, sd=st.sd * scale,
                               bias=st.bias * scale)


def studies(lot: Lot, references: Mapping[str, float], tolerances: Mapping[str, float],
            sources: Mapping[str, str] | None = None, k: float = K_DEFAULT, l: float = L_DEFAULT,
            min_n: int = DEFAULT_MIN_N) -> list[tuple[Type1Study, str]]:
    """The type-1 study of each of :data:`TYPE1_QUANTITIES` over the runs (display units in and
    out), with where each tolerance came from; ``sources``: where each reference came from
    (default ``"given"``)."""
    out = []
    for key in TYPE1_QUANTITIES:
        q = quantity(key)
        tol, source = tolerance_of(lot, key, tolerances)
        ref = references.get(key)
        st = type1_study(lot.values[key], None if ref is None else ref / q.scale,
                         None if tol is None else tol / q.scale, quantity=key, unit=q.unit,
                         reference_source=(sources or {}).get(key, "given"), k=k, l=l, min_n=min_n,
                         circular=key in CIRCULAR)
        out.append((_display(st, q.scale), source))
    return out


def verdict(results: list[tuple[Type1Study, str]]) -> bool:
    """Capable: every quantity with a tolerance has Cg and Cgk >= 1.33, and there is one.
    A quantity with a tolerance but no Cg/Cgk (too few runs, no reference) is not shown capable."""
    judged = [st for st, _src in results if st.tolerance is not None]
    return bool(judged) and all(st.capable is True for st in judged)


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def document(results: list[tuple[Type1Study, str]], *, serial: str, runs: Lot, min_n: int) -> dict[str, Any]:
    """The JSON document of a study (``docs/json.md``, "eol-cal msa type1"): NaN as null, each
    index with its reason."""
    k, l = (results[0][0].k, results[0][0].l) if results else (K_DEFAULT, L_DEFAULT)
    quantities = []
    for st, source in results:
        q = quantity(st.quantity)
        item: dict[str, Any] = {
            "key": st.quantity, "title": q.title, "unit": st.unit, "n": st.n, "circular": st.circular,
            "reference": _num(st.reference), "reference_source": st.reference_source,
            "tolerance": _num(st.tolerance), "tolerance_source": source,
            "mean": _num(st.mean), "sd": _num(st.sd), "bias": _num(st.bias), "t": _num(st.t), "p_value": _num(st.p_value),
        }
        for name in ("cg", "cgk", "var_repeatability_pct"):
            g = getattr(st, name)
            item[name] = g.value
            item[f"{name}_reason"] = g.reason
        item["capable"] = st.capable
        quantities.append(item)
    return {
        "schema": TYPE1_SCHEMA, "serial": serial, "runs": len(runs),
        "first": str(runs.started_at[0]) if len(runs) else None, "last": str(runs.started_at[-1]) if len(runs) else None,
        "convention": {"k": k, "l": l, "cg": f"({k:g} T) / ({l:g} s)", "cgk": f"({k / 2:g} T - |bias|) / ({l / 2:g} s)",
                       "capable_at": CAPABLE},
        "min_n": min_n, "quantities": quantities, "capable": verdict(results),
    }
