"""The master-motor gate on a station: the records' latest master run decides whether a
production motor may run (:func:`check_gate`), and a master run is judged against its
references (:func:`judge_master`). The rules are :mod:`eol_cal.msa.master`'s.

The latest master run is read from the records database: the station's (its ``station_id``)
runs of kind ``master`` of the master serial. A database that cannot be read gives no answer,
so production is refused until it can be (a master run made meanwhile is spooled and counts
once the spool is flushed into the database).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import sqlalchemy as sa

from eol_cal.errors import EolCalError, InputError
from eol_cal.msa.master import MasterRun, MasterSettings, check_master, master_due
from eol_cal.msa.study import quantity
from eol_cal.station.record import Problem
from eol_cal.station.records import runs
from eol_cal.station.records_query import read_rows, select_runs

if TYPE_CHECKING:
    from eol_cal.station.record import RunRecord


class MasterGateClosed(EolCalError):
    """A production run refused by the master gate (exit code 2): the check is due, or the last
    one failed. ``problems`` holds the refusal code and text (the cycle's refusal record)."""

    def __init__(self, code: str, text: str) -> None:
        super().__init__(text)
        self.problems = (Problem(code, text),)


def latest_master_run(db: str | Path, m: MasterSettings, station: str | None,
                      timeout_s: float = 5.0) -> MasterRun | None:
    """The latest run of kind ``master`` of ``m.serial`` on ``station`` (any station when None)."""
    if not str(db).count("://") and not Path(db).exists():
        return None  # a new station: no database yet, so no master run either
    q = (select_runs(serial=m.serial, station=station, kind="master")
         .with_only_columns(runs.c.run_id, runs.c.started_at, runs.c.verdict)
         .order_by(None).order_by(sa.desc(runs.c.started_at), sa.desc(runs.c.run_id)).limit(1))
    rows = read_rows(db, q, timeout_s)
    if not rows:
        return None
    r = rows[0]
    started = dt.datetime.fromisoformat(str(r["started_at"]))
    if started.tzinfo is None:
        started = started.replace(tzinfo=dt.UTC)
    return MasterRun(started, r["verdict"] == "pass", str(r["run_id"]), str(r["verdict"]))


def check_gate(db: str | Path, m: MasterSettings, station: str | None, now: dt.datetime | None = None,
               timeout_s: float = 5.0) -> MasterRun | None:
    """Raise :class:`MasterGateClosed` when production may not run now; else the master run
    that lets it (the latest, passed and within its period)."""
    now = now or dt.datetime.now(dt.UTC)
    try:
        last = latest_master_run(db, m, station, timeout_s)
    except InputError as exc:
        raise MasterGateClosed("master_due", f"master check: cannot read the last run of the master {m.serial}: "
                                             f"{exc.reason}") from None
    why = master_due(now, last, m)
    if why is not None:
        raise MasterGateClosed("master_failed" if why.startswith("master check failed") else "master_due",
                               f"{why}; run the master {m.serial} first")
    return last


#: the refusal codes of the gate
GATE_CODES = ("master_due", "master_failed")


def gate_refusal(rec: RunRecord) -> str | None:
    """The one line that says why the gate refused a run (None: not a gate refusal)."""
    if rec.kind != "refusal" or not set(rec.refusal_codes) & set(GATE_CODES):
        return None
    text = rec.error.message if rec.error is not None else "; ".join(rec.reasons)
    return f"{rec.serial}: refused, {text} (record {rec.run_id[:8]}; nothing was touched)"


def judge_master(values: Mapping[str, float], m: MasterSettings) -> list[str]:
    """The reasons a master run's values (stored units: N*m/A, rad, N*m, %) fail its check."""
    shown = {k: v * quantity(k).scale for k, v in values.items() if v is not None and math.isfinite(v)}
    return check_master(shown, m)[1]
