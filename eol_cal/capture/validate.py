"""Refusal of captures that cannot be trusted (capture format v1, "Bad input").

Every check raises :class:`~eol_cal.errors.InputError` with the capture's source file, the
channel (or metadata key) at fault and the reason, so that nothing is analysed silently.

"Too short" is defined on the hall signal, which is absolute: a capture holds a full
electrical revolution when its hall state changes at least 7 times (the first and the 7th
change lie on the same hall edge, one electrical revolution apart, whatever the direction) and
all six valid states occur. The encoder must also show at least ``ceil(2*N_enc/P)`` rising
edges of channel A, the number of A pulses in one electrical revolution.
"""

from __future__ import annotations

import math

import numpy as np

from eol_cal.capture.ecu_state import trace_of
from eol_cal.capture.metadata import METADATA_TYPES
from eol_cal.capture.data import (
    CANONICAL_CHANNELS,
    DIGITAL_CHANNELS,
    REQUIRED_METADATA,
    TRUTH_PREFIX,
    Capture,
)
from eol_cal.errors import InputError

#: hall state changes needed to span one full electrical revolution
MIN_HALL_CHANGES = 7

_DIGITAL_RANGE = {"enc_a": (0, 1), "enc_b": (0, 1), "hall": (0, 7)}

#: physical bounds of the analog channels, canonical units (docs/capture-format.md, "Bad input"):
#: far beyond any EPS motor on an end-of-line bench, far below what overflows a float64 sum or
#: square in an analysis (a 1e308 N*m sample passed the finite check and crashed the fit)
PHYSICAL_BOUNDS: dict[str, tuple[float, float]] = {
    "t": (-1e10, 1e10),            # s (epoch-based time stamps fit)
    "torque": (-1e3, 1e3),         # N*m
    "iq_ref": (-1e4, 1e4),         # A
    "iqc": (-1e4, 1e4),
    "iq": (-1e4, 1e4),
    "id": (-1e4, 1e4),
    "ia": (-1e4, 1e4),
    "ib": (-1e4, 1e4),
    "ic": (-1e4, 1e4),
    "speed": (-1e5, 1e5),          # rpm
    "temp": (-273.15, 1e3),        # degC
}
#: bounds of numeric metadata (poles, encoder_ppr and kt must also be positive)
METADATA_BOUNDS: dict[str, tuple[float, float]] = {
    "poles": (2, 1000),
    "encoder_ppr": (1, 1_000_000),
    "kt": (0.0, 100.0),            # N*m/A
    "iq_ref": (-1e4, 1e4),         # A
}


def _at(t: np.ndarray, index: int) -> str:
    return f"t = {float(t[index]):.6g} s (sample {index})"


def _first(bad: np.ndarray) -> tuple[int, int] | None:
    """(index of the first True, number of True) or None when all are False."""
    count = int(np.count_nonzero(bad))
    return (int(np.argmax(bad)), count) if count else None


def _within(values: np.ndarray, lo: float, hi: float) -> bool:
    """Every value within ``[lo, hi]``, from two reductions (the rule; a refusal looks for the
    first sample outside). False for no values and for a NaN, which the caller's full check
    then judges as before."""
    return bool(values.size) and bool(lo <= values.min()) and bool(values.max() <= hi)


def check_metadata(capture: Capture) -> None:
    """Required metadata present and of the right type and range; no ``truth.*`` leak."""
    src, meta = capture.source, capture.metadata
    for key in meta:
        if key.startswith(TRUTH_PREFIX):
            raise InputError(src, key, "simulator truth key found in metadata; truth.* belongs in Capture.truth")
    for key in REQUIRED_METADATA:
        if key not in meta or (isinstance(value := meta[key], str) and not value.strip()):
            raise InputError(src, key, "required metadata missing")
    for key, want in METADATA_TYPES.items():
        if key not in meta:
            continue
        value = meta[key]
        if want is int and (isinstance(value, bool) or not isinstance(value, int)):
            raise InputError(src, key, f"must be an integer, got {value!r}")
        if want is float and (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)):
            raise InputError(src, key, f"must be a finite number, got {value!r}")
    if meta["poles"] <= 0 or meta["poles"] % 2:
        raise InputError(src, "poles", f"must be a positive even integer, got {meta['poles']}")
    if meta["encoder_ppr"] <= 0:
        raise InputError(src, "encoder_ppr", f"must be a positive integer, got {meta['encoder_ppr']}")
    if "kt" in meta and meta["kt"] <= 0:
        raise InputError(src, "kt", f"must be positive, got {meta['kt']}")
    for key, (lo, hi) in METADATA_BOUNDS.items():
        if key in meta and not lo <= meta[key] <= hi:
            raise InputError(src, key, f"{meta[key]!r} outside the physical bounds {lo:g}..{hi:g}")
    trace_of(meta, src)  # a partial or malformed ECU-state record is refused here, before any analysis


