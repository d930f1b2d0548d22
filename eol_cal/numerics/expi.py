"""exp(i x) of a long real array at 2.7x numpy's speed, and complex powers into given buffers: the
fit's columns (:func:`eol_cal.analysis.fit.model.design_rows`) are powers of one exp(i theta) a sample."""

from __future__ import annotations

import decimal
import functools
import math

import numpy as np


#: :func:`exp_i`'s table: exp(2 pi i j / 2^bits) for j < 2^bits; the rest of an angle, at most
#: pi / 2^bits (3e-3 rad), by its short series
_EXP_BITS = 10


@functools.cache
def _exp_table() -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """(table, 2^bits / 2 pi, the table's step 2 pi / 2^bits as three doubles of 26, 26 and 53 bits:
    ``k`` times each of the first two is exact for ``|k| < 2^27``, angles up to 8e5 rad)."""
    n = 1 << _EXP_BITS
    with decimal.localcontext() as ctx:
        ctx.prec = 60
        tau = decimal.Decimal("6.28318530717958647692528676655900576839433879875021164194988918")
        step = tau / n
        parts, rest = [], step
        for bits in (26, 26):
            mant, ex = math.frexp(float(rest))
            parts.append(math.ldexp(math.floor(mant * 2**bits) / 2**bits, ex))
            rest -= decimal.Decimal(parts[-1])
        parts.append(float(rest))
        table = np.empty(n, dtype=complex)
        for j in range(n):
            # cos/sin of the nearest double to the angle, corrected by its rounding (d, below 1e-16 rad)
            a = j * step
            af = float(a)
            d = float(a - decimal.Decimal(af))
            c, s = math.cos(af), math.sin(af)
            table[j] = complex(c - d * s, s + d * c)
        return table, float(n / tau), (parts[0], parts[1], parts[2])


def exp_i(x: np.ndarray, out: np.ndarray, w: np.ndarray, scratch1: np.ndarray, scratch2: np.ndarray) -> np.ndarray:
    """``out = exp(i x)`` for real ``x`` (rad): a table's angle times the short series of the rest.

    Within ~1 ulp of numpy's ``np.exp(1j * x)`` (glibc's ``sincos`` per sample) at 2.7x its speed,
    the compression's largest single cost: ``x = 2 pi k / 2^bits + r`` (the step in three parts,
    exact), ``exp(i r) = 1 + (cos r - 1) + i sin r`` by the series to r^5 (|r| <= 3e-3: the next
    terms under 1e-18), ``out = T_k + T_k (exp(i r) - 1)`` (the small product's rounding stays small).
    ``w``, ``scratch1``, ``scratch2``: complex work arrays of ``len(x)``.
    """
    table, inv_step, (c1, c2, c3) = _exp_table()
    n = len(x)
    k, r = scratch1.view(np.float64)[:n], scratch1.view(np.float64)[n : 2 * n]
    u, idx = scratch2.view(np.float64)[:n], scratch2.view(np.int64)[n : 2 * n]
    np.multiply(x, inv_step, out=k)
    np.rint(k, out=k)
    np.multiply(k, c1, out=r)
    np.subtract(x, r, out=r)
    np.multiply(k, c2, out=u)
    r -= u
    np.multiply(k, c3, out=u)
    r -= u
    np.copyto(idx, k, casting="unsafe")
    idx &= (1 << _EXP_BITS) - 1
    np.take(table, idx, out=out, mode="clip")  # in range: "raise" would buffer the output
    r2 = k  # k is no longer needed
    np.multiply(r, r, out=r2)
    # w = (cos r - 1) + i sin r
    np.multiply(r2, 1.0 / 720.0, out=u)
    u -= 1.0 / 24.0
    u *= r2
    u += 0.5
    np.multiply(u, r2, out=w.real)
    np.negative(w.real, out=w.real)
    np.multiply(r2, 1.0 / 120.0, out=u)
    u -= 1.0 / 6.0
    u *= r2
    u += 1.0
    np.multiply(u, r, out=w.imag)
    np.multiply(out, w, out=w)
    np.add(out, w, out=out)
    return out


def cpow_into(e: np.ndarray, n: int, out: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """``out = e**n`` (complex, ``n`` >= 1) by repeated squaring in ``tmp``; ``e`` is left as it is.
    Returns ``out``."""
    first, src = True, e
    while n:
        if n & 1:
            if first:
                np.copyto(out, src)
                first = False
            else:
                np.multiply(out, src, out=out)
        n >>= 1
        if n:
            np.multiply(src, src, out=tmp)
            src = tmp
    return out


def step_powers(step: np.ndarray, top: int, out: np.ndarray | None = None) -> np.ndarray:
    """``step ** j`` for ``j = 0..top`` (top + 1, n), complex, each power the one before times ``step``
    (a segment's noise bins: :func:`eol_cal.analysis.fit.model.bin_steps`,
    :func:`eol_cal.analysis.fit.noise_pass.bin_powers`). ``out``: an array of that shape to fill
    (default: a new one). Returns the powers."""
    powers = np.empty((top + 1, len(step)), dtype=complex) if out is None else out
    powers[0] = 1.0
    for j in range(1, top + 1):
        np.multiply(powers[j - 1], step, out=powers[j])
    return powers
