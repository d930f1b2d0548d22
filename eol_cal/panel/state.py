"""What the operator panel shows, kept as one snapshot that the cycle's events update.

The cycle runs in the station's main thread (:mod:`eol_cal.station.cycle`, the terminal loop's
own); its observers (:class:`~eol_cal.station.executor.StepEvent`) and its ``on_verdict`` write
here, and the web server's threads read a copy (:meth:`PanelState.snapshot`) with a version that
grows with every change: the page's live stream sends a snapshot whenever the version moved.
Everything here is data (numbers and plain text); the page puts text into the document as text,
never as markup (:mod:`eol_cal.panel.app`).
"""

from __future__ import annotations

import copy
import math
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.rendering.display import display_unit
from eol_cal.msa.gate import GateStatus, gate_refusal
from eol_cal.station.executor import StepEvent
from eol_cal.station.steps import acquire_after, acquire_before

if TYPE_CHECKING:
    from eol_cal.records.record import RunRecord

#: the last motors the panel lists, and the limits its verdict shows (every failed one, else the closest)
LAST_MOTORS = 8
MARGIN_ROWS = 4
#: points of a torque trace sent to the page (the capture's samples, decimated)
TRACE_POINTS = 600
#: the acquisitions whose capture the panel draws: step name -> the context's field and its label
TRACED = {acquire_before.NAME: ("before", "calibration capture"), acquire_after.NAME: ("after", "compensated")}


def trace_points(t: np.ndarray, torque: np.ndarray, points: int = TRACE_POINTS) -> dict[str, list[float]]:
    """A capture's torque (N*m) against time (s), at most ``points`` samples: each kept point is a
    stretch's extreme away from its mean, so the ripple's peaks stay visible at any length."""
    n = len(t)
    if n <= points:
        return {"t": [round(float(x), 5) for x in t], "torque": [round(float(y), 5) for y in torque]}
    edges = np.linspace(0, n, points + 1).astype(int)
    keep = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        piece = torque[a:b]
        keep.append(a + int(np.argmax(np.abs(piece - piece.mean()))))
    idx = np.asarray(keep)
    return {"t": [round(float(x), 5) for x in t[idx]], "torque": [round(float(y), 5) for y in torque[idx]]}


def _number(x: float) -> float | None:
    """A figure for JSON (NaN and infinities: None)."""
    return float(x) if x is not None and math.isfinite(x) else None


def margins(rec: RunRecord, rows: int = MARGIN_ROWS) -> tuple[list[dict[str, Any]], int]:
    """The record's judged limits a person reads first: every failed one, then the closest to their
    limit (margin / limit), at most ``rows``; values in display units (k6 in mN*m/A). Also how many
    judged limits are left out (all met, with more margin)."""
    judged = [c for c in rec.checks if c.passed is not None]

    def closeness(c: Any) -> tuple[bool, float]:
        rel = abs(c.margin / c.limit) if c.limit and math.isfinite(c.margin) else math.inf
        return (c.passed is not False, rel)

    ordered = sorted(judged, key=closeness)
    shown = ordered[:max(rows, sum(c.passed is False for c in judged))]
    out = []
    for c in shown:
        unit, factor = display_unit(c.unit)
        out.append({"key": c.key, "title": c.title, "unit": "" if unit == "1" else unit, "sense": c.sense,
                    "value": _number(c.value * factor), "limit": _number(c.limit * factor),
                    "margin": _number(c.margin * factor), "passed": c.passed})
    return out, len(judged) - len(out)


def verdict_view(rec: RunRecord) -> dict[str, Any]:
    """The large verdict of one run: the word, its reasons (the gate's one line for its refusal),
    the limits' margins and what a person must know about the dyno and the ECU."""
    gate_line = gate_refusal(rec)
    reasons = [gate_line] if gate_line is not None else list(rec.reasons)
    notes = []
    if rec.kind == "refusal":
        notes.append(f"refused ({', '.join(rec.refusal_codes)}): nothing was written to the ECU; not the motor's result")
    if rec.safe_state:
        notes.append(f"dyno safe state: {rec.safe_state}")
    if rec.ecu_active is not None and rec.ecu_active.block == "uncompensated":
        notes.append("ECU: the uncompensated block is active: the motor is not calibrated")
    shown, left = margins(rec)
    return {"serial": rec.serial, "run_id": rec.run_id, "verdict": rec.verdict, "kind": rec.kind, "reasons": reasons,
            "notes": notes, "margins": shown, "margins_left": left, "report": None, "record": "being written"}


