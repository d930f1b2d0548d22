"""The encoder's fingerprint at end of line: each A edge's placement error, the frame the firmware
identifies against, and the identification margin it predicts (contract revision 1.2,
``firmware_params/MECH.md``, "End of line").

Per capture window (the encoder count is lost between windows): the quadrature count is decoded
as the estimator decodes it (from the window's first sample), every A rising edge's time and
boundary found, and the edge errors fitted by least squares, per direction, over the steady
stretches of the fit's segments: the boundary's nominal angle plus the edge's error is the rotor's
smooth angle at the edge time (a cubic polynomial in time per stretch), the errors orthogonal to
mechanical orders 0..2 (which the polynomials over a revolution or so would otherwise share).
The window's grid phase is where its count boundary 0 sits in the firmware's electrical frame
(the offline angle at its edges plus the firmware frame offset).

Windows are then put into one frame, that of the window with most edges (the block's): each other
window's offset is found by the halls (its grid phase allows one offset per pole pair) and the
fingerprint (the offset whose joint fit with the windows already placed leaves the least
residual), and the errors are fitted over all placed windows' edges together. The margin the
firmware will see after one revolution at the reference speed is predicted from the fingerprint,
its uncertainty and the tick quantisation.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from eol_cal.firmware.estimator import quadrature_phase
from eol_cal.analysis.fingerprint_fit import POLY_DEGREE, EdgeSums, JointFit, NormalEquations, PlacedWindows

#: speed (mechanical rpm) at which the field margin is predicted: the fastest of the range the
#: identification is tested over (noisier than slower speeds)
REF_RPM = 300.0


@dataclass(frozen=True)
class WindowEdges:
    """One window's A edges over its steady stretches, in its own count frame.

    stretches : per stretch of smooth motion in one direction, (edge times (s), A boundaries k
        (unwrapped): ``k >> 1`` indexes the fingerprint, both of its halves);
    grid_phase : rad electrical of the window's count boundary 0 (firmware frame);
    q : (n,) the window's unwrapped quadrature count per sample.
    """

    stretches: list[tuple[np.ndarray, np.ndarray]]
    grid_phase: float
    q: np.ndarray

    @property
    def n_edges(self) -> int:
        return sum(len(t) for t, _ in self.stretches)


@dataclass(frozen=True)
class Fingerprint:
    """A motor's fingerprint in the block's frame (the first usable window's).

    fp : (2N,) edge errors (rad electrical, mean 0 per direction, 0 where not measured); dirs :
    FP_FORWARD | FP_REVERSE measured; grid_phase : rad, [0, 2*pi); offsets : per window, its offset
    r into the block's frame (None: not placed, not used); scores : per window, (fraction error
    rad, residual ratio of the next offset; NaN when the joint fit could not tell) of its
    placement; equations : the joint fit's normal equations, which :attr:`sigma` is solved from.
    """

    fp: np.ndarray
    dirs: int
    grid_phase: float
    offsets: list[int | None]
    scores: list[tuple[float, float] | None] = field(default_factory=list)
    equations: NormalEquations | None = field(default=None, repr=False)

    @functools.cached_property
    def sigma(self) -> np.ndarray:
        """(2N,) the edge errors' standard errors (rad electrical; inf where not measured), solved
        when first asked: the angle correction and a refit's row never read them (issue 37: the
        covariance of ~120 unknowns a motor), the mechanical orders and the margin do."""
        var = self.equations.variances() if self.equations is not None else np.full(len(self.fp), np.nan)
        sigma = np.sqrt(np.where(np.isfinite(var), np.maximum(var, 0.0), np.inf))
        for d in (0, 1):
            if not self.dirs & (1 << d):
                sigma[d::2] = np.inf
        return sigma


def quadrature_counts(enc_a: np.ndarray, enc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The estimator's quadrature count per sample, unwrapped, from the first sample's phase.

    Returns ``(q, step, qep_errors)``: the count (int64), the step taken at each sample (+1, -1, 0;
    int64) and the number of double steps (not counted, as the estimator does).
    """
    # the levels in their own small integers (a capture's int8; the firmware's phase makes them
    # int32), not converted to int64 first: the same phases 0..3, a change mod 4 its low two bits
    ph = np.asarray(quadrature_phase(_low_bit(enc_a), _low_bit(enc_b)))
    d = (ph[1:] - ph[:-1]) & 3
    step = np.empty(len(ph), np.int64)
    step[0] = 0
    step[1:] = _STEP[d]
    q = int(ph[0]) + np.cumsum(step)
    return q, step, int(np.count_nonzero(d == 2))


