"""The master gate's rules as records: per station, in the records database, each change a row.

Table ``gate_rules`` beside ``runs`` (:mod:`eol_cal.records.tables`, on SQLite and PostgreSQL
through the engines of :mod:`eol_cal.records.connect`): one row per change of a station's rules, numbered ``seq`` 1, 2,
... per station, with when (``set_at``, UTC), by whom (``set_by``) and why (``note``) it was
made, and the rules themselves as JSON (``rules_json``: master serial, references, tolerances,
period; :func:`rules_document`) or ``action = 'clear'`` (the station has no gate from then on).
The latest row of a station is in force. Rows are never changed or deleted by this tool: the
table is the gate's history (``eol-cal gate history``).

Its layout is the records database's one version (:mod:`eol_cal.records.migrations`): the first
``eol-cal gate set`` on an empty database makes every table; a database at another version is
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

from eol_cal import __version__
from eol_cal.errors import InputError
from eol_cal.infra.inputs import loads_json
from eol_cal.msa.master import MASTER_QUANTITIES, MasterSettings, master_settings
from eol_cal.records.connect import DEFAULT_LOCK_TIMEOUT_S, connected, db_label, is_url
from eol_cal.records.migrations import ensure_schema, lock, migrate, readable
from eol_cal.records.tables import gate_rules

ACTIONS = ("set", "clear")

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
        migrate(db)  # a new file: every table, as the first record would make them
    set_at = (now or dt.datetime.now(dt.UTC)).astimezone(dt.UTC).isoformat(timespec="milliseconds")
    with connected(db, False, "change the gate rules") as con, con.begin():
        ensure_schema(con)
        lock(con)  # two changes at once get consecutive numbers
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
        if not readable(con):
            return []
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
        if not readable(con):
            return None
        r = con.execute(sa.select(gate_rules).where(gate_rules.c.station == station)
                        .order_by(sa.desc(gate_rules.c.seq)).limit(1)).mappings().first()
    return None if r is None else _rules_of_row(db, r)
