"""Raw columns as readers find them, and their assembly into one :class:`Capture`.

A reader turns a file into named :class:`Column` s (CSV: all on the rows of the file; MDF4:
each with the time base of its channel group). The channel map renames and converts them; then
:func:`assemble` puts everything on the torque channel's time base: analog channels by linear
interpolation, digital channels by zero-order hold (a level holds until the next change).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eol_cal.capture.data import CANONICAL_CHANNELS, DIGITAL_CHANNELS, Capture
from eol_cal.errors import InputError


@dataclass
class Column:
    """One channel as read from a file.

    Attributes
    ----------
    values : ndarray
        Samples in ``unit``.
    unit : str or None
        Unit as the file states it (pint syntax); ``None`` when the file gives none.
    times : ndarray or None
        The channel's own time base (s); ``None`` when it shares the file's rows (CSV).
    events : bool
        The samples are change events (irregular times, a new level at each), not levels.
    """

    values: np.ndarray
    unit: str | None = None
    times: np.ndarray | None = None
    events: bool = False


def zoh(times: np.ndarray, values: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Zero-order hold: at each ``t_new`` the last value at or before it.

    Parameters
    ----------
    times : ndarray
        Sorted times of ``values`` (s).
    values : ndarray
        Levels.
    t_new : ndarray
        Query times (s), none before ``times[0]``.
    """
    index = np.searchsorted(times, t_new, side="right") - 1
    return np.asarray(values)[np.clip(index, 0, len(times) - 1)]