def check_channels_present(capture: Capture) -> None:
    """Canonical names only, the required channels present, every channel as long as ``t``."""
    src = capture.source
    for name in capture.channels:
        if name == "t" or name not in CANONICAL_CHANNELS:
            raise InputError(src, name, f"not a canonical channel name; known: {', '.join(CANONICAL_CHANNELS)}")
    t = np.asarray(capture.t)
    if t.ndim != 1 or len(t) < 2:
        raise InputError(src, "t", f"need a 1-D time base with at least 2 samples, got shape {t.shape}")
    for name in ("torque", "enc_a", "hall"):
        if name not in capture.channels:
            raise InputError(src, name, "required channel missing")
    if "iq_ref" not in capture.channels and "iq_ref" not in capture.metadata:
        raise InputError(src, "iq_ref", "required channel missing (give the channel, or metadata iq_ref when constant)")
    for name, values in capture.channels.items():
        if np.shape(values) != t.shape:
            raise InputError(src, name, f"has {np.size(values)} samples but t has {len(t)}")


def check_finite(capture: Capture) -> None:
    """No NaN or infinity in ``t`` or any channel."""
    for name in ("t", *capture.channels):
        values = np.asarray(capture[name])
        if not np.issubdtype(values.dtype, np.number):
            raise InputError(capture.source, name, f"non-numeric values (dtype {values.dtype})")
        if values.dtype.kind in "iu":  # integers are finite (digital channels)
            continue
        finite = np.isfinite(values)
        if finite.all():  # the rule; the first and the count only for a refusal
            continue
        found = _first(~finite)
        if found:
            first, count = found
            kind = "NaN" if np.isnan(values[first]) else "infinite value"
            raise InputError(capture.source, name, f"{kind} at {_at(capture.t, first)}; {count} non-finite samples in all")


def check_bounds(capture: Capture) -> None:
    """Every analog value (and ``t``) within :data:`PHYSICAL_BOUNDS`: what passes is safe to sum,
    square and fit (no overflow to infinity downstream)."""
    for name in ("t", *capture.channels):
        if name not in PHYSICAL_BOUNDS:
            continue
        lo, hi = PHYSICAL_BOUNDS[name]
        values = np.asarray(capture[name], dtype=np.float64)
        if _within(values, lo, hi):
            continue
        found = _first((values < lo) | (values > hi))
        if found:
            first, count = found
            unit = CANONICAL_CHANNELS[name]
            raise InputError(
                capture.source,
                name,
                f"value {values[first]:.6g} {unit} at {_at(capture.t, first)} outside the physical bounds "
                f"{lo:g}..{hi:g} {unit}; {count} such samples",
            )


def check_time(capture: Capture) -> None:
    """Strictly increasing sample times."""
    found = _first(np.diff(capture.t) <= 0)
    if found:
        first, count = found
        raise InputError(
            capture.source,
            "t",
            f"time not strictly increasing: t[{first + 1}] = {float(capture.t[first + 1]):.9g} s after "
            f"t[{first}] = {float(capture.t[first]):.9g} s; {count} such steps",
        )


def check_digital(capture: Capture) -> None:
    """Digital channels integral and in range; hall states 0 and 7 refused as sensor faults."""
    for name in DIGITAL_CHANNELS:
        if name not in capture.channels:
            continue
        values = np.asarray(capture.channels[name])
        lo, hi = _DIGITAL_RANGE[name]
        if values.dtype.kind in "iu" and _within(values, lo, hi):  # integers: round() keeps them
            continue
        found = _first((values < lo) | (values > hi) | (values != np.round(values)))
        if found:
            first, count = found
            raise InputError(
                capture.source,
                name,
                f"value {values[first].item()!r} at {_at(capture.t, first)} outside {lo}..{hi} (integers); "
                f"{count} such samples",
            )
    hall = np.asarray(capture.channels["hall"])
    found = _first((hall == 0) | (hall == 7))
    if found:
        first, count = found
        raise InputError(
            capture.source,
            "hall",
            f"hall state {int(hall[first])} (a sensor fault; valid states are 1..6) at {_at(capture.t, first)}; "
            f"{count} faulty samples in all",
        )


