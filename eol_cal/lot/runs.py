"""A lot's runs column-wise: what lot statistics read, as numpy arrays in time order.

:class:`Lot` is built either from the records database's columns (:func:`read_lot`: no record
JSON is parsed, only the few distinct ``limits_json`` texts) or from run records
(:func:`from_records`: the lot page, tests). Both go through
:func:`eol_cal.records.rows.row_values`, the one mapping from a record to its columns (the
insert and the migrations use it too), so both give the same lot and the same statistics. A lot
holds the runs of one kind, ``production`` unless asked (``docs/records.md``, "Run kinds").

Time order is the order of the ``started_at`` times (ties by ``run_id``). The station writes
UTC ISO 8601 with milliseconds (``2026-11-22T08:00:00.000+00:00``), all of one length, whose
text order is their time order; numpy parses those in one call. A lot holding other forms
(another offset, no milliseconds, ``Z``; no offset: UTC) is parsed time by time.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass
from itertools import repeat
from pathlib import Path
from typing import Any, NamedTuple
from collections.abc import Iterable, Sequence

import numpy as np

from eol_cal.rendering.display import display_unit
from eol_cal.errors import InputError
from eol_cal.infra.inputs import loads_json
from eol_cal.records.limits import limit_on
from eol_cal.records.record import MEASURED_KIND, NO_STATION, RunRecord


class Quantity(NamedTuple):
    """A measured quantity of the lot: its column (``key``, :meth:`RunRecord.value`), its title and
    stored unit; its display unit and scale (:mod:`eol_cal.rendering.display`), and the limit on it
    (:func:`eol_cal.records.limits.limit_on`) follow."""

    key: str
    title: str
    stored_unit: str

    @property
    def unit(self) -> str:
        """The display unit."""
        return display_unit(self.stored_unit)[0]

    @property
    def scale(self) -> float:
        """Display value = scale x stored value."""
        return display_unit(self.stored_unit)[1]

    @property
    def limit_key(self) -> str | None:
        lim = limit_on(self.key)
        return None if lim is None else lim.key

    @property
    def sense(self) -> str:
        lim = limit_on(self.key)
        return "max" if lim is None else lim.sense


#: the quantities of the lot page and ``lot stats``; each key is a column of ``runs``
QUANTITIES: tuple[Quantity, ...] = (
    Quantity("k6", "k6", "N*m/A"),
    Quantity("phase_k6", "phase_k6", "rad"),
    Quantity("c6", "c6", "N*m"),
    Quantity("phase_c6", "phase_c6", "rad"),
    Quantity("pp_before_pct", "p-p before", "%"),
    Quantity("pp_after_pct", "p-p compensated", "%"),
    Quantity("improvement_pct", "improvement", "%"),
    Quantity("fit_r2", "fit R^2", "1"),
    Quantity("fit_rms_nm", "fit residual rms", "N*m"),
)
#: what the control charts follow per station
CHARTED = ("k6", "pp_after_pct")
#: the ``runs`` columns a lot reads per run (and the distinct ``limits_json`` texts)
LOT_COLUMNS = ("run_id", "serial", "started_at", "verdict", "station", "variant", "causes",
               *(q.key for q in QUANTITIES))
#: the ``variant`` of runs without one
NO_VARIANT = "(no variant)"


@dataclass(frozen=True)
class Lot:
    """Runs column-wise in time order (object arrays of str, float arrays in stored units).

    Attributes
    ----------
    run_id, serial, started_at, verdict, station, variant : numpy.ndarray
        Per run; ``station`` as the reports name it (``(no station id)`` without one), ``variant``
        :data:`NO_VARIANT` without one.
    causes : list of list of str
        The failure causes (:meth:`RunRecord.causes`) of each run that did not pass.
    values : dict of str -> numpy.ndarray
        Per :data:`QUANTITIES` key, stored units (NaN where the run has none).
    limits : dict of str -> numpy.ndarray
        Per limit key of :data:`QUANTITIES`, the distinct values it has over the lot's runs
        (stored units, ascending; several: the lot mixes variants).
    variant_limits : dict of str -> dict of str -> numpy.ndarray
        The same per variant (the ``variant`` of the limits the runs were judged against).
    """

    run_id: np.ndarray
    serial: np.ndarray
    started_at: np.ndarray
    verdict: np.ndarray
    station: np.ndarray
    causes: list[list[str]]
    values: dict[str, np.ndarray]
    limits: dict[str, np.ndarray]
    variant: np.ndarray
    variant_limits: dict[str, dict[str, np.ndarray]]

    def __len__(self) -> int:
        return len(self.run_id)

    def display(self, q: Quantity) -> np.ndarray:
        """The quantity's values in display units, time order."""
        return self.values[q.key] * q.scale

    def limit_values(self, q: Quantity) -> list[float]:
        """The distinct values of the quantity's limit over the lot, display units (several: the
        lot mixes variants; none: no limit)."""
        if q.limit_key is None:
            return []
        return [float(v) * q.scale for v in self.limits[q.limit_key]]

    def variant_limit_values(self, q: Quantity, variant: str) -> list[float]:
        """:meth:`limit_values` of one variant (several: its limit changed within the lot)."""
        if q.limit_key is None:
            return []
        return [float(v) * q.scale for v in self.variant_limits.get(variant, {}).get(q.limit_key, ())]

    def stations(self) -> list[tuple[str, np.ndarray]]:
        """``(station, indices of its runs in time order)``, by station name."""
        return _groups(self.station)

    def variants(self) -> list[tuple[str, np.ndarray]]:
        """``(variant, indices of its runs in time order)``, by variant name."""
        return _groups(self.variant)


