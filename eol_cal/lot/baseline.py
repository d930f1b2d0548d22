"""Frozen baselines in the records database: centre lines and sigmas per quantity, variant and
station, stored once (``eol-cal lot baseline``) and judged against later (``lot stats
--baseline NAME``), so a drifting process cannot move its own limits.

Two tables beside ``runs``, on SQLite and PostgreSQL through SQLAlchemy Core (the engines of
:mod:`eol_cal.station.records`): ``baselines`` (one row per baseline: its name, when it was made,
the filters that chose its runs, ``min_n``) and ``baseline_lines`` (one row per baseline,
quantity, variant and station: n, centre, sigma, MRbar, or the reason there are no limits).
Values are in the quantity's stored units (the ``runs`` column's: N*m/A, rad, %).

The tables have their own layout version in ``baseline_schema_version``
(:data:`BASELINE_SCHEMA_VERSION`), made the way ``schema_version`` is for ``runs``: created at
the current version by the first baseline (or by ``eol-cal records migrate``), a newer layout
refused. Keeping it apart from ``runs``'s version means the stations, which never write a
baseline, need no migration for it.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Connection

from eol_cal.errors import InputError
from eol_cal.lot.columns import NO_VARIANT, QUANTITIES, read_lot
from eol_cal.lot.spc import CIRCULAR, DEFAULT_MIN_N, ControlLine, freeze_line
from eol_cal.station.records import SchemaError, connected, db_label

#: the layout of the baseline tables this code writes
BASELINE_SCHEMA_VERSION = 1
_LOCK = 7413002  # PostgreSQL advisory lock: two first baselines at once, one creates the tables

_metadata = sa.MetaData()
baselines = sa.Table(
    "baselines", _metadata,
    sa.Column("name", sa.Text, primary_key=True),
    sa.Column("created_at", sa.Text, nullable=False),
    sa.Column("since", sa.Text),
    sa.Column("until", sa.Text),
    sa.Column("variant", sa.Text),
    sa.Column("station", sa.Text),
    sa.Column("min_n", sa.Integer, nullable=False),
    sa.Column("runs", sa.Integer, nullable=False),
    sa.Column("tool_version", sa.Text),
)
baseline_lines = sa.Table(
    "baseline_lines", _metadata,
    sa.Column("name", sa.Text, sa.ForeignKey("baselines.name", ondelete="CASCADE"), primary_key=True),
    sa.Column("quantity", sa.Text, primary_key=True),
    sa.Column("variant", sa.Text, primary_key=True),
    sa.Column("station", sa.Text, primary_key=True),
    sa.Column("circular", sa.Boolean, nullable=False),
    sa.Column("n", sa.Integer, nullable=False),
    sa.Column("center", sa.Float),
    sa.Column("sigma", sa.Float),
    sa.Column("mr_center", sa.Float),
    sa.Column("reason", sa.Text),
)
baseline_version = sa.Table("baseline_schema_version", _metadata, sa.Column("version", sa.Integer, nullable=False))


@dataclass(frozen=True)
class Baseline:
    """A named set of frozen control lines.

    Attributes
    ----------
    name : str
        Its name (unique in the database).
    created_at : str
        When it was made (UTC ISO 8601).
    filters : dict of str -> str or None
        ``since``, ``until`` (UTC days), ``variant``, ``station``: what chose its runs.
    min_n : int
        The minimum n its lines were made with.
    runs : int
        Runs it was made from.
    lines : dict of (quantity, variant, station) -> ControlLine
        Stored units.
    """

    name: str
    created_at: str
    filters: dict[str, str | None]
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
            out[(key, v, s)] = freeze_line(np.asarray(x, dtype=float)[idx], key in circular, min_n)
    return out


def make_baseline(name: str, lines: dict[tuple[str, str, str], ControlLine], runs: int,
                  filters: Mapping[str, str | None], min_n: int = DEFAULT_MIN_N) -> Baseline:
    """A :class:`Baseline` made now (UTC)."""
    if not name.strip():
        raise InputError(None, "name", "a baseline needs a name")
    created = dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")
    return Baseline(name, created, {k: filters.get(k) for k in ("since", "until", "variant", "station")}, min_n,
                    runs, dict(lines))


def baseline_of_db(db: str | Path, name: str, filters: Mapping[str, str | None], min_n: int = DEFAULT_MIN_N
                   ) -> Baseline:
    """The baseline of the runs a records database holds under ``filters`` (``since``, ``until``:
    UTC days; ``variant``, ``station``): every quantity of :data:`eol_cal.lot.columns.QUANTITIES`
    per variant and station, from the lot's columns (:func:`eol_cal.lot.columns.read_lot`)."""
    lot = read_lot(db, **{k: filters.get(k) for k in ("variant", "station", "since", "until")})
    if not len(lot):
        raise InputError(None, "baseline", "no runs selected: a baseline needs the runs of a period")
    lines = group_lines(lot.values, lot.variant, lot.station, CIRCULAR, min_n)
    return make_baseline(name, lines, len(lot), filters, min_n)


#: the ``schema`` of ``eol-cal lot baseline --json``
BASELINE_SCHEMA = "eol-cal/lot-baseline/1"