def change_events(times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The changes of a level sequence: (times (s), new levels); the initial level is no change."""
    values = np.asarray(values)
    changed = np.flatnonzero(values[1:] != values[:-1]) + 1
    return np.asarray(times, dtype=np.float64)[changed], values[changed]


def is_change_list(times: np.ndarray, rows: list[np.ndarray]) -> bool:
    """True when a group of integral channels holds change events rather than sampled levels.

    Every row after the first changes at least one channel (a sampled group repeats levels
    between edges), or the times are irregular (more than 0.1 % spread of the step). The rows
    are compared as float64, each converted where it is looked at: a group whose first channel
    is not integral (a torque) converts no other.
    """
    if len(times) < 2:
        return True
    changed = np.zeros(len(times) - 1, dtype=bool)
    for r in rows:
        v = np.asarray(r, dtype=np.float64)
        if not np.array_equal(v, np.round(v)):
            return False
        changed |= v[1:] != v[:-1]
    if changed.all():
        return True
    dt = np.diff(times)
    return bool(dt.max() - dt.min() > 1e-3 * np.median(dt))


def combine_hall_bits(bits: list[Column], file: str, labels: list[str]) -> Column:
    """Hall state U + 2*V + 4*W from three 0/1 lines (each possibly on its own time base)."""
    for column, label in zip(bits, labels, strict=True):
        values = np.asarray(column.values, dtype=np.float64)
        bad = (values != 0) & (values != 1)
        if bad.any():
            first = int(np.argmax(bad))
            raise InputError(
                file, label, f"hall bit line holds {values[first].item()!r} at sample {first}; a bit line takes 0 or 1"
            )
    if all(c.times is None for c in bits) or all(
        c.times is not None and np.array_equal(c.times, bits[0].times) for c in bits
    ):
        values = sum(np.asarray(c.values).astype(np.int8) << k for k, c in enumerate(bits))
        return Column(values, None, bits[0].times, all(c.events for c in bits))
    if any(c.times is None for c in bits):
        raise InputError(file, "hall", "hall bit lines mix shared rows and own time bases")
    times = np.unique(np.concatenate([c.times for c in bits]))
    times = times[times >= max(float(c.times[0]) for c in bits)]
    values = sum(zoh(c.times, np.asarray(c.values).astype(np.int8), times) << k for k, c in enumerate(bits))
    return Column(values.astype(np.int8), None, times, all(c.events for c in bits))


def _as_digital(values: np.ndarray) -> np.ndarray:
    """int8 levels when the values are integral and small; else unchanged, for validation to name."""
    values = np.asarray(values)
    if np.issubdtype(values.dtype, np.integer) or values.dtype == bool:
        if values.size == 0 or (values.min() >= -128 and values.max() <= 127):
            return values.astype(np.int8)
        return values
    finite = np.isfinite(values)
    if finite.all() and np.array_equal(values, np.round(values)) and values.min() >= -128 and values.max() <= 127:
        return values.astype(np.int8)
    return values


def _on_time_base(times: np.ndarray, t: np.ndarray, seen: dict[int, tuple[np.ndarray, bool]]) -> bool:
    """Whether a channel's ``times`` are the capture's time base ``t`` (s), each array compared
    once: the channels of one channel group share their time stamps (one array). ``seen`` holds
    the arrays compared (kept alive, so that an id is never another array's) and their answers."""
    known = seen.get(id(times))
    if known is None:
        known = seen[id(times)] = (times, len(times) == len(t) and np.array_equal(times, t))
    return known[1]


def assemble(
    columns: dict[str, Column],
    metadata: dict,
    truth: dict,
    source: str,
) -> Capture:
    """One :class:`Capture` from canonical, converted columns.

    Parameters
    ----------
    columns : dict[str, Column]
        Canonical name -> column in canonical units. Either all share the rows of a ``t``
        column (CSV), or each has its own ``times`` and the ``torque`` time base becomes the
        capture's; samples outside the span that every sampled channel covers are dropped
        (event channels hold their last level to the end).
    metadata, truth : dict
        Capture metadata and simulator truth.
    source : str
        File name for error messages and ``Capture.source``.
    """
    events: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if "t" in columns:
        t = np.asarray(columns["t"].values, dtype=np.float64)
        channels = {name: c.values for name, c in columns.items() if name != "t"}
    else:
        if "torque" not in columns:
            raise InputError(source, "torque", "required channel missing (its time base becomes the capture's)")
        t = np.asarray(columns["torque"].times, dtype=np.float64)
        if len(t) < 2:
            raise InputError(source, "torque", f"{len(t)} samples; a capture needs at least 2")
        lo = max(float(c.times[0]) for c in columns.values() if len(c.times))
        # the torque channel's group may read as change events (integral values): then it alone bounds the span
        hi = min((float(c.times[-1]) for c in columns.values() if not c.events and len(c.times)), default=float(t[-1]))
        keep = (t >= lo) & (t <= hi)
        kept = int(keep.sum())
        if kept < 2:
            raise InputError(source, "t", f"the channels' time bases overlap on {kept} torque samples")
        t = t.copy() if kept == len(t) else t[keep]  # the rule: every sample kept (no gather)
        channels = {}
        on_t: dict[int, tuple[np.ndarray, bool]] = {}
        for name, c in columns.items():
            times = np.asarray(c.times, dtype=np.float64)
            same = _on_time_base(times, t, on_t)
            if name in DIGITAL_CHANNELS:
                if c.events:
                    events[name] = change_events(times, _as_digital(c.values))
                if same:
                    channels[name] = c.values
                else:
                    channels[name] = zoh(times, c.values, t)
            elif same:
                channels[name] = c.values
            else:
                if np.any(np.diff(times) <= 0):
                    raise InputError(source, name, "time base of its channel group not strictly increasing")
                channels[name] = np.interp(t, times, np.asarray(c.values, dtype=np.float64))
    for name in DIGITAL_CHANNELS:
        if name in channels:
            channels[name] = _as_digital(channels[name])
        if name in events:
            times, levels = events[name]
            inside = (times > t[0]) & (times <= t[-1])
            events[name] = (times[inside], _as_digital(levels[inside]))
    for name in list(channels):
        if name not in DIGITAL_CHANNELS:
            channels[name] = np.asarray(channels[name], dtype=np.float64)
    order = {name: k for k, name in enumerate(CANONICAL_CHANNELS)}
    channels = {name: channels[name] for name in sorted(channels, key=lambda n: order.get(n, len(order)))}
    return Capture(t=t, channels=channels, metadata=metadata, truth=truth, events=events, source=source)
