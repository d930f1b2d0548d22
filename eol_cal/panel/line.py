"""The line view's figures, read from the records database and nothing else.

Per station: its latest runs, its first-pass yield, its master gate (the database's rules: due or
failed blocks production) and whether its latest run broke a rule of a stored baseline; for the line:
the yield and first-pass yield per shift and station. :class:`LineWatch` reads them again every few
seconds on a thread (the database is opened read-only where the driver allows it: SQLite's
``mode=ro``; on PostgreSQL only SELECTs are sent) and is what the line view's page follows.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import math
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from eol_cal.errors import EolCalError
from eol_cal.lot.baseline import Baseline
from eol_cal.lot.runs import CHARTED, QUANTITIES, read_lot
from eol_cal.lot.spc_stats import judge_lot
from eol_cal.lot.stats import first_pass_yield_of
from eol_cal.msa.gate import gate_status
from eol_cal.records.connect import db_label
from eol_cal.records.kinds import MEASURED_KIND
from eol_cal.records.query import read_rows, select_runs
from eol_cal.records.record import NO_STATION
from eol_cal.records.tables import runs

#: the runs a station's card lists, and the days of runs the view reads (the shifts it shows lie in them)
LAST_RUNS = 6
WINDOW_DAYS = 1
SHIFTS_SHOWN = 3
#: the days of a station's runs judged against a baseline for the panel's alarm
ALARM_DAYS = 30
COLUMNS = ("run_id", "serial", "station", "started_at", "verdict", "kind", "reasons", "operator")


def _yield(verdicts: Sequence[str]) -> float | None:
    judged = [v for v in verdicts if v in ("pass", "fail")]
    return sum(v == "pass" for v in judged) / len(judged) if judged else None


def _fpy(serials: Sequence[str], verdicts: Sequence[str]) -> float | None:
    value, n = first_pass_yield_of(np.array(serials, dtype=object), np.array(verdicts, dtype=object))
    return value if n and math.isfinite(value) else None


def shift_of(started_at: str, shifts: Sequence[dt.time]) -> str:
    """The start (UTC, ``YYYY-MM-DD HH:MM``) of the shift a run's start falls in."""
    t = dt.datetime.fromisoformat(started_at).astimezone(dt.UTC)
    starts = [dt.datetime.combine(t.date() + dt.timedelta(days=d), s, dt.UTC) for d in (-1, 0) for s in shifts]
    return max(s for s in starts if s <= t).strftime("%Y-%m-%d %H:%M")


def baseline_alarms(db: str | Path, baseline: Baseline | None, since: str | None = None,
                    station: str | None = None) -> dict[str, list[str]]:
    """Per station: the baseline's rules (Nelson's) that its latest production run is part of, in words."""
    if baseline is None:
        return {}
    lot = read_lot(db, station=station, since=since)
    if not len(lot):
        return {}
    violations, _ = judge_lot(lot, baseline, [q for q in QUANTITIES if q.key in CHARTED])
    latest = {name: lot.run_id[idx[-1]] for name, idx in lot.stations()}
    out: dict[str, list[str]] = {}
    for v in violations:
        if latest.get(v["station"]) in v["runs"]:
            out.setdefault(v["station"], []).append(
                f"station {v['station']}: {v['quantity']} breaks rule {v['rule']} of baseline {baseline.name!r} "
                f"({v['text']}; serials {', '.join(v['serials'][-3:])})")
    return out


def station_alarms(db: str | Path, station: str | None, baseline: Baseline | None, timeout_s: float = 5.0) -> list[str]:
    """The baseline's rules the station's latest run breaks (the operator panel's alarm)."""
    del timeout_s  # the lot's read has its own
    since = (dt.datetime.now(dt.UTC) - dt.timedelta(days=ALARM_DAYS)).strftime("%Y-%m-%d")
    try:
        found = baseline_alarms(db, baseline, since, station)
    except EolCalError as exc:
        return [f"baseline {baseline.name if baseline else ''}: cannot judge the runs: {exc}"]
    return found.get(station or NO_STATION, [])


