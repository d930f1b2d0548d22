"""Torque-ripple compensator: table generation and the firmware's per-tick evaluation.

Ripple model (firmware contract section 2, seed eq. 17 with phases and a cogging term)::

    T(theta, i_qo) = T_avg - c6*sin(6*theta + phase_c6) - k6*i_qo*sin(6*theta + phase_k6)
                     - sum_h [c_h*sin(h*theta + phase_c_h) + k_h*i_qo*sin(h*theta + phase_k_h)]

with h the higher multiples of 6 (12, 18, ...). The compensating current cancels it (seed eq. 20,
``i_q_ref = i_qo + i_qc``)::

    i_qc = (c6*sin(6θ+phase_c6) + k6*i_qo*sin(6θ+phase_k6) + sum_h ...) / kt

:func:`i_qc` is the firmware's evaluation, binary32 with a fixed order of operations; the exact
arithmetic is written out in ``firmware_params/COMPENSATOR.md`` and ported in
``firmware_params/c/eol_comp.c``. It uses only ``xp`` array operations and no Python branch on
values, so it runs bit-exactly under numpy (golden vectors) and traces under ``jax.numpy``
inside ``jit``/``vmap``/``lax.scan`` (the plant).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from eol_cal.errors import InputError
from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware.block import FLAG_COMP_ENABLE, TABLE_LEN_MAX, TABLE_LEN_MIN, ParamBlock, table_len_ok

K_6_OVER_2PI = np.float32(6.0 / (2.0 * math.pi))
"""6/(2*pi) rounded to binary32 (bit pattern 0x3f747645): table entries per rad of electrical angle, per N."""

Harmonic = tuple[int, float, float, float, float]
"""(order, c, phase_c, k, phase_k): order a multiple of 6 above 6; c in N*m, k in N*m/A, phases in rad."""


def _check_harmonics(harmonics: Sequence[Harmonic], N: int | None) -> None:
    for h in harmonics:
        if len(h) != 5:
            raise InputError(None, "harmonics", f"{h!r}: needs (order, c, phase_c, k, phase_k)")
        order = h[0]
        if int(order) != order or order < 12 or order % 6:
            raise InputError(None, "harmonics", f"order {order}: needs a multiple of 6 from 12")
        if N is not None and order // 6 >= N // 2:
            raise InputError(None, "harmonics", f"order {order} is not resolved by a {N}-entry table")


def ripple_parts(theta: Array, c6: float, phase_c6: float, k6: float, phase_k6: float, kt: float,
                 harmonics: Sequence[Harmonic] = ()) -> tuple[np.ndarray, np.ndarray]:
    """The analytic compensating current's two parts at electrical angle ``theta`` (float64).

    Parameters
    ----------
    theta : array_like
        Electrical angle (rad).
    c6, phase_c6 : float
        Load-independent 6th-harmonic ripple (N*m) and its phase (rad).
    k6, phase_k6 : float
        Load-proportional 6th-harmonic ripple (N*m/A) and its phase (rad).
    kt : float
        Torque constant (N*m/A).
    harmonics : sequence of (order, c, phase_c, k, phase_k)
        Higher multiples of 6, same units as the 6th.

    Returns
    -------
    i_const : ndarray
        Load-independent part of i_qc (A).
    i_per_amp : ndarray
        Part of i_qc per ampere of i_qo (A/A); ``i_qc = i_const + i_qo * i_per_amp``.
    """
    if not kt > 0:
        raise InputError(None, "kt", f"{kt}: must be > 0")
    _check_harmonics(harmonics, None)
    theta = np.asarray(theta, dtype=np.float64)
    i_const = c6 * np.sin(6.0 * theta + phase_c6)
    i_per_amp = k6 * np.sin(6.0 * theta + phase_k6)
    for order, c, phase_c, k, phase_k in harmonics:
        i_const = i_const + c * np.sin(order * theta + phase_c)
        i_per_amp = i_per_amp + k * np.sin(order * theta + phase_k)
    return i_const / kt, i_per_amp / kt


def ripple_i_qc(theta: Array, i_qo: Array, c6: float, phase_c6: float, k6: float, phase_k6: float,
                kt: float, harmonics: Sequence[Harmonic] = ()) -> np.ndarray:
    """Analytic i_qc (A, float64) that cancels the ripple at angle ``theta`` (rad) and ``i_qo`` (A)."""
    i_const, i_per_amp = ripple_parts(theta, c6, phase_c6, k6, phase_k6, kt, harmonics)
    return i_const + np.asarray(i_qo, dtype=np.float64) * i_per_amp


def make_tables(c6: float, phase_c6: float, k6: float, phase_k6: float, kt: float, N: int,
                harmonics: Sequence[Harmonic] = ()) -> tuple[np.ndarray, np.ndarray]:
    """The block's two tables for one period of the 6th harmonic.

    Entry ``j`` is at ``6*theta_j = 2*pi*j/N``; values are computed in float64 and rounded once
    to binary32.

    Parameters
    ----------
    c6, phase_c6, k6, phase_k6, kt, harmonics
        As in :func:`ripple_parts` (N*m, rad, N*m/A, rad, N*m/A).
    N : int
        Table length, a power of two from 16 to 1024.

    Returns
    -------
    table_const : ndarray of float32, shape (N,)
        Load-independent part of i_qc (A).
    table_per_amp : ndarray of float32, shape (N,)
        Part of i_qc per ampere of i_qo (A/A).
    """
    N = int(N)
    if not table_len_ok(N):
        raise InputError(None, "table_len", f"{N}: needs a power of two in {TABLE_LEN_MIN}..{TABLE_LEN_MAX}")
    _check_harmonics(harmonics, N)
    theta_j = 2.0 * math.pi * np.arange(N) / (6.0 * N)
    i_const, i_per_amp = ripple_parts(theta_j, c6, phase_c6, k6, phase_k6, kt, harmonics)
    return i_const.astype(np.float32), i_per_amp.astype(np.float32)


@functools.lru_cache(maxsize=16)
def _lerp_consts(n: int) -> tuple[np.float32, np.float32, np.float32]:
    """``(1/N, N, 1)`` in binary32 for tables of ``n`` entries: built once, not every tick."""
    return np.float32(1.0 / n), np.float32(n), np.float32(1.0)


def table_sum(x: Array, i_qo: Array, table_const: Array, table_per_amp: Array, scale: Array,
              xp: ArrayModule = np) -> Array:
    """The two tables read at angle ``x`` and summed, before the clamp (binary32, fixed order).

    ``v = x * scale`` is the angle in table entries; it is reduced into [0, N) and the tables are
    interpolated linearly: the steps from ``v`` to ``s`` of COMPENSATOR.md, shared by the
    6th-harmonic tables (``x`` = the lead angle ``t``, ``scale`` = N * 6/(2*pi)) and the mechanical
    ones of layout 2 (firmware_params/MECH.md).

    Parameters
    ----------
    x : array_like
        Angle (rad), any finite value.
    i_qo : array_like
        Nominal q current (A), signed.
    table_const, table_per_amp : array_like, shape (N,)
        Tables (A, A/A); N a power of two.
    scale : float
        Table entries per rad of ``x`` (binary32).

    Returns
    -------
    s : array of float32
        ``lerp(table_const) + i_qo * lerp(table_per_amp)`` (A).
    """
    f32 = xp.float32
    tc = xp.asarray(table_const, dtype=f32)
    tp = xp.asarray(table_per_amp, dtype=f32)
    n = int(tc.shape[0])  # static: the table shape, never a traced value
    if n & (n - 1) or n < 2 or tp.shape != tc.shape:
        raise InputError(None, "table_len", f"tables of shape {tc.shape}, {tp.shape}: need equal power-of-two lengths")
    recip_n, n_f, one = _lerp_consts(n)
    v = xp.asarray(x, dtype=f32) * f32(scale)
    q = xp.floor(v * recip_n)
    u = v - q * n_f
    g = xp.floor(u)
    f = u - g
    j = xp.bitwise_and(g.astype(xp.int32), n - 1)
    j1 = xp.bitwise_and(j + 1, n - 1)
    w = one - f
    lc = w * xp.take(tc, j) + f * xp.take(tc, j1)
    lp = w * xp.take(tp, j) + f * xp.take(tp, j1)
    return lc + xp.asarray(i_qo, dtype=f32) * lp


def lead_angle(theta_hat: Array, omega_hat: Array, lead_s: Array, xp: ArrayModule = np) -> Array:
    """The angle the tables are read at: ``theta_hat + omega_hat * lead_s`` (rad, binary32, two roundings)."""
    f32 = xp.float32
    a = xp.asarray(omega_hat, dtype=f32) * xp.asarray(lead_s, dtype=f32)
    return xp.asarray(theta_hat, dtype=f32) + a


def i_qc(theta_hat: Array, omega_hat: Array, i_qo: Array, table_const: Array, table_per_amp: Array,
         lead_s: Array, iqc_limit: Array, xp: ArrayModule = np, mech_on: Array | None = None,
         mech_sum: Array | None = None) -> Array:
    """Compensating q current as the firmware computes it each tick (binary32, fixed order).

    Parameters
    ----------
    theta_hat : array_like
        Estimated electrical angle (rad), any finite value (negative, beyond 2*pi).
    omega_hat : array_like
        Estimated electrical speed (rad/s), signed.
    i_qo : array_like
        Nominal q current (A), signed.
    table_const, table_per_amp : array_like, shape (N,)
        The block's tables (A, A/A); N a power of two.
    lead_s : array_like
        Look-up lead (s).
    iqc_limit : array_like
        Clamp of abs(i_qc) (A), >= 0.
    xp : module
        ``numpy`` or ``jax.numpy``.
    mech_on, mech_sum : array_like, optional
        Layout 2 (contract revision 1.2): where ``mech_on`` is true, the mechanical-order current
        ``mech_sum`` (A, :func:`eol_cal.firmware.mech.mech_sum`) is added before the clamp:
        ``s = s + mech_sum``. Elsewhere (and without them) the result is layout 1's, bit for bit.

    Returns
    -------
    i_qc : array of float32
        Compensating current (A), broadcast over the inputs.

    Notes
    -----
    Every step rounds to binary32 (see COMPENSATOR.md)::

        a = omega_hat * lead_s;  t = theta_hat + a;  v = t * S        S = N * 0x3f747645 (exact)
        q = floor(v * R);  u = v - q * Nf                             R = 1/N, Nf = N (exact)
        g = floor(u);  f = u - g;  j = int(g) & (N-1);  j1 = (j+1) & (N-1)
        lc = (1-f)*tc[j] + f*tc[j1];  lp = (1-f)*tp[j] + f*tp[j1]     products first, then the sum
        s = lc + i_qo*lp;  i_qc = s > L ? L : (s < -L ? -L : s)

    ``u`` is v reduced into [0, N]: the steps before its rounding are exact, so u < N except when
    the exact value lies within half an ulp below N (v slightly negative), where it rounds to N
    and the mask maps j = N to entry 0 with f = 0, the same point.
    """
    f32 = xp.float32
    n = int(xp.asarray(table_const).shape[0])  # static: the table shape
    scale = f32(np.float32(n) * K_6_OVER_2PI)
    limit = xp.asarray(iqc_limit, dtype=f32)
    t = lead_angle(theta_hat, omega_hat, lead_s, xp)
    s = table_sum(t, i_qo, table_const, table_per_amp, scale, xp)
    if mech_on is not None:
        s = xp.where(mech_on, s + xp.asarray(mech_sum, dtype=f32), s)
    return xp.where(s > limit, limit, xp.where(s < -limit, -limit, s))


def block_i_qc(block: ParamBlock, theta_hat: Array, omega_hat: Array, i_qo: Array, xp: ArrayModule = np) -> Array:
    """:func:`i_qc` with a block's tables, lead and limit; zero when ``COMP_ENABLE`` is clear (A)."""
    out = i_qc(theta_hat, omega_hat, i_qo, block.table_const, block.table_per_amp,
               block.lead_s, block.iqc_limit, xp=xp)
    if block.flags & FLAG_COMP_ENABLE:  # a static block field, not a traced value
        return out
    return xp.zeros_like(out)
