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

#: the quantities a master check may compare (display units: mN*m/A, deg, mN*m, %, %)
MASTER_QUANTITIES = ("k6", "phase_k6", "c6", "pp_before_pct", "pp_after_pct")
_UNITS = {"k6": "mN*m/A", "phase_k6": "deg", "c6": "mN*m", "pp_before_pct": "%", "pp_after_pct": "%"}
_ANGLES = frozenset({"phase_k6"})


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
    ref = {k: float(v) for k in MASTER_QUANTITIES if (v := values.get(f"master.reference.{k}")) is not None}  # type: ignore[arg-type]
    tol = {k: float(v) for k in MASTER_QUANTITIES if (v := values.get(f"master.tolerance.{k}")) is not None}  # type: ignore[arg-type]
    if not ref:
        raise InputError(where, "master.reference", "no reference values: give at least master.reference.k6")
    for k in ref:
        if k not in tol:
            raise InputError(where, f"master.tolerance.{k}", f"required: master.reference.{k} is set")
        if not (math.isfinite(tol[k]) and tol[k] > 0.0):
            raise InputError(where, f"master.tolerance.{k}", f"{tol[k]} is not a positive number")
    for k in tol:
        if k not in ref:
            raise InputError(where, f"master.reference.{k}", f"required: master.tolerance.{k} is set")
    every = values.get("master.every_h")
    shifts_text = values.get("master.shifts")
    if (every is None) == (shifts_text is None):
        raise InputError(where, "master.every_h", "set either master.every_h or master.shifts (how often the master runs)")
    tz = str(values.get("master.timezone") or "UTC")
    _zone(tz, at("master.timezone"))
    shifts = parse_shifts(str(shifts_text), where) if shifts_text is not None else ()
    return MasterSettings(str(serial), ref, tol, None if every is None else float(every), shifts, tz, where)  # type: ignore[arg-type]


def _zone(name: str, where: str) -> dt.tzinfo:
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise InputError(where, "master.timezone", f"{name!r} is not a time zone (IANA name, e.g. Europe/Berlin)") from None


def check_master(measured: Mapping[str, float], m: MasterSettings) -> tuple[bool, list[str]]:
    """Whether a master run's values (display units) lie within the tolerances of their
    references; the reasons of those that do not (a missing value does not pass)."""
    reasons = []
    for key, ref in m.reference.items():
        x = measured.get(key)
        unit = _UNITS[key]
        if x is None or not math.isfinite(x):
            reasons.append(f"master {key}: not measured")
            continue
        dev = x - ref
        if key in _ANGLES:
            dev = (dev + 180.0) % 360.0 - 180.0
        if abs(dev) > m.tolerance[key]:
            reasons.append(f"master {key} = {x:.4g} {unit} deviates {dev:+.3g} from its reference {ref:.4g} "
                           f"(tolerance +-{m.tolerance[key]:g})")
    return not reasons, reasons


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
    when = last.started_at.astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    if not last.passed:
        return (f"master check failed: the last run of the master {m.serial} ({when}, "
                f"{last.verdict or 'not passed'}) must be followed by a passing one")
    if m.every_h is not None:
        age_h = (now - last.started_at).total_seconds() / 3600.0
        if age_h > m.every_h:
            return f"master check due: the last passing run of {m.serial} was {age_h:.1f} h ago ({when}; every {m.every_h:g} h)"
        return None
    start = shift_start(now, m)
    if last.started_at < start:
        return (f"master check due: no passing run of {m.serial} since the shift began "
                f"({start.strftime('%Y-%m-%d %H:%M %Z')}; last {when})")
    return None
