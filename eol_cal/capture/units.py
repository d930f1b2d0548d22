"""Conversion of channel values to the canonical units of capture format v1, with pint.

One :class:`pint.UnitRegistry` serves the whole process (building it costs about half a second,
so it is built lazily on the first conversion that needs it and cached).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.capture.data import CANONICAL_CHANNELS, DIGITAL_CHANNELS
from eol_cal.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import pint

#: longest unit text taken (``N*m``, ``1/min``, ``mV/deg``: < 20 characters)
MAX_UNIT_CHARS = 64

#: unit spellings DAQ exports use for dimensionless digital lines
_DIMENSIONLESS_SPELLINGS = frozenset({"", "1", "-", "dimensionless"})

# DAQ exports write torque as "Nm"; pint's default registry reads that as "number_meter"
# (a paper-weight unit), which would turn a torque into a wrong dimension. These three
# definitions replace that reading; nothing else in the default registry changes.
_EXTRA_DEFINITIONS = (
    "Nm = newton * meter",
    "Ncm = newton * centimeter",
    "Nmm = newton * millimeter",
)


@functools.lru_cache(maxsize=1)
def unit_registry() -> pint.UnitRegistry:
    """The process-wide pint registry (cached)."""
    import pint

    ureg: pint.UnitRegistry = pint.UnitRegistry(on_redefinition="ignore")
    for definition in _EXTRA_DEFINITIONS:
        ureg.define(definition)
    return ureg


@functools.lru_cache(maxsize=256)
def _parse_unit(unit: str) -> pint.Unit:
    return unit_registry().Unit(unit)


def parse_unit(unit: str, file: str | None, channel: str | None) -> pint.Unit:
    """Parse a unit string, refusing unknown units with an :class:`InputError`.

    Parameters
    ----------
    unit : str
        Unit in pint syntax (``"N*cm"``, ``"mA"``, ``"rad/s"``, ``"degF"``, ...).
    file, channel : str or None
        Where the unit came from, for the error message.
    """
    if len(unit.strip()) > MAX_UNIT_CHARS:  # pint's parser is not linear in the text; no real unit is this long
        raise InputError(file, channel, f"unit of {len(unit.strip())} characters ({unit.strip()[:24]!r}...); a unit "
                                        f"has at most {MAX_UNIT_CHARS}")
    try:
        return _parse_unit(unit.strip())
    except Exception as exc:  # noqa: BLE001 - pint raises several unrelated types for bad strings
        raise InputError(file, channel, f"unknown unit {unit!r} ({exc.__class__.__name__}: {exc})") from None


def check_unit(channel: str, unit: str | None, file: str | None, label: str | None = None) -> None:
    """Refuse a unit that cannot be converted to ``channel``'s canonical unit (no data needed)."""
    to_canonical(channel, np.zeros(1), unit, file, label)


def to_canonical(
    channel: str, values: np.ndarray, unit: str | None, file: str | None, label: str | None = None
) -> np.ndarray:
    """Convert ``values`` given in ``unit`` to the canonical unit of ``channel``.

    Parameters
    ----------
    channel : str
        Canonical channel name (a key of :data:`CANONICAL_CHANNELS`).
    values : ndarray
        Samples in ``unit``.
    unit : str or None
        Source unit in pint syntax; ``None`` means the values are already canonical.
    file : str or None
        Source file, for error messages.
    label : str, optional
        Field named in error messages (default ``channel``), e.g. ``"torque (column 'Drehmoment')"``.

    Returns
    -------
    ndarray
        float64 samples in the canonical unit (digital channels are returned unchanged).

    Notes
    -----
    Offset units (``degF``, ``K``) convert correctly because the quantity is built from the
    array, not multiplied by the unit. A ``speed`` given without an angle (``1/min``, ``Hz``)
    counts revolutions per time, as every DAQ means it; pint alone would count radians.
    """
    field = label or channel
    canonical = CANONICAL_CHANNELS.get(channel)
    if canonical is None:
        raise InputError(file, channel, f"not a canonical channel; known: {', '.join(CANONICAL_CHANNELS)}")
    if unit is None or unit.strip() == canonical:
        return values
    unit = unit.strip()
    if channel in DIGITAL_CHANNELS:
        if unit in _DIMENSIONLESS_SPELLINGS:
            return values
        raise InputError(file, field, f"unit {unit!r} given for a digital channel; it takes no unit (0/1 levels, hall 0..7)")
    if canonical == "1" and unit in _DIMENSIONLESS_SPELLINGS:
        return values
    source = parse_unit(unit, file, field)
    ureg = unit_registry()
    try:
        quantity = ureg.Quantity(np.asarray(values, dtype=np.float64), source)
        if channel == "speed" and "radian" not in ureg.get_root_units(source)[1]._units:
            # an offset unit (degC) fails here already: it cannot be multiplied by a revolution
            quantity = quantity * ureg.revolution
        return np.asarray(quantity.to(canonical).magnitude, dtype=np.float64)
    except Exception as exc:  # noqa: BLE001 - DimensionalityError, OffsetUnitCalculusError, ...
        raise InputError(
            file, field, f"unit {unit!r} cannot be converted to {canonical!r} ({exc.__class__.__name__})"
        ) from None
