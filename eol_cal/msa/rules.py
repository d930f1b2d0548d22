"""The master gate's rules as records: per station, in the records database, each change a row.

Table ``gate_rules`` beside ``runs`` (SQLite and PostgreSQL through the engines of
:mod:`eol_cal.station.records`): one row per change of a station's rules, numbered ``seq`` 1, 2,
... per station, with when (``set_at``, UTC), by whom (``set_by``) and why (``note``) it was
made, and the rules themselves as JSON (``rules_json``: master serial, references, tolerances,
period; :func:`rules_document`) or ``action = 'clear'`` (the station has no gate from then on).
The latest row of a station is in force. Rows are never changed or deleted by this tool: the
table is the gate's history (``eol-cal gate history``).

Its layout version is in ``gate_schema_version`` (:data:`GATE_SCHEMA_VERSION`), kept apart from
``runs``'s as the baselines' is: created by the first ``eol-cal gate set``; a newer layout is
refused. Every row read is checked as the settings are (:func:`eol_cal.msa.master.master_settings`):
a stored row that would not pass as a setting refuses the gate, naming the row.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from eol_cal import __version__
from eol_cal.errors import InputError
from eol_cal.inputs import loads_json
from eol_cal.msa.master import MASTER_QUANTITIES, MasterSettings, master_settings
from eol_cal.station.records import DEFAULT_LOCK_TIMEOUT_S, SchemaError, connected, db_label, is_url
from eol_cal.station.records import migrate as migrate_runs

#: the layout of the gate tables this code writes
GATE_SCHEMA_VERSION = 1
_LOCK = 7413003  # PostgreSQL advisory lock: two changes at once get consecutive numbers
ACTIONS = ("set", "clear")

_metadata = sa.MetaData()
gate_rules = sa.Table(
    "gate_rules", _metadata,
    sa.Column("station", sa.Text, primary_key=True),
    sa.Column("seq", sa.Integer, primary_key=True),
    sa.Column("set_at", sa.Text, nullable=False),
    sa.Column("set_by", sa.Text),
    sa.Column("action", sa.Text, sa.CheckConstraint("action IN ('set', 'clear')"), nullable=False),
    sa.Column("rules_json", sa.Text),
    sa.Column("note", sa.Text),
    sa.Column("tool_version", sa.Text),
)
gate_version = sa.Table("gate_schema_version", _metadata, sa.Column("version", sa.Integer, nullable=False))


@dataclass(frozen=True)
class GateRules:
    """One change of a station's gate rules: its number, when, by whom, why, and the rules it set
    (``master`` None: the change cleared the gate)."""

    station: str
    seq: int
    set_at: str
    set_by: str | None
    master: MasterSettings | None
    note: str | None = None

    @property
    def label(self) -> str:
        """``rules #3 of EOL-1 (set 2026-11-22 08:00 UTC)`` for messages."""
        return f"rules #{self.seq} of {self.station} (set {self.set_at[:16].replace('T', ' ')} UTC)"


def rules_document(m: MasterSettings) -> dict[str, Any]:
    """The rules as stored and as the run record carries them (display units)."""
    return {"serial": m.serial, "reference": dict(m.reference), "tolerance": dict(m.tolerance),
            "every_h": m.every_h, "shifts": [t.strftime("%H:%M") for t in m.shifts] or None,
            "timezone": m.timezone}


def settings_values(doc: Any, where: str) -> dict[str, object]:
    """A rules document as the flattened settings keys :func:`master_settings` checks."""
    if not isinstance(doc, dict):
        raise InputError(where, None, f"expected the rules as an object, got {type(doc).__name__}")
    unknown = sorted(set(doc) - {"serial", "reference", "tolerance", "every_h", "shifts", "timezone"})
    if unknown:
        raise InputError(where, unknown[0], "not a rule of the gate")
    values: dict[str, object] = {"master.serial": doc.get("serial"), "master.every_h": doc.get("every_h"),
                                 "master.timezone": doc.get("timezone")}
    shifts = doc.get("shifts")
    if shifts is not None:
        if not isinstance(shifts, list) or not all(isinstance(t, str) for t in shifts):
            raise InputError(where, "master.shifts", "expected a list of HH:MM texts")
        values["master.shifts"] = ",".join(shifts)
    for part in ("reference", "tolerance"):
        got = doc.get(part)
        if not isinstance(got, dict):
            raise InputError(where, f"master.{part}", "expected an object of quantities")
        for k, v in got.items():
            if k not in MASTER_QUANTITIES:
                raise InputError(where, f"master.{part}.{k}", f"not a quantity ({', '.join(MASTER_QUANTITIES)})")
            values[f"master.{part}.{k}"] = v
    return values


def rules_from_document(doc: Any, where: str) -> MasterSettings:
    """The :class:`MasterSettings` of a rules document, checked as the settings are."""
    m = master_settings(settings_values(doc, where), where)
    if m is None:
        raise InputError(where, "master.serial", "required: the master motor's serial")
    return m


# --------------------------------------------------------------------------- the tables
def _version(con: Connection) -> int | None:
    if not sa.inspect(con).has_table("gate_schema_version"):
        return None
    v = con.execute(sa.select(sa.func.max(gate_version.c.version))).scalar()
    return int(v) if v is not None else None