def _groups(names: np.ndarray) -> list[tuple[str, np.ndarray]]:
    distinct, codes = _codes(names.tolist())
    return sorted((str(name), np.flatnonzero(codes == k)) for k, name in enumerate(distinct))


def _causes(verdict: np.ndarray, run_id: np.ndarray, causes: np.ndarray) -> list[list[str]]:
    """The failure causes of each run that did not pass (their JSON lists parsed: a few runs)."""
    out: list[list[str]] = []
    for i in np.flatnonzero(verdict != "pass"):
        try:
            doc = loads_json(causes[i], None) if causes[i] else []
        except InputError:
            doc = None
        if not isinstance(doc, list) or not all(isinstance(c, str) for c in doc):
            raise InputError(None, f"run {run_id[i]} causes", "not a JSON list of strings")
        out.append(doc)
    return out


def _number(x: Any) -> float:
    # as the record-wise reading did: a number, else NaN
    if x is None:
        return math.nan
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _floats(col: Sequence[Any]) -> np.ndarray:
    try:
        return np.asarray(col, dtype=float)  # None is NaN
    except (TypeError, ValueError):
        return np.array([_number(x) for x in col], dtype=float)


def _codes(texts: Sequence[Any]) -> tuple[list[Any], np.ndarray]:
    """The distinct values of ``texts`` (first-seen order) and each one's index among them."""
    distinct = list(dict.fromkeys(texts))
    index = {t: k for k, t in enumerate(distinct)}
    return distinct, np.fromiter(map(index.__getitem__, texts), dtype=np.intp, count=len(texts))


