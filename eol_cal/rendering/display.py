"""One display unit per stored unit: what a person reads in tables, reports, the lot page and CSV.

Records, fit results and limits files keep SI units (k6 in N*m/A, c6 and the fit's RMS in N*m,
phases in rad). A person reads the paper's scale: k6 in mN*m/A, torque ripple terms in mN*m,
phases in degrees. :data:`DISPLAY` is the one table of those conversions; every place that
shows a stored number to a person converts it here (``tests/test_units.py`` checks each factor
against pint, which is not imported here: ``lot stats`` over 100 000 runs would pay its half
second of start-up).
"""

from __future__ import annotations

import math

#: stored unit -> (display unit, factor: display value = factor x stored value); units not listed
#: are shown as stored
DISPLAY: dict[str, tuple[str, float]] = {
    "N*m/A": ("mN*m/A", 1e3),
    "N*m": ("mN*m", 1e3),
    "rad": ("deg", 180.0 / math.pi),
}


def display_unit(unit: str) -> tuple[str, float]:
    """``(display unit, factor)`` of a stored unit."""
    return DISPLAY.get(unit, (unit, 1.0))


def to_display(value: float | None, unit: str) -> float:
    """A stored value in its display unit (None and NaN stay NaN)."""
    if value is None:
        return math.nan
    return float(value) * display_unit(unit)[1]
