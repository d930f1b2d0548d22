"""The master-motor gate on a station: the rules in force (:func:`gate_in_force`: the records
database's, :mod:`eol_cal.msa.rules`), the station's latest master run deciding whether a
production motor may run (:func:`check_gate`), and a master run judged against its references
(:func:`judge_master`). The rules themselves are :mod:`eol_cal.msa.master`'s.

The rules live in the records database per station; a station's settings (``[master]``) that
give rules where the database has none are recorded there as the station's first change, and
settings that differ from the database's rules are refused (``eol-cal gate set`` changes them).
So no run under a station id with rules can leave them out.

The master run that counts is read from the records: a run of kind ``master`` of the master
serial on this station exactly (a run without a station id only for a station without one),
the latest by its start as an instant (never by its text) that is not after the station's
clock, and judged against the change of rules in force. A database that cannot be read gives
no answer, so production is refused until it can be (a master run made meanwhile is spooled
and counts once the spool is flushed into the database).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import sqlalchemy as sa

from eol_cal.errors import EolCalError, InputError
from eol_cal.msa.master import MasterRun, MasterSettings, master_checks, master_due
from eol_cal.msa.rules import GateRules, change, current, rules_document
from eol_cal.msa.study import quantity
from eol_cal.records.record import GateInfo, MasterCheck, Problem
from eol_cal.records.rows import parse_record
from eol_cal.records.tables import runs
from eol_cal.records.query import read_rows

if TYPE_CHECKING:
    from eol_cal.records.record import RunRecord


class MasterGateClosed(EolCalError):
    """A production run refused by the master gate (exit code 2): the check is due, or the last
    one failed. ``problems`` holds the refusal code and text (the cycle's refusal record)."""

    def __init__(self, code: str, text: str) -> None:
        super().__init__(text)
        self.problems = (Problem(code, text),)


@dataclass(frozen=True)
class Gate:
    """The gate in force on a station: its rules, and the change in the records database that set
    them (None: a station without an id, whose rules are its settings')."""

    master: MasterSettings
    change: GateRules | None

    def info(self, **admitted: object) -> GateInfo:
        """The record's ``gate`` (``admitted``: the master run's fields and checks)."""
        c = self.change
        return GateInfo(rules_document(self.master), "records database" if c else f"settings {self.master.source}",
                        c.station if c else None, c.seq if c else None, c.set_at if c else None,
                        **admitted)  # type: ignore[arg-type]


def gate_in_force(db: str | Path, station: str | None, settings: MasterSettings | None, *, adopt: bool = True,
                  timeout_s: float = 5.0) -> Gate | None:
    """The gate of ``station``: the records database's rules; the settings' (``settings``) where
    the database has none, recorded there as the station's first change (``adopt``); None where
    neither has rules (or the latest change cleared them). Settings that differ from the
    database's rules are refused (:class:`InputError`, naming both); a database that cannot be
    read raises :class:`MasterGateClosed`."""
    if station is None:
        return None if settings is None else Gate(settings, None)
    try:
        cur = current(db, station, timeout_s)
    except InputError as exc:
        raise MasterGateClosed("master_due", f"master check of station {station}: {exc}") from None
    if cur is None:
        if settings is None:
            return None
        if not adopt:
            return Gate(settings, None)
        try:
            made = change(db, station, settings, set_by=f"settings {settings.source}",
                          note="the station's [master] settings, recorded by its first run")
        except InputError as exc:
            raise MasterGateClosed("master_due", f"master check of station {station}: {exc}") from None
        return Gate(settings, made)
    if settings is not None and (cur.master is None or rules_document(cur.master) != rules_document(settings)):
        held = "no gate (cleared)" if cur.master is None else "other rules"
        raise InputError(settings.source, "master", f"the records database holds {held} for station {station} "
                                                    f"({cur.label}); the database's rules are in force: change them "
                                                    "with eol-cal gate set, or remove [master] from the settings")
    return None if cur.master is None else Gate(cur.master, cur)


def _instant(text: object, run_id: object) -> dt.datetime:
    try:
        t = dt.datetime.fromisoformat(str(text))
    except ValueError:
        raise InputError(None, f"run {run_id} started_at", f"{text!r}: not an ISO 8601 time") from None
    return t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)  # no offset: UTC, as the lot reads it


def latest_master_run(db: str | Path, m: MasterSettings, station: str | None, now: dt.datetime | None = None,
                      timeout_s: float = 5.0) -> tuple[MasterRun | None, int]:
    """The latest run of kind ``master`` of ``m.serial`` on ``station`` (None: the runs without a
    station id) that started by ``now`` (an instant; default the clock), with its gate's rules
    number and checks; and how many such runs are dated after ``now`` (they do not count)."""
    now = now or dt.datetime.now(dt.UTC)
    if "://" not in str(db) and not Path(db).exists():
        return None, 0  # a new station: no database yet, so no master run either
    where = [runs.c.kind == "master", runs.c.serial == m.serial,
             runs.c.station == station if station is not None else runs.c.station.is_(None)]
    rows = read_rows(db, sa.select(runs.c.run_id, runs.c.started_at).where(*where), timeout_s)
    timed = [(_instant(r["started_at"], r["run_id"]), str(r["run_id"])) for r in rows]
    past = [t for t in timed if t[0] <= now]
    if not past:
        return None, len(timed)
    started, run_id = max(past)
    (row,) = read_rows(db, sa.select(runs.c.record_json).where(runs.c.run_id == run_id), timeout_s)
    rec = parse_record(db, run_id, row["record_json"])
    g = rec.gate
    return MasterRun(started, rec.verdict == "pass", run_id, rec.verdict, None if g is None else g.seq,
                     () if g is None else g.checks), len(timed) - len(past)