def line_state(db: str | Path, shifts: Sequence[dt.time], baseline: Baseline | None = None,
               now: dt.datetime | None = None, timeout_s: float = 5.0) -> dict[str, Any]:
    """The line as the view shows it (JSON-ready): ``stations`` (state, last runs, yields, gate,
    alarms), ``shifts`` (yield per shift and station), ``fpy`` of the line, ``alarms``."""
    now = now or dt.datetime.now(dt.UTC)
    since = (now - dt.timedelta(days=WINDOW_DAYS)).strftime("%Y-%m-%d")
    q = select_runs(since=since).with_only_columns(*(runs.c[c] for c in COLUMNS))
    rows = read_rows(db, q, timeout_s)
    by_station: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        by_station.setdefault(r["station"] or NO_STATION, []).append(r)
    rule_alarms = baseline_alarms(db, baseline, since)
    stations, alarms = [], []
    for name in sorted(by_station):
        rs = by_station[name]
        prod = [r for r in rs if r["kind"] == MEASURED_KIND]
        gate = gate_status(db, None if name == NO_STATION else name, None, timeout_s)
        station_alarms_ = ([gate.line] if gate is not None and gate.blocked else []) + rule_alarms.get(name, [])
        alarms += [a if a.startswith("station ") else f"station {name}: {a}" for a in station_alarms_]
        last = rs[-1]
        state = "blocked" if gate is not None and gate.blocked else ("alarm" if rule_alarms.get(name) else last["verdict"])
        stations.append({
            "station": name, "state": state, "last_at": last["started_at"], "gate": None if gate is None else gate.line,
            "alarms": station_alarms_, "runs": len(prod), "yield": _yield([r["verdict"] for r in prod]),
            "fpy": _fpy([r["serial"] for r in prod], [r["verdict"] for r in prod]),
            "last": [{"serial": r["serial"], "verdict": r["verdict"], "kind": r["kind"], "started_at": r["started_at"],
                      "operator": r["operator"], "reasons": r["reasons"]} for r in reversed(rs[-LAST_RUNS:])],
        })
    per_shift: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        if r["kind"] == MEASURED_KIND:
            per_shift.setdefault((shift_of(r["started_at"], shifts), r["station"] or NO_STATION), []).append(r)
    shown = sorted({s for s, _ in per_shift}, reverse=True)[:SHIFTS_SHOWN]
    shift_rows = [{"shift": s, "station": st, "runs": len(rs), **{v: sum(r["verdict"] == v for r in rs)
                                                                    for v in ("pass", "fail", "error")},
                   "yield": _yield([r["verdict"] for r in rs]),
                   "fpy": _fpy([r["serial"] for r in rs], [r["verdict"] for r in rs])}
                  for (s, st), rs in sorted(per_shift.items(), key=lambda kv: (kv[0][0], kv[0][1]), reverse=True)
                  if s in shown]
    prod = [r for r in rows if r["kind"] == MEASURED_KIND]
    return {"db": db_label(db), "read_at": now.isoformat(timespec="seconds"), "since": since, "stations": stations,
            "shifts": shift_rows, "fpy": _fpy([r["serial"] for r in prod], [r["verdict"] for r in prod]),
            "alarms": alarms, "error": None}


class LineWatch:
    """The line's state read again every ``poll_s`` seconds on a thread; a version that grows when it changed."""

    def __init__(self, db: str | Path, shifts: Sequence[dt.time], baseline: Baseline | None, poll_s: float) -> None:
        self.db, self.shifts, self.baseline, self.poll_s = db, tuple(shifts), baseline, poll_s
        self._lock = threading.Lock()
        self._state: dict[str, Any] = {"db": db_label(db), "stations": [], "shifts": [], "fpy": None, "alarms": [],
                                       "error": "not read yet", "read_at": None}
        self._version = 0

    @property
    def version(self) -> int:
        with self._lock:
            return self._version

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._state, version=self._version)

    def read(self) -> None:
        """Read the database once; a failure is shown on the page (the view keeps trying)."""
        try:
            state = line_state(self.db, self.shifts, self.baseline)
        except EolCalError as exc:
            with self._lock:
                state = dict(self._state, error=f"cannot read the records: {exc}")
        with self._lock:
            if {k: v for k, v in state.items() if k != "read_at"} != {k: v for k, v in self._state.items() if k != "read_at"}:
                self._version += 1
            self._state = state

    @contextlib.contextmanager
    def running(self, closing: threading.Event) -> Iterator[None]:
        """Read now, then every ``poll_s`` on a thread until ``closing`` is set."""
        self.read()

        def loop() -> None:
            while not closing.wait(self.poll_s):
                self.read()

        thread = threading.Thread(target=loop, name="line-watch", daemon=True)
        thread.start()
        try:
            yield
        finally:
            closing.set()
            thread.join(self.poll_s + 30.0)
