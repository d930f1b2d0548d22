"""Where a capture holds still enough to be judged: direction pieces, whole revolutions (or 60-degree
units) of the reconstructed angle, and runs of steady units. Shared by the ripple metrics
(:mod:`eol_cal.analysis.metrics`) and the fit's segmentation (:mod:`eol_cal.analysis.fit.capture`)."""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi

#: Electrical speed (rad/s) below which the shaft counts as standing still: an absolute floor, not
#: a fraction of the capture's top speed, so one continuous capture from 60 to 1500 rpm keeps its
#: slow windows (the edge-interpolated speed of a 1500 rpm stretch peaks near 800 rad/s with the
#: encoder's jitter, and 5 % of that took every window below ~125 rpm). 2 rad/s is 6.4 rpm with 3
#: pole pairs, 19 rpm with one: well below the slowest test speed (60 rpm, 19 rad/s with 3 pole
#: pairs, its 6th-harmonic speed ripple included), while a reversal or a stop still splits the
#: pieces (their edge speeds pass through zero). Slower stretches yield no steady whole revolution
#: within a capture window anyway.
STANDSTILL_RAD_S = 2.0

#: a load point's tolerance (A; fraction): units whose ``i_qo`` is within ``max(IQ_TOL_A, IQ_TOL_REL *
#: |i_qo|)`` of the run's first share a steady run (the defaults of the segments' and the metrics'
#: windows); a load step beyond it also ends a fingerprint stretch (:mod:`eol_cal.analysis.fit.fp_angle`)
IQ_TOL_A = 0.5
IQ_TOL_REL = 0.02


def direction_pieces(omega_r: np.ndarray, standstill_rad_s: float = STANDSTILL_RAD_S) -> list[tuple[int, int]]:
    """Sample ranges of constant direction of rotation.

    Parameters
    ----------
    omega_r : ndarray
        Electrical speed per sample (rad/s).
    standstill_rad_s : float
        Electrical speeds (rad/s) below this count as standstill (no direction).

    Returns
    -------
    list of (start, stop)
        Half-open sample ranges.
    """
    w = np.asarray(omega_r, dtype=float)
    s = np.sign(w)
    s[np.abs(w) < standstill_rad_s] = 0
    edges = np.flatnonzero(np.diff(s) != 0) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [len(s)]])
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if s[a] != 0 and b - a > 1]


def revolution_bounds(theta_r: np.ndarray, per_rev: int = 1) -> np.ndarray:
    """Sample indices where each whole electrical revolution (or part of one) starts.

    Parameters
    ----------
    theta_r : ndarray
        Unwrapped electrical angle (rad); either direction.
    per_rev : int
        Units per revolution: 1 for whole revolutions, 6 for 60-degree units.

    Returns
    -------
    idx : ndarray of int
        ``idx[k]`` is the first sample at which the angle travelled ``2*pi*k/per_rev`` from
        its start (running maximum, so a standstill or a reversal only lengthens a unit); the
        last entry ends the last whole unit.
    """
    travel = np.asarray(theta_r, dtype=float) - float(theta_r[0])
    if travel[-1] < 0:
        travel = -travel
    reach = np.maximum.accumulate(travel)
    step = TWO_PI / per_rev
    n = int(np.floor(reach[-1] / step * (1 + 1e-12)))
    return np.searchsorted(reach, step * np.arange(n + 1) * (1 - 1e-12), side="left")


def _spans(x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """``np.ptp`` of each unit ``x[bounds[k]:bounds[k + 1]]`` (the unit of ``x``), two reductions for
    all of them (a maximum and a minimum are exact: the same values); an empty unit raises as
    ``np.ptp`` does."""
    b = np.asarray(bounds)
    if np.any(b[1:] <= b[:-1]):
        return np.array([np.ptp(x[b[k]:b[k + 1]]) for k in range(len(b) - 1)])
    x = x[:b[-1]]  # the last unit ends at the last bound
    return np.maximum.reduceat(x, b[:-1]) - np.minimum.reduceat(x, b[:-1])


def steady_runs(
    t: np.ndarray,
    bounds: np.ndarray,
    i_qo: np.ndarray | None,
    speed_tol: float,
    iq_tol_a: float,
    iq_tol_rel: float,
) -> list[list[int]]:
    """Group consecutive steady revolutions (or units, see :func:`revolution_bounds`) into runs.

    Parameters
    ----------
    t : ndarray
        Sample times (s).
    bounds : ndarray of int
        Revolution (or unit) start indices from :func:`revolution_bounds`.
    i_qo : ndarray or None
        Nominal q current per sample (A).
    speed_tol : float
        Allowed relative deviation of a unit's duration (judged together with the next unit's,
        when that one is steady inside too) from the run's mean unit duration so far.
    iq_tol_a, iq_tol_rel : float
        i_qo tolerance: ``max(iq_tol_a, iq_tol_rel * |i_qo of the first unit|)`` (A),
        for the spread inside a unit and for the deviation of its mean.

    Returns
    -------
    runs : list of list of int
        Unit numbers of each run (unit k spans ``bounds[k]:bounds[k+1]``).
    """
    n_rev = len(bounds) - 1
    if i_qo is not None:
        seg = [i_qo[bounds[k] : bounds[k + 1]] for k in range(n_rev)]
        iq_mean = np.array([s.mean() for s in seg])
        iq_span = _spans(np.asarray(i_qo), bounds) if n_rev else np.zeros(0)
    runs: list[list[int]] = []
    current: list[int] = []
    for k in range(n_rev):
        if i_qo is not None:
            ref_iq = iq_mean[current[0]] if current else iq_mean[k]
            tol = max(iq_tol_a, iq_tol_rel * abs(ref_iq))
            steady_in = iq_span[k] <= tol
        else:
            steady_in = True
        if current and steady_in:
            # Reference: the run's mean unit duration so far (s); unit boundaries come from the
            # reconstructed angle, and an angle error at one boundary lengthens one unit and
            # shortens the next by as much (1-2 % of a 60-degree unit on the plant's 64 PPR
            # encoder at 10 kHz, while the shaft holds its speed within 0.1 %). So a unit is
            # judged together with the next one when that one is steady inside too: the shared
            # boundary's error cancels, a change of operating point persists and still ends the run.
            ref = (t[bounds[k]] - t[bounds[current[0]]]) / len(current)
            j = k + 1 if k + 1 < n_rev and (i_qo is None or iq_span[k + 1] <= tol) else k
            span = (t[bounds[j + 1]] - t[bounds[k]]) / (j - k + 1)
            ok = abs(span - ref) <= speed_tol * ref
            if i_qo is not None:
                ok = ok and abs(iq_mean[k] - iq_mean[current[0]]) <= tol
            if ok:
                current.append(k)
                continue
        if current:
            runs.append(current)
        current = [k] if steady_in else []
    if current:
        runs.append(current)
    return runs