def line_document(line: ControlLine, scale: float) -> dict[str, Any]:
    """A line's figures in display units (``scale`` x stored; None where not made). A phase's
    limits are ``centre -+ 3 sigma`` as numbers (they may pass +-180 deg: judged on the circle)."""
    def d(x: float | None) -> float | None:
        return None if x is None else x * scale

    return {"n": line.n, "circular": line.circular, "center": d(line.center), "sigma": d(line.sigma),
            "lcl": d(line.lcl), "ucl": d(line.ucl), "mr_center": d(line.mr_center), "mr_ucl": d(line.mr_ucl),
            "reason": line.reason}


def baseline_document(b: Baseline) -> dict[str, Any]:
    """The baseline as ``lot baseline --json`` prints it (display units; ``docs/json.md``)."""
    unit = {q.key: (q.scale, q.unit) for q in QUANTITIES}
    lines = []
    for (key, variant, station), line in sorted(b.lines.items()):
        scale, u = unit.get(key, (1.0, ""))
        lines.append({"quantity": key, "unit": u, "variant": variant, "station": station, **line_document(line, scale)})
    return {"schema": BASELINE_SCHEMA, "name": b.name, "created_at": b.created_at, "filters": b.filters,
            "min_n": b.min_n, "runs": b.runs, "lines": lines}


# --------------------------------------------------------------------------- the tables
def _version(con: Connection) -> int | None:
    if not sa.inspect(con).has_table("baseline_schema_version"):
        return None
    v = con.execute(sa.select(sa.func.max(baseline_version.c.version))).scalar()
    return int(v) if v is not None else None


def ensure_tables(con: Connection) -> tuple[int | None, int]:
    """The migration step of the baseline tables, inside the caller's transaction: create them
    at :data:`BASELINE_SCHEMA_VERSION` when absent; refuse a newer layout. Returns ``(version
    before, version now)`` (before None: created)."""
    if con.dialect.name == "postgresql":
        con.execute(sa.text(f"SELECT pg_advisory_xact_lock({_LOCK})"))
    v = _version(con)
    if v is None:
        _metadata.create_all(con)
        con.execute(baseline_version.insert().values(version=BASELINE_SCHEMA_VERSION))
        return None, BASELINE_SCHEMA_VERSION
    if v > BASELINE_SCHEMA_VERSION:
        raise SchemaError(f"baseline tables at layout version {v} are newer than this tool "
                          f"({BASELINE_SCHEMA_VERSION})")
    return v, BASELINE_SCHEMA_VERSION


def migrate(db: str | Path) -> tuple[int | None, int]:
    """Bring the baseline tables of a records database to :data:`BASELINE_SCHEMA_VERSION`."""
    with connected(db, False, "migrate the baseline tables") as con, con.begin():
        return ensure_tables(con)


def store(db: str | Path, baseline: Baseline, replace: bool = False) -> None:
    """Store a baseline in one transaction (the tables made first when absent). A baseline of
    that name already there is refused unless ``replace``."""
    with connected(db, False, "store the baseline") as con, con.begin():
        ensure_tables(con)
        exists = con.execute(sa.select(baselines.c.name).where(baselines.c.name == baseline.name)).first()
        if exists and not replace:
            raise InputError(db_label(db), f"baseline {baseline.name!r}", "exists already (--replace to make it anew)")
        if exists:
            con.execute(baseline_lines.delete().where(baseline_lines.c.name == baseline.name))
            con.execute(baselines.delete().where(baselines.c.name == baseline.name))
        from eol_cal import __version__

        con.execute(baselines.insert().values(name=baseline.name, created_at=baseline.created_at,
                                              min_n=baseline.min_n, runs=baseline.runs, tool_version=__version__,
                                              **baseline.filters))
        rows = [{"name": baseline.name, "quantity": q, "variant": v, "station": s, "circular": bool(line.circular),
                 "n": line.n, "center": line.center, "sigma": line.sigma, "mr_center": line.mr_center,
                 "reason": line.reason} for (q, v, s), line in sorted(baseline.lines.items())]
        if rows:
            con.execute(baseline_lines.insert(), rows)


def load(db: str | Path, name: str) -> Baseline:
    """The baseline ``name``; :class:`InputError` naming the ones there are when it is not there."""
    with connected(db, True, "read the baseline") as con:
        if _version(con) is None:
            raise InputError(db_label(db), f"baseline {name!r}", "not found: the database holds no baselines "
                                                                  "(eol-cal lot baseline makes one)")
        head = con.execute(sa.select(baselines).where(baselines.c.name == name)).mappings().first()
        if head is None:
            there = con.execute(sa.select(baselines.c.name).order_by(baselines.c.name)).scalars().all()
            raise InputError(db_label(db), f"baseline {name!r}", f"not found (there are: {', '.join(there) or 'none'})")
        rows = con.execute(sa.select(baseline_lines).where(baseline_lines.c.name == name)).mappings().all()
    lines = {(r["quantity"], r["variant"], r["station"]):
             ControlLine(int(r["n"]), _float(r["center"]), _float(r["sigma"]), _float(r["mr_center"]),
                         bool(r["circular"]), r["reason"]) for r in rows}
    return Baseline(head["name"], head["created_at"], {k: head[k] for k in ("since", "until", "variant", "station")},
                    int(head["min_n"]), int(head["runs"]), lines)


def list_baselines(db: str | Path) -> list[dict[str, Any]]:
    """The baselines of a database (name, created_at, filters, min_n, runs), by name."""
    with connected(db, True, "read the baselines") as con:
        if _version(con) is None:
            return []
        return [dict(r) for r in con.execute(sa.select(baselines).order_by(baselines.c.name)).mappings()]


def _float(x: Any) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)