def check_events(capture: Capture) -> None:
    """Recorded change events: known digital channels, sorted times, levels in range."""
    for name, (times, levels) in capture.events.items():
        if name not in DIGITAL_CHANNELS:
            raise InputError(capture.source, name, "events are kept for digital channels only")
        times, levels = np.asarray(times), np.asarray(levels)
        lo, hi = _DIGITAL_RANGE[name]
        if times.shape != levels.shape or times.ndim != 1:
            raise InputError(capture.source, name, "event times and levels differ in shape")
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
            raise InputError(capture.source, name, "event times not finite and sorted")
        if np.any((levels < lo) | (levels > hi)):
            raise InputError(capture.source, name, f"event level outside {lo}..{hi}")


def states_seen(hall: np.ndarray) -> list[int]:
    """The distinct hall states of a sample sequence (each taken as ``int``), ascending.

    Not ``np.unique``: it imports numpy.ma, 0.1-0.2 s of ``eol-cal capture info``.
    """
    states = np.asarray(hall).astype(np.int64)
    if not len(states):
        return []
    low, high = int(states.min()), int(states.max())
    if high - low > 4096:  # not a hall sequence: no table that wide
        return sorted({int(s) for s in states.tolist()})
    return (np.flatnonzero(np.bincount(states - low)) + low).tolist()


def hall_changes(hall: np.ndarray) -> int:
    """Number of hall state changes in a sample sequence."""
    return int(np.count_nonzero(np.diff(np.asarray(hall)) != 0))


def rising_edges(level: np.ndarray) -> int:
    """Number of 0 -> 1 transitions of a 0/1 sample sequence."""
    level = np.asarray(level)
    return int(np.count_nonzero((level[1:] > 0) & (level[:-1] == 0)))


def check_activity(capture: Capture) -> None:
    """Encoders toggle, and the capture spans at least one full electrical revolution."""
    src = capture.source
    for name in ("enc_a", "enc_b"):
        if name in capture.channels:
            values = np.asarray(capture.channels[name])
            if np.all(values == values[0]):
                duration = float(capture.t[-1] - capture.t[0])
                raise InputError(
                    src, name, f"encoder never toggles: stuck at {int(values[0])} for the whole {duration:.6g} s"
                )
    hall = np.asarray(capture.channels["hall"])
    changes = hall_changes(hall)
    seen = states_seen(hall)
    if changes < MIN_HALL_CHANGES or len(seen) < 6:
        raise InputError(
            src,
            "hall",
            f"too short to hold a full electrical revolution: {changes} hall state changes "
            f"(need {MIN_HALL_CHANGES}) and states {seen} seen (need all of 1..6)",
        )
    need = math.ceil(2 * capture.encoder_ppr / capture.poles)
    edges = rising_edges(capture.channels["enc_a"])
    if edges < need:
        raise InputError(
            src,
            "enc_a",
            f"too short to hold a full electrical revolution: {edges} rising edges of A, need "
            f"{need} (= 2*N_enc/P with N_enc = {capture.encoder_ppr}, P = {capture.poles})",
        )


def validate(capture: Capture) -> Capture:
    """Refuse a capture that cannot be trusted; return it unchanged when it can.

    Checks, in this order: channel names, presence and lengths; metadata (with its bounds);
    finite values; values within :data:`PHYSICAL_BOUNDS`; strictly increasing time; digital ranges
    and hall faults (states 0 and 7); recorded events;
    encoders that never toggle; at least one full electrical revolution (see module docstring).

    Parameters
    ----------
    capture : Capture
        The capture; ``capture.source`` names the file in error messages.

    Returns
    -------
    Capture
        The same object.

    Raises
    ------
    InputError
        On the first problem found, naming file, channel and reason.
    """
    check_channels_present(capture)
    check_metadata(capture)
    check_finite(capture)
    check_bounds(capture)
    check_time(capture)
    check_digital(capture)
    check_events(capture)
    check_activity(capture)
    return capture