def _check_version(v: int | None) -> None:
    if v is not None and v > GATE_SCHEMA_VERSION:
        raise SchemaError(f"gate tables at layout version {v} are newer than this tool ({GATE_SCHEMA_VERSION})")


def ensure_tables(con: Connection) -> tuple[int | None, int]:
    """The migration step of the gate tables, inside the caller's transaction: create them at
    :data:`GATE_SCHEMA_VERSION` when absent; refuse a newer layout. ``(before, now)``."""
    if con.dialect.name == "postgresql":
        con.execute(sa.text(f"SELECT pg_advisory_xact_lock({_LOCK})"))
    v = _version(con)
    if v is None:
        _metadata.create_all(con)
        con.execute(gate_version.insert().values(version=GATE_SCHEMA_VERSION))
        return None, GATE_SCHEMA_VERSION
    _check_version(v)
    return v, GATE_SCHEMA_VERSION


def migrate(db: str | Path) -> tuple[int | None, int]:
    """Bring the gate tables of a records database to :data:`GATE_SCHEMA_VERSION`."""
    with connected(db, False, "migrate the gate tables") as con, con.begin():
        return ensure_tables(con)


def _station(station: str) -> str:
    if not isinstance(station, str) or not station.strip() or not station.isprintable() or len(station) > 64:
        raise InputError(None, "station", f"{station!r}: a station id of 1 to 64 printable characters")
    return station


def change(db: str | Path, station: str, master: MasterSettings | None, set_by: str | None = None,
           note: str | None = None, now: dt.datetime | None = None) -> GateRules:
    """Record a change of ``station``'s rules (``master`` None: clear the gate) as its next row;
    the tables are made when absent (a new SQLite file too). Returns the change."""
    station = _station(station)
    if not is_url(db) and not Path(db).exists():
        migrate_runs(db)  # a new database: the runs table too, as the first record would make it
    else:
        with connected(db, True, "read the records database", DEFAULT_LOCK_TIMEOUT_S) as con:
            empty = not sa.inspect(con).has_table("runs")
        if empty:  # a new server database: likewise (an existing one is left at its version)
            migrate_runs(db)
    set_at = (now or dt.datetime.now(dt.UTC)).astimezone(dt.UTC).isoformat(timespec="milliseconds")
    with connected(db, False, "change the gate rules") as con, con.begin():
        ensure_tables(con)
        last = con.execute(sa.select(sa.func.max(gate_rules.c.seq)).where(gate_rules.c.station == station)).scalar()
        seq = int(last or 0) + 1
        con.execute(gate_rules.insert().values(
            station=station, seq=seq, set_at=set_at, set_by=set_by, action="set" if master else "clear",
            rules_json=None if master is None else json.dumps(rules_document(master), allow_nan=False),
            note=note, tool_version=__version__))
    return GateRules(station, seq, set_at, set_by, master, note)


def _rules_of_row(db: str | Path, r: Any) -> GateRules:
    """A stored row, checked like any input: :class:`InputError` naming the database and the row."""
    where = f"{db_label(db)}, gate_rules row {r['station']!r} #{r['seq']}"
    if r["action"] not in ACTIONS:
        raise InputError(where, "action", f"{r['action']!r}: one of {', '.join(ACTIONS)}")
    if not isinstance(r["set_at"], str):
        raise InputError(where, "set_at", f"{r['set_at']!r}: not a time")
    try:
        at = dt.datetime.fromisoformat(r["set_at"])
    except ValueError:
        raise InputError(where, "set_at", f"{r['set_at']!r}: not an ISO 8601 time") from None
    if at.tzinfo is None:
        raise InputError(where, "set_at", f"{r['set_at']!r}: no UTC offset")
    master = None
    if r["action"] == "set":
        text = r["rules_json"]
        if not isinstance(text, str):
            raise InputError(where, "rules_json", "missing")
        master = rules_from_document(loads_json(text, where, "rules_json"), where)
    return GateRules(str(r["station"]), int(r["seq"]), r["set_at"], r["set_by"], master, r["note"])


def history(db: str | Path, station: str | None = None, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> list[GateRules]:
    """Every change of ``station``'s rules (None: every station's), oldest first, each checked."""
    with connected(db, True, "read the gate rules", timeout_s) as con:
        v = _version(con)
        if v is None:
            return []
        _check_version(v)
        q = sa.select(gate_rules).order_by(gate_rules.c.station, gate_rules.c.seq)
        if station is not None:
            q = q.where(gate_rules.c.station == station)
        rows = con.execute(q).mappings().all()
    return [_rules_of_row(db, r) for r in rows]


def current(db: str | Path, station: str | None, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> GateRules | None:
    """The change in force on ``station`` (its latest; None: none, or no station id, or no database
    file yet). A cleared gate is returned as such (``master`` None)."""
    if station is None or (not is_url(db) and not Path(db).exists()):
        return None
    with connected(db, True, "read the gate rules", timeout_s) as con:
        v = _version(con)
        if v is None:
            return None
        _check_version(v)
        r = con.execute(sa.select(gate_rules).where(gate_rules.c.station == station)
                        .order_by(sa.desc(gate_rules.c.seq)).limit(1)).mappings().first()
    return None if r is None else _rules_of_row(db, r)