def _limits(texts: Iterable[str | None]) -> tuple[dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """Per limit key, its distinct finite values over the ``limits_json`` texts, over all and
    per variant (each distinct text parsed once; one that is not a JSON object sets no limit)."""
    keys = [q.limit_key for q in QUANTITIES if q.limit_key]
    table = np.full((0, len(keys)), math.nan)
    variants: list[str] = []
    for text in dict.fromkeys(texts):
        try:
            doc = loads_json(text, None) if text else None
        except InputError:
            doc = None
        if isinstance(doc, dict):
            table = np.vstack([table, [_number(doc.get(key)) for key in keys]])
            variants.append(NO_VARIANT if doc.get("variant") is None else str(doc["variant"]))

    def distinct(rows: np.ndarray) -> dict[str, np.ndarray]:
        return {key: np.unique(rows[np.isfinite(rows[:, j]), j]) for j, key in enumerate(keys)}

    names = np.asarray(variants, dtype=object)
    return distinct(table), {v: distinct(table[names == v]) for v in dict.fromkeys(variants)}


#: the station's form of a start time: UTC, milliseconds (``2026-11-22T08:00:00.000+00:00``)
_STATION_FORM = len("2026-11-22T08:00:00.000+00:00")


def _utc(text: str) -> np.datetime64:
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise InputError(None, "started_at", f"{text!r}: not an ISO 8601 time") from None
    if t.tzinfo is not None:
        t = t.astimezone(dt.UTC).replace(tzinfo=None)
    return np.datetime64(t, "us")


def _times(started_at: Sequence[str]) -> np.ndarray:
    """The start times as datetime64 (UTC), parsed by numpy when all are in the station's form."""
    if set(map(len, started_at)) == {_STATION_FORM} and all(map(str.endswith, started_at, repeat("+00:00"))):
        try:
            return np.array([s[:-6] for s in started_at], dtype="datetime64[us]")
        except ValueError:
            pass  # of the right length but not a time: the one by one reading names it
    return np.array([_utc(s) for s in started_at], dtype="datetime64[us]")


def time_order(started_at: Sequence[str], run_id: Sequence[str]) -> np.ndarray:
    """Indices that put runs in time order, ties by run id (see the module doc)."""
    t = _times(started_at)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    bounds = np.concatenate(([0], np.flatnonzero(ts[1:] != ts[:-1]) + 1, [len(ts)]))
    for g in np.flatnonzero(np.diff(bounds) > 1):  # runs that started at the same time: by run id
        b, e = bounds[g], bounds[g + 1]
        order[b:e] = sorted(order[b:e], key=lambda i: run_id[i])
    return order


def from_columns(cols: dict[str, Sequence[Any]], limits_json: Iterable[str | None]) -> Lot:
    """A :class:`Lot` of the ``runs`` columns :data:`LOT_COLUMNS` (any row order) and the runs'
    ``limits_json`` texts (each run's, or only the distinct ones)."""
    order = time_order(cols["started_at"], cols["run_id"])

    def text(name: str) -> np.ndarray:
        return np.asarray(cols[name], dtype=object)[order] if len(order) else np.zeros(0, dtype=object)

    station, variant = text("station"), text("variant")
    station[station == None] = NO_STATION  # noqa: E711 - elementwise: the runs without a station id
    variant[variant == None] = NO_VARIANT  # noqa: E711
    run_id, verdict = text("run_id"), text("verdict")
    limits, variant_limits = _limits(limits_json)
    return Lot(run_id=run_id, serial=text("serial"), started_at=text("started_at"), verdict=verdict, station=station,
               causes=_causes(verdict, run_id, text("causes")),
               values={q.key: _floats(cols[q.key])[order] for q in QUANTITIES},
               limits=limits, variant=variant, variant_limits=variant_limits)


def from_records(records: Sequence[RunRecord]) -> Lot:
    """A :class:`Lot` of run records (their columns as the database would hold them; every record
    given, whatever its kind: choose the kind before)."""
    from eol_cal.records.rows import row_values

    rows = [row_values(r) for r in records]
    return from_columns({name: [row[name] for row in rows] for name in LOT_COLUMNS},
                        (row["limits_json"] for row in rows))


def read_lot(db: str | Path, variant: str | None = None, station: str | None = None, since: str | None = None,
             until: str | None = None, kind: str | Sequence[str] | None = MEASURED_KIND) -> Lot:
    """The selected runs of a records database as a :class:`Lot`, from its columns alone (schema
    version 4). Filters as :func:`eol_cal.records.query.select_runs` (``kind``: production
    runs unless asked)."""
    return read_lots(db, variant, station, since, until, kind)[0]


def read_lots(db: str | Path, variant: str | None = None, station: str | None = None, since: str | None = None,
              until: str | None = None, kind: str | Sequence[str] | None = MEASURED_KIND,
              also: Sequence[str] = ()) -> list[Lot]:
    """:func:`read_lot` and, from the same snapshot of the database, the lot of each kind in ``also``
    (the refusals beside the production runs)."""
    from eol_cal.errors import naming
    from eol_cal.records.connect import db_key, is_url
    from eol_cal.records.tables import runs
    from eol_cal.records.query import read_columns, select_runs

    queries = []
    for k in (kind, *also):
        q = select_runs(variant=variant, station=station, since=since, until=until, kind=k).order_by(None)
        # the order is made here (the server's text collation need not be code-point order); the
        # limits are few distinct texts, asked for as such (not 100 000 copies of them)
        queries += [q.with_only_columns(*(runs.c[name] for name in LOT_COLUMNS)),
                    q.with_only_columns(runs.c.limits_json).distinct()]
    got = read_columns(db, *queries)
    with naming(db_key(db) if is_url(db) else str(db)):
        return [from_columns(got[k], got[k + 1]["limits_json"]) for k in range(0, len(got), 2)]
