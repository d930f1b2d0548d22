"""Angle wrapping: the one rule for bringing an angle (rad) back into one turn.

Every float64 angle in the library (phases of fitted harmonics, hall tables, residuals, the
plant's rotor angle) is wrapped here. The firmware model keeps its own binary32 reduction
(:func:`eol_cal.firmware.estimator.wrap`): it specifies, operation by operation, what the C port
computes, which is a contract of its own and not a convenience.

Both functions take ``xp`` (``numpy`` by default, ``jax.numpy`` inside traced code) so the
plant's scan and the analysis use the same rule.
"""

from __future__ import annotations

import math

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule

TWO_PI = 2.0 * math.pi


def wrap_2pi(x: Array, xp: ArrayModule = np) -> Array:
    """Angle ``x`` (rad, scalar or array) reduced into [0, 2*pi) (rad); an ``x`` a rounding
    error below 0 may come back as 2*pi itself.

    Parameters
    ----------
    x : float or array
        Angle (rad).
    xp : module
        Array namespace (``numpy`` or ``jax.numpy``).
    """
    # floor, not xp.mod: the same result here, and fewer operations inside the plant's scan
    return x - TWO_PI * xp.floor(x / TWO_PI)


def wrap_pi(x: Array, xp: ArrayModule = np) -> Array:
    """Angle ``x`` (rad, scalar or array) reduced into (-pi, pi] (rad): the signed difference
    of two angles, or a phase as the fit reports it. An angle already in range comes back
    unchanged, bit for bit."""
    return x - TWO_PI * xp.ceil((x - math.pi) / TWO_PI)
