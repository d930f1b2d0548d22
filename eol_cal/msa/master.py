"""The master-motor gate: a station measures its master motor every period and runs no
production motor while that check is due or last failed.

Station settings (``docs/station.md``, "Master motor")::

    [master]
    serial = "MASTER-0001"
    every_h = 8                      # a check every 8 hours, or
    shifts = "06:00,14:00,22:00"     # one per shift (starts in master.timezone)
    timezone = "Europe/Berlin"       # IANA name; default UTC
    [master.reference]               # the master's values, display units
    k6 = 0.640                       # mN*m/A
    phase_k6 = 12.5                  # deg
    pp_after_pct = 0.9               # %
    [master.tolerance]               # the allowed deviation from each reference (+-, same units)
    k6 = 0.03
    phase_k6 = 2.0
    pp_after_pct = 0.3

A master run passes when every quantity with a reference lies within its tolerance (a phase on
the circle). The gate (:func:`master_due`) looks at the latest master run: none, failed, older
than ``every_h``, or from before the current shift began -> due, with the reason. Pure functions;
the station reads the latest master run and writes the refusal record.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from eol_cal.errors import InputError
from eol_cal.firmware.block import serial_problem
from eol_cal.records.parts import MasterCheck

#: the quantities a master check may compare (display units: mN*m/A, deg, mN*m, %, %)
MASTER_QUANTITIES = ("k6", "phase_k6", "c6", "pp_before_pct", "pp_after_pct")
_UNITS = {"k6": "mN*m/A", "phase_k6": "deg", "c6": "mN*m", "pp_before_pct": "%", "pp_after_pct": "%"}
_ANGLES = frozenset({"phase_k6"})
#: the hours ``master.every_h`` may take (as the settings key)
EVERY_H_BOUNDS = (0.01, 10_000.0)


@dataclass(frozen=True)
class MasterSettings:
    """A station's master motor: its serial, reference values and tolerances (display units),
    and how often it is checked (``every_h`` hours, or once per shift: ``shifts`` start times in
    ``timezone``)."""

    serial: str
    reference: Mapping[str, float]
    tolerance: Mapping[str, float]
    every_h: float | None = None
    shifts: tuple[dt.time, ...] = ()
    timezone: str = "UTC"
    source: str = field(default="settings", compare=False)


@dataclass(frozen=True)
class MasterRun:
    """The latest master run: when it started (aware datetime), whether it passed, its run id."""

    started_at: dt.datetime
    passed: bool
    run_id: str = ""
    verdict: str = ""
    rules_seq: int | None = None  # the change of the station's gate rules it was judged against
    checks: tuple[MasterCheck, ...] = ()  # its checks against the references


def parse_shifts(text: str, where: str, key: str = "master.shifts") -> tuple[dt.time, ...]:
    """``"06:00,14:00,22:00"`` -> the shift start times (sorted); bad ones name the key."""
    out = []
    for part in text.split(","):
        try:
            out.append(dt.time.fromisoformat(part.strip()))
        except ValueError:
            raise InputError(where, key, f"{part.strip()!r} is not a time HH:MM") from None
    if not out:
        raise InputError(where, key, "no shift start times")
    return tuple(sorted(set(out)))


def master_settings(values: Mapping[str, object], where: str | Callable[[str], str]) -> MasterSettings | None:
    """The :class:`MasterSettings` of a station's flattened settings keys (``master.serial``,
    ``master.reference.k6``...); None when ``master.serial`` is unset. Every reference needs a
    tolerance and a period must be set; each refusal names the key and where it came from
    (``where``: the file, or a function of the key giving the file or ``$VARIABLE``)."""
    at = where if callable(where) else (lambda _key: where)
    try:
        return _master_settings(values, at)
    except InputError as exc:
        raise InputError(at(exc.field or "master.serial"), exc.field, exc.reason) from None


def _master_settings(values: Mapping[str, object], at: Callable[[str], str]) -> MasterSettings | None:
    where = at("master.serial")
    serial = values.get("master.serial")
    if serial is None:
        stray = [k for k, v in values.items() if k.startswith("master.") and v is not None and k != "master.timezone"]
        if stray:
            raise InputError(where, stray[0], "set master.serial too (the master motor's serial)")
        return None
    if not isinstance(serial, str) or (why := serial_problem(serial)) is not None:
        raise InputError(where, "master.serial", f"{serial!r}: " + (why or "not a text"))
    ref = {k: _number(values, f"master.reference.{k}", where) for k in MASTER_QUANTITIES
           if values.get(f"master.reference.{k}") is not None}
    tol = {k: _number(values, f"master.tolerance.{k}", where) for k in MASTER_QUANTITIES
           if values.get(f"master.tolerance.{k}") is not None}
    if not ref:
        raise InputError(where, "master.reference", "no reference values: give at least master.reference.k6")
    for k, x in ref.items():
        if k not in _ANGLES and x < 0.0:
            raise InputError(where, f"master.reference.{k}", f"{x:g}: an amplitude is not negative")
        if k in _ANGLES and not -360.0 <= x <= 360.0:
            raise InputError(where, f"master.reference.{k}", f"{x:g} deg: a phase between -360 and 360 deg")
        if k not in tol:
            raise InputError(where, f"master.tolerance.{k}", f"required: master.reference.{k} is set")
    for k, t in tol.items():
        if not t > 0.0:
            raise InputError(where, f"master.tolerance.{k}", f"{t:g} is not a positive number")
        if k in _ANGLES and not t < 180.0:
            raise InputError(where, f"master.tolerance.{k}", f"{t:g} deg: a phase's tolerance below 180 deg "
                                                            "(wider takes every angle)")
        if k not in ref:
            raise InputError(where, f"master.reference.{k}", f"required: master.tolerance.{k} is set")
    every = values.get("master.every_h")
    shifts_text = values.get("master.shifts")
    if (every is None) == (shifts_text is None):
        raise InputError(where, "master.every_h", "set either master.every_h or master.shifts (how often the master runs)")
    if every is not None:
        every = _number(values, "master.every_h", where)
        if not EVERY_H_BOUNDS[0] <= every <= EVERY_H_BOUNDS[1]:
            raise InputError(where, "master.every_h", f"{every:g} h: between {EVERY_H_BOUNDS[0]:g} and "
                                                      f"{EVERY_H_BOUNDS[1]:g} h")
    tz = values.get("master.timezone") or "UTC"
    if not isinstance(tz, str):
        raise InputError(at("master.timezone"), "master.timezone", f"{tz!r}: not a text")
    _zone(tz, at("master.timezone"))
    if shifts_text is not None and not isinstance(shifts_text, str):
        raise InputError(where, "master.shifts", f"{shifts_text!r}: not a text")
    shifts = parse_shifts(str(shifts_text), where) if shifts_text is not None else ()
    return MasterSettings(serial, ref, tol, every, shifts, tz, where)


def _number(values: Mapping[str, object], key: str, where: str) -> float:
    """A finite number of the settings (a bool or a text is not one), or an :class:`InputError`."""
    x = values.get(key)
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
        raise InputError(where, key, f"{x!r} is not a finite number")
    return float(x)


def _zone(name: str, where: str) -> dt.tzinfo:
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise InputError(where, "master.timezone", f"{name!r} is not a time zone (IANA name, e.g. Europe/Berlin)") from None


def master_checks(measured: Mapping[str, float], m: MasterSettings) -> list[MasterCheck]:
    """Each quantity with a reference: the master run's value (display units) against it (a
    missing or non-finite value does not pass)."""
    out = []
    for key, ref in m.reference.items():
        x = measured.get(key)
        if x is None or not math.isfinite(x):
            out.append(MasterCheck(key, _UNITS[key], None, ref, m.tolerance[key], None, False))
            continue
        dev = x - ref
        if key in _ANGLES:
            dev = (dev + 180.0) % 360.0 - 180.0
        out.append(MasterCheck(key, _UNITS[key], float(x), ref, m.tolerance[key], dev, abs(dev) <= m.tolerance[key]))
    return out


def check_master(measured: Mapping[str, float], m: MasterSettings) -> tuple[bool, list[str]]:
    """Whether a master run's values (display units) lie within the tolerances of their
    references; the reasons of those that do not (a missing value does not pass)."""
    reasons = [c.reason for c in master_checks(measured, m) if c.reason is not None]
    return not reasons, reasons


def duration(hours: float) -> str:
    """A span for people, never rounded to nothing: ``9.0 h`` from an hour up, ``1.2 min`` from
    a minute, else seconds (``36 s``, ``0.4 s``)."""
    if hours >= 1.0:
        return f"{hours:.1f} h"
    if hours * 60.0 >= 1.0:
        return f"{hours * 60.0:.1f} min"
    s = hours * 3600.0
    return f"{s:.0f} s" if s >= 10.0 else f"{s:.2g} s"


def shift_start(now: dt.datetime, m: MasterSettings) -> dt.datetime:
    """The start of the shift ``now`` (aware) lies in, as an aware datetime."""
    zone = _zone(m.timezone, m.source)
    local = now.astimezone(zone)
    starts = [dt.datetime.combine(local.date() + dt.timedelta(days=d), t, tzinfo=zone)
              for d in (-1, 0) for t in m.shifts]
    return max(s for s in starts if s <= local)


def master_due(now: dt.datetime, last: MasterRun | None, m: MasterSettings) -> str | None:
    """Why production may not run now (the master check is due or last failed), or None.

    ``last`` is the station's latest master run of ``m.serial`` (None: there is none).
    """
    if last is None:
        return f"master check due: no run of the master {m.serial} recorded"
    when = last.started_at.astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    if not last.passed:
        return (f"master check failed: the last run of the master {m.serial} ({when}, "
                f"{last.verdict or 'not passed'}) must be followed by a passing one")
    if m.every_h is not None:
        age_h = (now - last.started_at).total_seconds() / 3600.0
        if age_h > m.every_h:
            period = f"{m.every_h:g} h" if m.every_h >= 1.0 else duration(m.every_h)
            return f"master check due: the last passing run of {m.serial} was {duration(age_h)} ago ({when}; every {period})"
        return None
    start = shift_start(now, m)
    if last.started_at < start:
        return (f"master check due: no passing run of {m.serial} since the shift began "
                f"({start.strftime('%Y-%m-%d %H:%M %Z')}; last {when})")
    return None
