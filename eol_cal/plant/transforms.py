"""Clarke and Park transforms (amplitude-invariant), shared by the plant's models."""

from __future__ import annotations

import math

from eol_cal.numerics.arrays import Array, ArrayModule

_SQRT3_2 = math.sqrt(3.0) / 2.0
_INV_SQRT3 = 1.0 / math.sqrt(3.0)


def dq_to_alphabeta(x_d: Array, x_q: Array, theta: Array, xp: ArrayModule) -> tuple[Array, Array]:
    """Rotate a dq vector at electrical angle ``theta`` (rad) into the stator frame."""
    c, s = xp.cos(theta), xp.sin(theta)
    return c * x_d - s * x_q, s * x_d + c * x_q


def alphabeta_to_dq(x_alpha: Array, x_beta: Array, theta: Array, xp: ArrayModule) -> tuple[Array, Array]:
    """Rotate a stator-frame vector into the dq frame at ``theta`` (rad)."""
    c, s = xp.cos(theta), xp.sin(theta)
    return c * x_alpha + s * x_beta, -s * x_alpha + c * x_beta


def alphabeta_to_abc(x_alpha: Array, x_beta: Array) -> tuple[Array, Array, Array]:
    """Phase quantities from an amplitude-invariant alpha-beta vector."""
    return x_alpha, -0.5 * x_alpha + _SQRT3_2 * x_beta, -0.5 * x_alpha - _SQRT3_2 * x_beta


def abc_to_alphabeta(x_a: Array, x_b: Array, x_c: Array) -> tuple[Array, Array]:
    """Amplitude-invariant Clarke transform (the zero sequence is dropped)."""
    return (2.0 * x_a - x_b - x_c) / 3.0, (x_b - x_c) * _INV_SQRT3