class PanelState:
    """The panel's snapshot and its version; every method is safe from any thread."""

    def __init__(self, station: str | None, operator: str | None = None, demo: bool = False) -> None:
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._data: dict[str, Any] = {
            "station": station, "operator": operator, "demo": demo, "phase": "idle", "serial": None, "run_id": None,
            "steps": [], "traces": [], "verdict": None, "last": [], "counts": None, "gate": None, "alarms": [],
            "message": None, "ended": False, "version": 0,
        }

    # ------------------------------------------------------------------ reading
    @property
    def version(self) -> int:
        with self._lock:
            return int(self._data["version"])

    def snapshot(self) -> dict[str, Any]:
        """A deep copy of the panel's state (JSON-ready)."""
        with self._lock:
            return copy.deepcopy(self._data)

    def get(self, key: str) -> Any:
        with self._lock:
            return copy.deepcopy(self._data[key])

    def wait_change(self, version: int, timeout_s: float) -> int:
        """Block until the version is past ``version`` or ``timeout_s`` passed; the version now."""
        with self._changed:
            self._changed.wait_for(lambda: self._data["version"] != version, timeout_s)
            return int(self._data["version"])

    # ------------------------------------------------------------------ writing
    def update(self, **values: Any) -> None:
        with self._changed:
            self._data.update(values)
            self._data["version"] += 1
            self._changed.notify_all()

    def message(self, level: str, text: str) -> None:
        """A line for the operator (``error``: a refused scan or action; ``info``)."""
        self.update(message={"level": level, "text": text, "at": time.time()})

    def begin(self, serial: str) -> None:
        """A motor's cycle starts: its steps and traces from nothing, the last verdict put away."""
        self.update(phase="running", serial=serial, run_id=None, steps=[], traces=[], verdict=None, message=None)

    def observe(self, event: StepEvent) -> None:
        """The executor's observer: each step's start and end with its time; a capture's torque trace."""
        trace = None
        if event.what == "done" and event.step in TRACED and event.context is not None:
            field, label = TRACED[event.step]
            cap = getattr(event.context, field, None)
            if cap is not None and cap.has("torque"):
                trace = {"label": label, **trace_points(np.asarray(cap.t), np.asarray(cap["torque"]))}
        with self._changed:
            steps = self._data["steps"]
            if event.what == "start":
                steps.append({"step": event.step, "what": "start", "seconds": None, "since": time.time()})
            else:
                row = next((s for s in reversed(steps) if s["step"] == event.step), None)
                if row is None:
                    row = {"step": event.step}
                    steps.append(row)
                row.update(what=event.what, seconds=event.elapsed_s)
            self._data["run_id"] = event.run_id
            if trace is not None:
                self._data["traces"].append(trace)
            self._data["version"] += 1
            self._changed.notify_all()

    def verdict_known(self, rec: RunRecord, spooled: bool = True) -> None:
        """The cycle's ``on_verdict``: the verdict the moment it is known (``spooled``: the record
        is safe in the spool; otherwise it is written before the next scan)."""
        view = verdict_view(rec)
        if not spooled:
            view["record"] = "being written (the spool could not take it: not safe until written)"
        self.update(verdict=view)

    def finished(self, rec: RunRecord, report: str | None, where: str, counts: dict[str, int]) -> None:
        """The motor's report and record are written (``where``: the database or the spool): it joins
        the last motors and the session's counts."""
        with self._changed:
            verdict = self._data["verdict"] or verdict_view(rec)
            if verdict["run_id"] == rec.run_id:
                verdict = verdict_view(rec) | {"report": report, "record": where}
            self._data["verdict"] = verdict
            self._data["last"] = ([{"serial": rec.serial, "verdict": rec.verdict, "kind": rec.kind, "run_id": rec.run_id,
                                    "started_at": rec.started_at}] + self._data["last"])[:LAST_MOTORS]
            self._data.update(phase="idle", serial=None, counts=counts)
            self._data["version"] += 1
            self._changed.notify_all()

    def written(self, rec: RunRecord, report: str | None, where: str) -> None:
        """A motor's report and record written after the panel took the next scan (the report
        thread's, :mod:`eol_cal.station.report_behind`): its verdict, where it is still shown, and
        its line among the last motors, as the record ends (a failed report makes it an error)."""
        with self._changed:
            shown = self._data["verdict"]
            if shown is not None and shown["run_id"] == rec.run_id:
                self._data["verdict"] = verdict_view(rec) | {"report": report, "record": where}
            for last in self._data["last"]:
                if last["run_id"] == rec.run_id:
                    last["verdict"] = rec.verdict
            self._data["version"] += 1
            self._changed.notify_all()

    def interrupted(self, serial: str, why: str, counts: dict[str, int]) -> None:
        """A motor stopped by the stop button or a signal: the dyno was sent to its safe state and
        the run recorded (an error, unless it had ended)."""
        with self._changed:
            known = self._data["verdict"]
            if known is not None and known["run_id"] == self._data["run_id"]:  # the record's own verdict and reasons
                known["reasons"].insert(0, why)
            else:
                known = {"serial": serial, "run_id": self._data["run_id"], "verdict": "error", "kind": "production",
                         "reasons": [why], "margins": [], "margins_left": 0, "notes": [], "report": None}
            known["notes"].append("the dyno was sent to its safe state and the run recorded (an error, unless it had ended)")
            known["record"] = "written"
            self._data["verdict"] = known
            self._data["last"] = ([{"serial": serial, "verdict": "error", "kind": "production",
                                    "run_id": self._data["run_id"], "started_at": None}] + self._data["last"])[:LAST_MOTORS]
            self._data.update(phase="idle", serial=None, counts=counts)
            self._data["version"] += 1
            self._changed.notify_all()

    def gate(self, status: GateStatus | None) -> None:
        self.update(gate=None if status is None else {"blocked": status.blocked, "line": status.line})

    def alarms(self, lines: Sequence[str]) -> None:
        self.update(alarms=list(lines))