def check_gate(db: str | Path, gate: Gate | MasterSettings, station: str | None, now: dt.datetime | None = None,
               timeout_s: float = 5.0) -> MasterRun | None:
    """Raise :class:`MasterGateClosed` when production may not run now; else the master run that
    lets it (the latest by ``now``, passed, judged against the rules in force, within its period).
    ``gate`` as :func:`gate_in_force` gives it (a :class:`MasterSettings`: the database's rules
    of ``station`` when it has them, else these, nothing recorded)."""
    now = now or dt.datetime.now(dt.UTC)
    if isinstance(gate, MasterSettings):
        gate = gate_in_force(db, station, gate, adopt=False, timeout_s=timeout_s) or Gate(gate, None)
    m = gate.master
    try:
        last, later = latest_master_run(db, m, station, now, timeout_s)
    except InputError as exc:
        raise MasterGateClosed("master_due", f"master check: cannot read the last run of the master {m.serial}: "
                                             f"{exc.reason}") from None
    if last is None and later:
        raise MasterGateClosed("master_due", f"master check due: no run of the master {m.serial} before the station's "
                                             f"clock ({now.astimezone(dt.UTC):%Y-%m-%d %H:%M:%S} UTC; {later} dated "
                                             f"after it do not count); run the master {m.serial} first")
    if last is not None and gate.change is not None and last.rules_seq != gate.change.seq:
        judged = "no gate rules" if last.rules_seq is None else f"rules #{last.rules_seq}"
        raise MasterGateClosed("master_due", f"master check due: the last run of the master {m.serial} "
                                             f"({last.started_at.astimezone(dt.UTC):%Y-%m-%d %H:%M:%S} UTC) was judged "
                                             f"against {judged}, the station's {gate.change.label} are in force; "
                                             f"run the master {m.serial} first")
    why = master_due(now, last, m)
    if why is not None:
        raise MasterGateClosed("master_failed" if why.startswith("master check failed") else "master_due",
                               f"{why}; run the master {m.serial} first")
    return last


def admitted_info(gate: Gate, last: MasterRun) -> GateInfo:
    """The record's ``gate`` of a production run the master run ``last`` admitted."""
    return gate.info(master_run=last.run_id, master_started_at=last.started_at.isoformat(timespec="milliseconds"),
                     master_verdict=last.verdict, checks=last.checks)


#: the refusal codes of the gate
GATE_CODES = ("master_due", "master_failed")


def gate_refusal(rec: RunRecord) -> str | None:
    """The one line that says why the gate refused a run (None: not a gate refusal)."""
    if rec.kind != "refusal" or not set(rec.refusal_codes) & set(GATE_CODES):
        return None
    text = rec.error.message if rec.error is not None else "; ".join(rec.reasons)
    return f"{rec.serial}: refused, {text} (record {rec.run_id[:8]}; nothing was touched)"


def judge_master(values: Mapping[str, float], m: MasterSettings) -> list[MasterCheck]:
    """A master run's checks of its values (stored units: N*m/A, rad, N*m, %) against the
    references (display units); the failed ones' ``reason`` says why."""
    shown = {k: v * quantity(k).scale for k, v in values.items() if v is not None and math.isfinite(v)}
    return master_checks(shown, m)


@dataclass(frozen=True)
class GateStatus:
    """A station's master gate now, for a person: whether production is blocked, and one line why."""

    blocked: bool
    line: str


def gate_status(db: str | Path, station: str | None, settings: MasterSettings | None,
                timeout_s: float = 5.0) -> GateStatus | None:
    """The master gate of ``station`` (its settings' rules, or the records database's) and whether
    production may run now; None for a station without a gate. Reads only (nothing adopted)."""
    try:
        gate = gate_in_force(db, station, settings, adopt=False, timeout_s=timeout_s)
    except (MasterGateClosed, InputError) as exc:  # the cycle refuses each run with the same reason
        return GateStatus(True, f"master gate: {exc}")
    if gate is None:
        return None
    m = gate.master
    period = f"every {m.every_h:g} h" if m.every_h is not None else f"per shift ({m.timezone})"
    try:
        last = check_gate(db, gate, station, timeout_s=timeout_s)
    except MasterGateClosed as exc:
        return GateStatus(True, f"master {m.serial} ({period}): {exc}")
    if last is None:  # no rule asks for a master run yet
        return GateStatus(False, f"master {m.serial} ({period}): production may run")
    return GateStatus(False, f"master {m.serial} ({period}): passed {last.started_at:%Y-%m-%d %H:%M} UTC; "
                             "production may run")
