"""Frozen baselines in the records database: centre lines and sigmas per quantity, variant and
station, stored once (``eol-cal lot baseline``) and judged against later (``lot stats
--baseline NAME``), so a drifting process cannot move its own limits.

Two tables beside ``runs`` (:mod:`eol_cal.records.tables`, on SQLite and PostgreSQL through the
engines of :mod:`eol_cal.records.connect`): ``baselines`` (one row per baseline: its name, when it was made,
the filters that chose its runs, ``min_n``) and ``baseline_lines`` (one row per baseline,
quantity, variant and station: n, centre, sigma, MRbar, or the reason there are no limits).
Values are in the quantity's stored units (the ``runs`` column's: N*m/A, rad, %).

Their layout is the records database's one version (:mod:`eol_cal.records.migrations`): made
with every other table by the first writer or ``eol-cal records migrate``; a database at another
version is refused, naming it.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sqlalchemy as sa

from eol_cal import __version__
from eol_cal.errors import InputError
from eol_cal.infra.inputs import loads_json
from eol_cal.lot.runs import NO_VARIANT, QUANTITIES, read_lot
from eol_cal.lot.spc import CIRCULAR, DEFAULT_MIN_N, ControlLine, freeze_line, natural_floor
from eol_cal.records.record import KINDS, MEASURED_KIND
from eol_cal.records.connect import connected, db_label
from eol_cal.records.migrations import ensure_schema, readable
from eol_cal.records.tables import baseline_lines, baselines

#: the text filters a baseline keeps (``since``/``until``: UTC instants, ISO 8601)
FILTER_KEYS = ("since", "until", "variant", "station", "kind")

@dataclass(frozen=True)
class Baseline:
    """A named set of frozen control lines.

    Attributes
    ----------
    name : str
        Its name (unique in the database).
    created_at : str
        When it was made (UTC ISO 8601).
    filters : dict of str -> str or None or list
        ``since``, ``until`` (UTC instants, ISO 8601), ``variant``, ``station`` (the one station
        chosen), ``stations`` (every one chosen; None: all), ``kind`` (the runs' kind): what
        chose its runs.
    min_n : int
        The minimum n its lines were made with.
    runs : int
        Runs it was made from.
    lines : dict of (quantity, variant, station) -> ControlLine
        Stored units.
    """

    name: str
    created_at: str
    filters: dict[str, Any]
    min_n: int
    runs: int
    lines: dict[tuple[str, str, str], ControlLine] = field(default_factory=dict)

    def line(self, quantity: str, variant: str | None, station: str) -> ControlLine | None:
        """The line of a quantity for a variant (None: :data:`NO_VARIANT`) and station, or None."""
        return self.lines.get((quantity, variant if variant is not None else NO_VARIANT, station))


def group_lines(values: Mapping[str, np.ndarray], variant: Sequence[Any] | np.ndarray, station: Sequence[str] | np.ndarray,
                circular: frozenset[str] | set[str] = frozenset(), min_n: int = DEFAULT_MIN_N
                ) -> dict[tuple[str, str, str], ControlLine]:
    """Per quantity (``values``: key -> values in time order), variant and station (each run's),
    the :func:`eol_cal.lot.spc.freeze_line` of that group's runs in time order. A group's runs
    without the quantity (NaN) are left out of its n."""
    var = np.array([NO_VARIANT if v is None else str(v) for v in variant], dtype=object)
    sta = np.asarray(station, dtype=object)
    out: dict[tuple[str, str, str], ControlLine] = {}
    groups = sorted({(str(a), str(b)) for a, b in zip(var.tolist(), sta.tolist(), strict=True)})
    for v, s in groups:
        idx = np.flatnonzero((var == v) & (sta == s))
        for key, x in values.items():
            out[(key, v, s)] = freeze_line(np.asarray(x, dtype=float)[idx], key in circular, min_n, natural_floor(key))
    return out


def make_baseline(name: str, lines: dict[tuple[str, str, str], ControlLine], runs: int,
                  filters: Mapping[str, Any], min_n: int = DEFAULT_MIN_N) -> Baseline:
    """A :class:`Baseline` made now (UTC)."""
    if not name.strip() or not name.isprintable() or len(name) > 200:
        raise InputError(None, "name", f"{name!r}: a baseline needs a name of 1 to 200 printable characters")
    created = dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")
    stations = filters.get("stations")
    station = filters.get("station") or (stations[0] if stations and len(stations) == 1 else None)
    return Baseline(name, created, {**{k: filters.get(k) for k in FILTER_KEYS}, "station": station,
                                    "stations": None if not stations else list(stations),
                                    "kind": filters.get("kind") or MEASURED_KIND}, min_n, runs, dict(lines))


def instant(text: str, name: str, end: bool = False) -> dt.datetime:
    """``--since``/``--until`` as an aware UTC instant: an ISO 8601 time with its offset
    (``2026-11-22T06:00+01:00``, ``...Z``), or a UTC day (its start; ``end``: the start of the next
    day, so the day is whole). A time without an offset is refused: which instant it is depends
    on a zone it does not name."""
    try:
        if len(text) == 10:
            day = dt.date.fromisoformat(text)
            return dt.datetime.combine(day + dt.timedelta(days=1 if end else 0), dt.time(), tzinfo=dt.UTC)
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise InputError(None, name, f"{text!r}: expected YYYY-MM-DD or an ISO 8601 time with its offset") from None
    if t.tzinfo is None:
        raise InputError(None, name, f"{text!r}: give the time's UTC offset (Z, +01:00): an instant, not a wall time")
    return t.astimezone(dt.UTC)


def _started(texts: Sequence[str] | np.ndarray) -> np.ndarray:
    """Start times as aware UTC instants (no offset: UTC, as the lot reads them)."""
    out = []
    for t in texts:
        x = dt.datetime.fromisoformat(str(t))
        out.append(x if x.tzinfo is not None else x.replace(tzinfo=dt.UTC))
    return np.array(out, dtype=object)


def baseline_of_db(db: str | Path, name: str, filters: Mapping[str, Any], min_n: int = DEFAULT_MIN_N) -> Baseline:
    """The baseline of the runs a records database holds under ``filters``: ``since`` (inclusive)
    and ``until`` (exclusive) as aware instants or None, ``variant``, ``stations`` (a sequence;
    None: all), ``kind`` (default ``production``): every quantity of
    :data:`eol_cal.lot.runs.QUANTITIES` per variant and station, from the lot's columns
    (:func:`eol_cal.lot.runs.read_lot`). Times are compared as instants, never as text."""
    since, until = filters.get("since"), filters.get("until")
    if since is not None and until is not None and not since < until:
        raise InputError(None, "until", f"{until.isoformat()} is not after --since {since.isoformat()}")
    stations = filters.get("stations") or None
    kind = filters.get("kind") or MEASURED_KIND
    day = dt.timedelta(days=1)  # the day filter in SQL takes the UTC days around: offsets move a time's text day
    lot = read_lot(db, variant=filters.get("variant"), station=stations[0] if stations and len(stations) == 1 else None,
                   since=None if since is None else (since - day).date().isoformat(),
                   until=None if until is None else (until + day).date().isoformat(), kind=kind)
    t = _started(lot.started_at)
    keep = np.ones(len(lot), dtype=bool)
    if since is not None:
        keep &= np.array([x >= since for x in t], dtype=bool)
    if until is not None:
        keep &= np.array([x < until for x in t], dtype=bool)
    if stations:
        keep &= np.isin(lot.station.astype(str), list(stations))
    if not keep.any():
        raise InputError(None, "baseline", "no runs selected: a baseline needs the runs of a period")
    idx = np.flatnonzero(keep)
    lines = group_lines({k: v[idx] for k, v in lot.values.items()}, lot.variant[idx], lot.station[idx], CIRCULAR, min_n)
    shown = {"since": None if since is None else since.isoformat(), "until": None if until is None else until.isoformat(),
             "variant": filters.get("variant"), "stations": stations, "kind": kind}
    return make_baseline(name, lines, len(idx), shown, min_n)


#: the ``schema`` of ``eol-cal lot baseline --json``
BASELINE_SCHEMA = "eol-cal/lot-baseline/1"


def line_document(line: ControlLine, scale: float) -> dict[str, Any]:
    """A line's figures in display units (``scale`` x stored; None where not made). A phase's
    limits are ``centre -+ 3 sigma`` as numbers (they may pass +-180 deg: judged on the circle)."""
    def d(x: float | None) -> float | None:
        return None if x is None else x * scale

    return {"n": line.n, "circular": line.circular, "center": d(line.center), "sigma": d(line.sigma),
            "lcl": d(line.lcl), "ucl": d(line.ucl), "mr_center": d(line.mr_center), "mr_ucl": d(line.mr_ucl),
            "reason": line.reason, "note": line.note}


def baseline_document(b: Baseline) -> dict[str, Any]:
    """The baseline as ``lot baseline --json`` prints it (display units; ``docs/json.md``)."""
    unit = {q.key: (q.scale, q.unit) for q in QUANTITIES}
    lines = []
    for (key, variant, station), line in sorted(b.lines.items()):
        scale, u = unit.get(key, (1.0, ""))
        lines.append({"quantity": key, "unit": u, "variant": variant, "station": station, **line_document(line, scale)})
    return {"schema": BASELINE_SCHEMA, "name": b.name, "created_at": b.created_at, "filters": b.filters,
            "min_n": b.min_n, "runs": b.runs, "lines": lines}


def store(db: str | Path, baseline: Baseline, replace: bool = False) -> None:
    """Store a baseline in one transaction (every table made first in an empty database; one at
    another version refused). A baseline of that name already there is refused unless ``replace``."""
    with connected(db, False, "store the baseline") as con, con.begin():
        ensure_schema(con)
        exists = con.execute(sa.select(baselines.c.name).where(baselines.c.name == baseline.name)).first()
        if exists and not replace:
            raise InputError(db_label(db), f"baseline {baseline.name!r}", "exists already (--replace to make it anew)")
        if exists:
            con.execute(baseline_lines.delete().where(baseline_lines.c.name == baseline.name))
            con.execute(baselines.delete().where(baselines.c.name == baseline.name))
        stations = baseline.filters.get("stations")
        con.execute(baselines.insert().values(name=baseline.name, created_at=baseline.created_at,
                                              min_n=baseline.min_n, runs=baseline.runs, tool_version=__version__,
                                              **{k: baseline.filters.get(k) for k in FILTER_KEYS},
                                              stations=None if stations is None else json.dumps(list(stations))))
        rows = [{"name": baseline.name, "quantity": q, "variant": v, "station": s, "circular": bool(line.circular),
                 "n": line.n, "center": line.center, "sigma": line.sigma, "mr_center": line.mr_center,
                 "reason": line.reason} for (q, v, s), line in sorted(baseline.lines.items())]
        if rows:
            con.execute(baseline_lines.insert(), rows)


def load(db: str | Path, name: str) -> Baseline:
    """The baseline ``name``; :class:`InputError` naming the ones there are when it is not there.
    Its stored rows are checked like any input (a newer layout is refused; a line with a sigma
    that is not a positive number, a centre that is text...: refused naming the row)."""
    with connected(db, True, "read the baseline") as con:
        found = con.execute(sa.select(baselines).where(baselines.c.name == name)).mappings().first() \
            if readable(con) else None
        if found is None:
            there = con.execute(sa.select(baselines.c.name).order_by(baselines.c.name)).scalars().all() \
                if readable(con) else []
            raise InputError(db_label(db), f"baseline {name!r}", f"not found (there are: {', '.join(there)})" if there
                             else "not found: the database holds no baselines (eol-cal lot baseline makes one)")
        rows = con.execute(sa.select(baseline_lines).where(baseline_lines.c.name == name)).mappings().all()
    head = dict(found)
    where = f"{db_label(db)}, baseline {name!r}"
    lines = {(r["quantity"], r["variant"], r["station"]): _line_of_row(r, where) for r in rows}
    filters: dict[str, Any] = {k: _opt_text(head[k], where, k) for k in FILTER_KEYS}
    if filters["kind"] is not None and filters["kind"] not in KINDS:
        raise InputError(where, "kind", f"{filters['kind']!r}: not a run kind ({', '.join(KINDS)})")
    filters["stations"] = _stations(head["stations"], where)
    return Baseline(head["name"], _time(head["created_at"], where, "created_at"), filters,
                    _count(head["min_n"], where, "min_n", 2), _count(head["runs"], where, "runs", 0), lines)


def _text(x: Any, where: str, key: str) -> str:
    if not isinstance(x, str):
        raise InputError(where, key, f"{x!r}: not a text")
    return x


def _time(x: Any, where: str, key: str) -> str:
    """A stored time: ISO 8601 with its UTC offset (as eol-cal writes it)."""
    try:
        t = dt.datetime.fromisoformat(_text(x, where, key))
    except ValueError:
        t = None
    if t is None or t.tzinfo is None:
        raise InputError(where, key, f"{x!r}: not an ISO 8601 time with its offset")
    return str(x)


def _opt_text(x: Any, where: str, key: str) -> str | None:
    return None if x is None else _text(x, where, key)


def _stations(x: Any, where: str) -> list[str] | None:
    if x is None:
        return None
    got = loads_json(_text(x, where, "stations"), where, "stations")
    if not isinstance(got, list) or not got or not all(isinstance(s, str) for s in got):
        raise InputError(where, "stations", "not a JSON list of station ids")
    return got


def _count(x: Any, where: str, key: str, least: int) -> int:
    if isinstance(x, bool) or not isinstance(x, int) or x < least:
        raise InputError(where, key, f"{x!r}: not a whole number >= {least}")
    return x


def _stored_number(x: Any, where: str, key: str, positive: bool = False) -> float | None:
    """A stored figure: None (not made), or a finite number (``positive``: > 0); text, NaN and
    infinities are refused."""
    if x is None:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(float(x)) or (positive and not x > 0):
        raise InputError(where, key, f"{x!r}: not a {'positive' if positive else 'finite'} number")
    return float(x)


def _line_of_row(r: Any, where: str) -> ControlLine:
    """A stored line, checked: a known quantity, n a count, centre, sigma > 0 and MRbar > 0 all
    there or all absent (then a reason says why), a phase flagged as one."""
    key = r["quantity"]
    at = f"{where}, line {key!r} {r['variant']!r} {r['station']!r}"
    if key not in {q.key for q in QUANTITIES}:
        raise InputError(at, "quantity", f"{key!r}: not a quantity of the lot")
    if not isinstance(r["variant"], str) or not isinstance(r["station"], str):
        raise InputError(at, "variant", "variant and station must be texts")
    circular = r["circular"]
    if circular not in (True, False, 0, 1) or bool(circular) != (key in CIRCULAR):
        raise InputError(at, "circular", f"{circular!r}: {key} is {'' if key in CIRCULAR else 'not '}a phase")
    center = _stored_number(r["center"], at, "center")
    sigma = _stored_number(r["sigma"], at, "sigma", positive=True)
    mr = _stored_number(r["mr_center"], at, "mr_center", positive=True)
    reason = _opt_text(r["reason"], at, "reason")
    made = [x is not None for x in (center, sigma, mr)]
    if any(made) and not all(made):
        raise InputError(at, "sigma", "centre, sigma and MRbar are stored together or not at all")
    if not any(made) and reason is None:
        raise InputError(at, "reason", "a line without limits must say why")
    if key in CIRCULAR and center is not None and not -math.pi <= center <= math.pi:
        raise InputError(at, "center", f"{center!r} rad: a phase's centre lies in [-pi, pi]")
    return ControlLine(_count(r["n"], at, "n", 0), center, sigma, mr, bool(circular), reason,
                       lower_bound=natural_floor(key))


def list_baselines(db: str | Path) -> list[dict[str, Any]]:
    """The baselines of a database (name, created_at, filters, min_n, runs), by name."""
    with connected(db, True, "read the baselines") as con:
        if not readable(con):
            return []
        return [dict(r) for r in con.execute(sa.select(baselines).order_by(baselines.c.name)).mappings()]
