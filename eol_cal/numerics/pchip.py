"""Monotone piecewise-cubic (PCHIP) interpolation in numpy alone, bit for bit scipy's.

The angle between encoder edges is interpolated with PCHIP (Fritsch-Carlson derivatives, the
one-sided three-point end rule). ``scipy.interpolate`` costs about 0.45 CPU s to import, most of a
light command's start, for this one interpolant. This module computes what
``scipy.interpolate.PchipInterpolator(x, y, extrapolate=False)`` and its ``derivative()`` compute
(scipy 1.17: the same derivatives, the same Hermite coefficients, the same order of operations in
the evaluation of each local polynomial), so the results are identical to the last bit
(tests/test_numerics_filters.py compares them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _edge_slope(h0: float, h1: float, m0: float, m1: float) -> float:
    """One-sided three-point derivative at an end, kept shape-preserving (Python floats: the same
    IEEE arithmetic as numpy's scalars, without their per-operation cost)."""
    h0, h1, m0, m1 = float(h0), float(h1), float(m0), float(m1)
    d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    if _sign(d) != _sign(m0):
        return 0.0
    if _sign(m0) != _sign(m1) and abs(d) > 3.0 * abs(m0):
        return 3.0 * m0
    return d


def _sign(v: float) -> float:
    """``np.sign`` of a Python float: -1, 0 or +1, NaN for NaN."""
    return v if v != v else float((v > 0) - (v < 0))


def pchip_derivatives(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivatives ``dy/dx`` at the knots (unit of y per unit of x): zero at a local extremum or a
    flat segment, else the weighted harmonic mean of the neighbouring slopes."""
    hk = x[1:] - x[:-1]
    mk = (y[1:] - y[:-1]) / hk
    if len(y) == 2:
        return np.array([mk[0], mk[0]])
    smk = np.sign(mk)
    condition = (smk[1:] != smk[:-1]) | (mk[1:] == 0) | (mk[:-1] == 0)
    w1 = 2 * hk[1:] + hk[:-1]
    w2 = hk[1:] + 2 * hk[:-1]
    with np.errstate(divide="ignore", invalid="ignore"):  # where condition holds: not used
        whmean = (w1 / mk[:-1] + w2 / mk[1:]) / (w1 + w2)
    dk = np.zeros_like(y)
    dk[1:-1][~condition] = 1.0 / whmean[~condition]
    dk[0] = _edge_slope(hk[0], hk[1], mk[0], mk[1])
    dk[-1] = _edge_slope(hk[-1], hk[-2], mk[-1], mk[-2])
    return dk


@dataclass(frozen=True)
class PiecewisePoly:
    """A piecewise polynomial, coefficients of ``(x - x_i)**(k-1-j)`` in row ``j``, on the knots
    ``x``; evaluated inside ``[x[0], x[-1]]`` only (NaN outside), each interval closed on the left,
    the last one on both sides."""

    c: np.ndarray  # (k, len(x) - 1)
    x: np.ndarray

    def __call__(self, xq: np.ndarray | float) -> np.ndarray:
        """Values at ``xq`` (NaN outside the knots' span)."""
        return self.with_slope(xq, slope=False)[0]

    def with_slope(self, xq: np.ndarray | float, slope: bool = True,
                   sorted_inside: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Values and first derivative (:meth:`derivative`'s, bit for bit) at ``xq``, sharing the search
        for the intervals (NaN outside the knots' span; ``None`` for the slope unless asked).

        ``sorted_inside``: the caller knows ``xq`` is increasing and inside the knots' span (a
        capture's samples between its first and last edge): each interval's queries are then one
        run (:func:`sorted_counts`), every coefficient repeated over its run (the values a gather
        by interval gives, without an index per query), and no query is checked for the span."""
        xq = np.asarray(xq, dtype=float)
        flat = xq.reshape(-1)
        k = len(self.c)
        if sorted_inside:
            n = sorted_counts(self.x, flat)
            s = flat - np.repeat(self.x[:-1], n)
            rows = [np.repeat(self.c[j], n) for j in range(k)]
        else:
            i = np.searchsorted(self.x, flat, side="right") - 1
            np.clip(i, 0, len(self.x) - 2, out=i)
            s = flat - self.x[i]
            # one gather per coefficient: contiguous rows (a gather of c.T's rows leaves each column
            # strided, ~1.5x the time of the arithmetic below; the same values either way)
            rows = [self.c[j][i] for j in range(k)]
        res, der = _evaluate(rows, s, slope)
        outside = None if sorted_inside else (flat < self.x[0]) | (flat > self.x[-1])
        if outside is not None and outside.any():
            res[outside] = np.nan
            if der is not None:
                der[outside] = np.nan
        return res.reshape(xq.shape), None if der is None else der.reshape(xq.shape)

    def derivative(self) -> PiecewisePoly:
        """The first derivative (scipy's ``PPoly.derivative``: the coefficients times the powers)."""
        k = len(self.c)
        return PiecewisePoly(self.c[:-1] * np.arange(k - 1, 0, -1, dtype=float)[:, None], self.x)


def _evaluate(rows: list[np.ndarray], s: np.ndarray, slope: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """scipy's evaluate_poly1 at offsets ``s`` from each query's knot, the coefficients ``rows``
    (highest power first, one value a query; the constant row is overwritten by the result):
    the constant term first, then each power of ``s`` times its coefficient; and the first
    derivative alike (``derivative()``'s coefficients, times the powers) when ``slope``. The
    products go through two buffers (the same operations, the same values, no new array each)."""
    k = len(rows)
    res = rows[k - 1]
    der = rows[k - 2] * float(1) if slope and k > 1 else None
    tmp = np.empty_like(s)
    z = s
    for j in range(k - 2, -1, -1):
        res += np.multiply(rows[j], z, out=tmp)
        if der is not None and j > 0:
            np.multiply(rows[j - 1], float(k - j), out=tmp)
            der += np.multiply(tmp, z, out=tmp)
        if j > 0:  # the next power (the last one is not used)
            z = np.multiply(z, s, out=None if z is s else z)
    return res, der


def sorted_counts(x: np.ndarray, xq: np.ndarray) -> np.ndarray:
    """How many of the increasing queries ``xq``, all within ``[x[0], x[-1]]``, fall in each
    interval of the knots ``x`` (the last interval closed on both sides): the run lengths of
    ``clip(searchsorted(x, xq, "right") - 1, 0, len(x) - 2)``, from a search of the few knots among
    the many queries (a capture: ~200 knots, 7000 samples)."""
    at = np.searchsorted(xq, x[:-1], side="left")  # each interval's first query
    return np.diff(at, append=len(xq))


def pchip(x: np.ndarray, y: np.ndarray) -> PiecewisePoly:
    """The PCHIP interpolant of ``y`` (any unit) over strictly increasing ``x``.

    Raises
    ------
    ValueError
        Fewer than two knots, ``x`` not strictly increasing, or a value not finite (as scipy).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.ndim != 1 or len(x) < 2 or y.shape != x.shape:
        raise ValueError("`x` must be 1-dimensional with at least 2 elements, and `y` of its length.")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("`x` and `y` must contain only finite values.")
    dx = np.diff(x)
    if np.any(dx <= 0):
        raise ValueError("`x` must be strictly increasing sequence.")
    dydx = pchip_derivatives(x, y)
    slope = np.diff(y) / dx
    t = (dydx[:-1] + dydx[1:] - 2 * slope) / dx
    c = np.stack((t / dx, (slope - dydx[:-1]) / dx - t, dydx[:-1], y[:-1]))
    return PiecewisePoly(c, x)