#: the step of a quadrature phase change (mod 4): none, forward, a double step (not counted), back
_STEP = np.array([0, 1, 0, -1], dtype=np.int64)


def _low_bit(levels: np.ndarray) -> np.ndarray:
    """A digital channel's low bit (0/1), in its own integer type (int64 for any other)."""
    x = np.asarray(levels)
    return (x if x.dtype.kind in "iu" else x.astype(np.int64)) & 1


def a_edges(t: np.ndarray, enc_a: np.ndarray, enc_b: np.ndarray, q: np.ndarray, step: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every level change of channel A: times (s, the midpoint of the two samples around), the
    boundary ``k`` it crosses (unwrapped; the estimator's numbering: ``q`` stepping forward,
    ``q + 1`` stepping back) and the direction of motion (+1/-1).

    A rises at ``k = 4m + 1`` and falls at ``4m + 3`` in forward rotation; in reverse the same
    boundaries are crossed the other way. The firmware's forward fingerprint is the edges at
    ``4m + 1`` (A rising forward), its reverse fingerprint those at ``4m + 3`` (A rising in
    reverse): both are measured whichever way the motor turns (fingerprint index ``k >> 1``).
    """
    a = _low_bit(enc_a)
    # a change of A at a sample where the count moved (never the first sample)
    idx = np.flatnonzero((a[1:] != a[:-1]) & (step[1:] != 0)) + 1
    times = 0.5 * (t[idx - 1] + t[idx])
    fwd = step[idx] > 0
    k = np.where(fwd, q[idx], q[idx] + 1)
    return times, k, np.where(fwd, 1, -1)


def window_edges(t: np.ndarray, enc_a: np.ndarray, enc_b: np.ndarray, theta_fw: np.ndarray,
                 poles: int, N: int, ranges: Sequence[tuple[int, int]]) -> WindowEdges | None:
    """One capture window's A edges over its steady stretches (the fit's segments) and its grid phase.

    Parameters
    ----------
    t : ndarray
        Sample times (s).
    enc_a, enc_b : ndarray
        Encoder levels.
    theta_fw : ndarray
        Electrical angle per sample in the firmware's frame (rad, any unwrapping): the offline
        angle plus the firmware frame offset.
    poles, N : int
        P and the encoder's pulses per revolution.
    ranges : sequence of (start, stop)
        The steady stretches (sample ranges): one speed, load and direction each, so the motion
        within is smooth.

    Returns
    -------
    WindowEdges, or None when a quadrature error makes the count untrustworthy or no stretch
    holds edges.
    """
    t = np.asarray(t, dtype=float)
    q, step, qep = quadrature_counts(enc_a, enc_b)
    if qep:
        return None
    times, k, dirn = a_edges(t, enc_a, enc_b, q, step)
    quarter = poles * math.pi / N / 4.0
    stretches = []
    used = np.zeros(len(times), bool)
    for a, b in ranges:
        for d in (1, -1):
            sel = (dirn == d) & (times >= t[a]) & (times <= t[b - 1])
            if sel.sum() > 2 * (POLY_DEGREE + 2):
                stretches.append((times[sel], k[sel]))
                used |= sel
    if not stretches:
        return None
    # the grid phase from the forward fingerprint's edges (A rising forward: the duty cycle's
    # error would shift the others by a constant)
    rise = used & ((k & 3) == 1)
    th = np.interp(times[rise], t, np.asarray(theta_fw, dtype=float))
    gp = float(np.angle(np.mean(np.exp(1j * (th - k[rise] * quarter)))) % (2 * math.pi))
    return WindowEdges(stretches, gp, q)


def pitch_errors(fp: np.ndarray, N: int) -> np.ndarray:
    """The fingerprint's pitch errors ``fp[2m+d] - fp[2((m-1) mod N)+d]`` (2N,), as the firmware forms them."""
    prev = np.roll(np.asarray(fp, dtype=float).reshape(N, 2), 1, axis=0).reshape(-1)
    return np.asarray(fp, dtype=float) - prev


def hypotheses(dF_meas: np.ndarray, dF_ref: np.ndarray, dg: float, poles: int, N: int
               ) -> tuple[int, float, float, float]:
    """The firmware's evaluation in float64 (MECH.md, "Evaluation") for one direction's pitch errors.

    Returns ``(r, cosine, margin, fraction_error)`` of the best of the P/2 hypotheses the grid-phase
    difference ``dg`` (rad) allows; the margin is over ``max(0, next best)``.
    """
    delta = poles * math.pi / N
    den = math.sqrt(float(dF_meas @ dF_meas) * float(dF_ref @ dF_ref))
    rhos, rs, es = [], [], []
    for j in range(poles // 2):
        r = int(math.floor((dg % (2 * math.pi) + 2 * math.pi * j) / delta + 0.5)) % N
        rs.append(r)
        es.append(math.remainder(dg - r * delta, 2 * math.pi))
        rhos.append(float(dF_meas @ np.roll(dF_ref, -r)) / den if den > 0 else 0.0)
    b = int(np.argmax(rhos))
    second = max([0.0] + [x for j, x in enumerate(rhos) if j != b])
    return rs[b], rhos[b], rhos[b] - second, es[b]


def merge_windows(windows: Sequence[WindowEdges | None], poles: int, N: int, min_ratio: float = 2.0,
                  frac_tol: float = math.radians(2.0)) -> Fingerprint | None:
    """The fingerprint of every window's edges in one frame: the window with most edges' (None
    when no window, or no direction, holds a revolution and a half of edges).

    Each other window is placed by the halls and the fingerprint together: of the P/2 offsets its
    grid phase allows (one per pole pair), the one whose joint fit leaves the smallest residual,
    when it agrees with the halls' fraction within ``frac_tol`` and the next offset's residual is
    ``min_ratio`` times larger; otherwise the window is left out (its offset None).
    """
    present = {i: w for i, w in enumerate(windows) if w is not None}
    usable = list(present)
    if not usable:
        return None
    ref = max(usable, key=lambda i: present[i].n_edges)
    quarter = poles * math.pi / N / 4.0
    delta = 4 * quarter
    offsets: list[int | None] = [None] * len(windows)
    scores: list[tuple[float, float] | None] = [None] * len(windows)
    offsets[ref] = 0
    stats = {i: EdgeSums(present[i].stretches, N, quarter) for i in usable}
    placed = PlacedWindows(N)
    placed.add(stats[ref], 0)
    todo = [i for i in sorted(usable, key=lambda j: -present[j].n_edges) if i != ref]
    changed = True
    while todo and changed:  # a window that overlaps nothing placed yet may overlap what later windows add
        changed = False
        for i in list(todo):
            r, score = _place(present[i], stats[i], present[ref].grid_phase, placed, poles, N, delta,
                              min_ratio, frac_tol)
            scores[i] = score
            if r is not None:
                offsets[i] = r
                placed.add(stats[i], r)
                todo.remove(i)
                changed = True
    fit = placed.fit(cov=False)  # the variances when first asked (Fingerprint.sigma)
    if fit is None:
        return None
    fp, _, _, dirs, _ = fit
    for d in (0, 1):
        if dirs & (1 << d):
            fp[d::2] -= fp[d::2].mean()
        else:
            fp[d::2] = 0.0
    return Fingerprint(fp, dirs, present[ref].grid_phase, offsets, scores, placed.equations())


def _place(w: WindowEdges, stats: EdgeSums, ref_phase: float, placed: PlacedWindows, poles: int, N: int, delta: float,
           min_ratio: float, frac_tol: float) -> tuple[int | None, tuple[float, float]]:
    """Where window ``w`` (its sums ``stats``) goes in the frame of the windows ``placed``:
    ``(r or None, (fraction error rad, residual ratio))``.

    The halls allow one offset per pole pair (the ``grid_phase`` difference); the one within
    ``frac_tol`` of its fraction is taken unless the fingerprint contradicts it: a joint fit with
    enough data to tell (N/2 more edges than unknowns) in which another offset leaves a residual
    ``min_ratio`` times smaller. Several offsets within ``frac_tol`` (pulses that divide evenly among
    the pole pairs) need the fingerprint to prefer one by ``min_ratio``.
    """
    dg = (w.grid_phase - ref_phase) % (2 * math.pi)
    rs = [int(math.floor((dg + 2 * math.pi * j) / delta + 0.5)) % N for j in range(poles // 2)]
    trials = [(fit[0] if fit is not None and fit[1] >= N // 2 else math.nan, r, math.remainder(dg - r * delta, 2 * math.pi))
              for r, fit in zip(rs, placed.trials(stats, rs), strict=True)]
    frac_ok = sorted((x for x in trials if abs(x[2]) <= frac_tol), key=lambda x: abs(x[2]))
    if not frac_ok:
        return None, (float(min(abs(x[2]) for x in trials)), math.nan)
    told = [x for x in trials if math.isfinite(x[0])]
    if len(frac_ok) > 1:
        cands = sorted((x for x in frac_ok if math.isfinite(x[0])), key=lambda x: x[0])
        if len(cands) < 2 or cands[1][0] < min_ratio * cands[0][0]:
            return None, (float(frac_ok[0][2]), math.nan)  # neither the halls nor the fingerprint can tell
        best = cands[0]
    else:
        best = frac_ok[0]
    others = [x[0] for x in told if x is not best]
    ratio = min(others) / max(best[0], 1e-300) if others and math.isfinite(best[0]) else math.nan
    if math.isfinite(ratio) and ratio * min_ratio <= 1.0:
        return None, (float(best[2]), float(ratio))  # the fingerprint contradicts the halls
    return best[1], (float(best[2]), float(ratio))


def predicted_margin(fp: np.ndarray, sigma: np.ndarray, dirs: int, poles: int, N: int, tick_hz: float,
                     ref_rpm: float = REF_RPM, noise: Sequence[float] | np.ndarray | None = None) -> tuple[float, float]:
    """The identification the firmware can expect after one revolution of samples at ``ref_rpm``.

    For each measured direction: the signal energy of the pitch errors ``S`` (their sum of squares
    less the measurement's noise ``N_eol``), the field's noise energy ``N_f`` (the tick quantisation
    of one pitch, ``DELTA / sqrt(6) / ticks_per_pitch`` per sample); the true hypothesis' cosine
    ``S / sqrt((S + N_eol) (S + N_f))``, each pole-pair neighbour's (lags L with
    ``|wrap(L*DELTA)| < DELTA``) its autocorrelation scaled alike, and three standard deviations
    of the noise's share taken off the margin. Returns ``(cosine, margin)`` of the worse direction;
    ``(0, 0)`` when nothing was measured.

    ``N_eol`` (rad^2 electrical) is ``noise[d]`` where given and finite (:func:`split_noise`: the
    error the pitch errors were measured with), else the sum of the pitch errors' variances from
    ``sigma`` (the edges' standard errors, rad electrical; 0 for a true fingerprint).
    """
    delta = poles * math.pi / N
    ticks = tick_hz * 60.0 / (abs(ref_rpm) * N)
    sq = delta / math.sqrt(6.0) / ticks
    dF = pitch_errors(fp, N)
    s2 = np.where(np.isfinite(sigma), np.asarray(sigma, dtype=float) ** 2, 0.0)
    var_dF = s2 + np.roll(s2.reshape(N, 2), 1, axis=0).reshape(-1)
    lags = [L for L in range(1, N) if abs(math.remainder(L * delta, 2 * math.pi)) < delta]
    out = None
    for d in (0, 1):
        if not dirs & (1 << d):
            continue
        x = dF[d::2]
        n_eol = float(var_dF[d::2].sum())
        if noise is not None and math.isfinite(noise[d]):
            n_eol = float(noise[d])
        S = max(float(x @ x) - n_eol, 0.0)
        Nf = N * sq * sq
        den = math.sqrt((S + n_eol) * (S + Nf))
        if den <= 0.0:
            return 0.0, 0.0
        rho = S / den
        wrong = max((float(x @ np.roll(x, -L)) / den for L in lags), default=0.0)
        share = 3.0 * math.sqrt(2.0) * sq / math.sqrt(S + Nf)  # three sd of the field noise's share
        cand = (rho - 3.0 * sq / math.sqrt(S + Nf), rho - max(wrong, 0.0) - share)
        out = cand if out is None or cand[1] < out[1] else out
    return out if out is not None else (0.0, 0.0)


def split_noise(prints: Sequence[WindowEdges | None], fp: Fingerprint, poles: int, N: int) -> np.ndarray:
    """The error energy of the fingerprint's pitch errors (rad^2 electrical, per direction, NaN
    where it cannot be measured), measured from the edges themselves: a jackknife over the stretches.

    The stretches of the windows placed in ``fp`` are fitted together ``n`` times, each time
    without one of them, in the block's frame. Whatever differs from stretch to stretch (the tick
    quantisation, the motion a stretch's polynomial misses) moves the fit as the left-out stretch
    changes: ``(n - 1) / n`` times the replicates' squared spread about their mean, summed over the
    direction's pitch errors, is the whole fit's error energy. ``n`` fits without variances (the
    two halves of the 32 splits this replaced cost 64 with them), and over the end-to-end sets'
    0.2x and 0.3x motors it measured 0.97 of the actual error (median; 0.82-1.28 for 90 % of them)
    where the halves measured 0.87 (0.74-1.20), the margin predicted from it off the margin from
    the actual error by a standard deviation of 0.015 (the halves' 0.024; MECH.md, "The switch").

    The edges' standard errors (``fp.sigma``) take the residual as white and of one size for every
    stretch: a stretch whose motion the polynomial misses (a load step inside it) makes them tens
    of times the fingerprint's actual error, which varies mostly slowly with the angle, where the
    pitch errors hardly see it. A direction the fit loses when one stretch is left out (too few
    stretches to tell) is NaN.
    """
    quarter = poles * math.pi / N / 4.0
    items = [(EdgeSums([st], N, quarter), fp.offsets[i]) for i, w in enumerate(prints)
             if w is not None and fp.offsets[i] is not None for st in w.stretches]
    n = len(items)
    out = np.full(2, np.nan)
    whole = _fit_items(items, N)
    if n < 3 or whole is None:
        return out
    reps: list[list[np.ndarray]] = [[], []]
    for k in range(n):
        f = _fit_items(items[:k] + items[k + 1:], N)
        for d in (0, 1):
            if f is not None and f[3] & (1 << d):
                reps[d].append(pitch_errors(f[0], N)[d::2])
    for d in (0, 1):
        if fp.dirs & whole[3] & (1 << d) and len(reps[d]) == n:
            R = np.asarray(reps[d])
            out[d] = (n - 1) / n * float(np.sum((R - R.mean(axis=0)) ** 2))
    return out


def _fit_items(items: Sequence[tuple[EdgeSums, int | None]], N: int) -> JointFit | None:
    """The joint fit (without variances) of stretches at their offsets."""
    placed = PlacedWindows(N)
    for stats, r in items:
        assert r is not None  # only stretches of placed windows
        placed.add(stats, r)
    return placed.fit(cov=False) if items else None


def block_frame_mech_angle(q: np.ndarray, r: int, grid_phase: float, theta_fw: np.ndarray, poles: int, N: int
                           ) -> np.ndarray:
    """The rotor's mechanical angle in the block's frame (rad, [0, 2*pi)) at samples with window
    counts ``q`` (unwrapped), the window's offset ``r`` and the firmware-frame electrical angle
    ``theta_fw`` (rad): the firmware's rule (MECH.md, "Compensation") in float64."""
    M = 4 * N
    quarter = poles * math.pi / N / 4.0
    k = (np.asarray(q) + 4 * int(r)) % M
    Ek = grid_phase + k * quarter
    E = Ek + np.remainder(np.asarray(theta_fw, dtype=float) - Ek + math.pi, 2 * math.pi) - math.pi
    return np.mod(E / (poles // 2), 2 * math.pi)
