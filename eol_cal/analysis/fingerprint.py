"""The encoder's fingerprint at end of line: each A edge's placement error, the frame the firmware
identifies against, and the identification margin it predicts (contract revision 1.2,
``firmware_params/MECH.md``, "End of line").

Per capture window (the encoder count is lost between windows): the quadrature count is decoded
as the estimator decodes it (from the window's first sample), every A rising edge's time and
boundary found, and the edge errors fitted by least squares, per direction, over the steady
stretches of the fit's segments: the boundary's nominal angle plus the edge's error is the rotor's
smooth angle at the edge time (a cubic polynomial in time per stretch), the errors orthogonal to
mechanical orders 0..2 (which the polynomials over a revolution or so would otherwise share). The window's grid phase is where its count boundary 0 sits in the
firmware's electrical frame (the offline angle at its edges plus the firmware frame offset).

Windows are then put into one frame, the first window's (the block's): each other window's offset
is identified as the firmware does (hall fraction hypotheses, cosine of the pitch errors), and the
windows' errors are averaged there. The margin the firmware will see after one revolution at the
reference speed is predicted from the fingerprint, its uncertainty and the tick quantisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from eol_cal.firmware.estimator import quadrature_phase

#: speed (mechanical rpm) at which the field margin is predicted: the fastest of the range the
#: identification is tested over (noisier than slower speeds)
REF_RPM = 300.0
#: degree of each steady stretch's polynomial motion (Legendre in time)
_POLY_DEGREE = 3
#: mechanical orders taken out of the fitted errors (the spline shares them)
_LOW_ORDERS = 2


@dataclass(frozen=True)
class WindowPrint:
    """One window's fingerprint in its own count frame.

    fp, var : (2N,) edge errors (rad electrical, NaN where not measured) and their variances;
    dirs : fp_dirs bits measured; grid_phase : rad electrical of count boundary 0 (firmware frame);
    q : (n,) the window's unwrapped quadrature count per sample; n_edges : edges used per direction.
    """

    fp: np.ndarray
    var: np.ndarray
    dirs: int
    grid_phase: float
    q: np.ndarray
    n_edges: tuple[int, int]


@dataclass(frozen=True)
class Fingerprint:
    """A motor's fingerprint in the block's frame (the first usable window's).

    fp, sigma : (2N,) edge errors (rad electrical, mean 0 per direction, 0 where not measured) and
    their standard errors; dirs : FP_FORWARD | FP_REVERSE measured; grid_phase : rad, [0, 2*pi);
    offsets : per window, its offset r into the block's frame (None: not identified, not used);
    scores : per window, (cosine, margin) of its identification against the block's frame.
    """

    fp: np.ndarray
    sigma: np.ndarray
    dirs: int
    grid_phase: float
    offsets: list[int | None]
    scores: list[tuple[float, float] | None] = field(default_factory=list)


def quadrature_counts(enc_a: np.ndarray, enc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The estimator's quadrature count per sample, unwrapped, from the first sample's phase.

    Returns ``(q, step, qep_errors)``: the count (int64), the step taken at each sample (+1, -1, 0)
    and the number of double steps (not counted, as the estimator does).
    """
    ph = np.asarray(quadrature_phase(np.asarray(enc_a).astype(np.int64) & 1, np.asarray(enc_b).astype(np.int64) & 1))
    d = np.diff(ph) % 4
    step = np.concatenate(([0], np.where(d == 1, 1, np.where(d == 3, -1, 0))))
    q = ph[0] + np.cumsum(step)
    return q, step, int(np.sum(d == 2))


def a_edges(t: np.ndarray, enc_a: np.ndarray, enc_b: np.ndarray, q: np.ndarray, step: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rising edges: times (s, the midpoint of the two samples around), boundary ``k`` (unwrapped;
    forward ``q``, reverse ``q + 1``, as the estimator numbers them) and direction (+1/-1)."""
    ph = np.asarray(quadrature_phase(np.asarray(enc_a).astype(np.int64) & 1, np.asarray(enc_b).astype(np.int64) & 1))
    fwd = (step == 1) & (ph == 1)
    rev = (step == -1) & (ph == 2)
    idx = np.flatnonzero(fwd | rev)
    idx = idx[idx > 0]
    times = 0.5 * (t[idx - 1] + t[idx])
    k = np.where(fwd[idx], q[idx], q[idx] + 1)
    return times, k, np.where(fwd[idx], 1, -1)


def _low_order_complement(N: int) -> np.ndarray:
    """Orthonormal basis (N, N - 1 - 2*_LOW_ORDERS) of the errors without orders 0.._LOW_ORDERS."""
    m = np.arange(N)
    cols = [np.ones(N)]
    for h in range(1, _LOW_ORDERS + 1):
        cols += [np.cos(2 * np.pi * h * m / N), np.sin(2 * np.pi * h * m / N)]
    A = np.stack(cols, axis=1)
    q_full, _ = np.linalg.qr(np.concatenate([A, np.eye(N)], axis=1))
    return q_full[:, A.shape[1]:N]


def _fit_direction(groups: list[tuple[np.ndarray, np.ndarray]], N: int, quarter: float
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """Edge errors (N,) and variances from one direction's edges in steady stretches, or None when
    the stretches hold fewer than a revolution and a half of edges.

    ``groups`` holds per stretch the edge times (s) and boundaries; each stretch's motion is a
    polynomial in time of its own (degree ``_POLY_DEGREE``), the errors are shared.
    """
    groups = [(t, k) for t, k in groups if len(t) > _POLY_DEGREE + 2]
    if sum(len(t) for t, _ in groups) < N + N // 2:
        return None
    P = _low_order_complement(N)
    nb = (_POLY_DEGREE + 1) * len(groups)
    rows, rhs = [], []
    for g, (times, k) in enumerate(groups):
        x = (times - times[0]) / max(times[-1] - times[0], 1e-12) * 2.0 - 1.0
        V = np.zeros((len(times), nb))
        V[:, g * (_POLY_DEGREE + 1):(g + 1) * (_POLY_DEGREE + 1)] = np.polynomial.legendre.legvander(x, _POLY_DEGREE)
        rows.append(np.concatenate([V, -P[(k >> 2) % N]], axis=1))
        rhs.append(k * quarter)
    A = np.concatenate(rows)
    phi = np.concatenate(rhs)
    sol, *_ = np.linalg.lstsq(A, phi, rcond=None)
    resid = phi - A @ sol
    dof = max(1, len(phi) - A.shape[1])
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    f = P @ sol[nb:]
    var = np.einsum("ij,jk,ik->i", P, cov[nb:, nb:], P)
    return f, var


def window_print(t: np.ndarray, enc_a: np.ndarray, enc_b: np.ndarray, theta_fw: np.ndarray,
                 poles: int, N: int, ranges: Sequence[tuple[int, int]]) -> WindowPrint | None:
    """One capture window's fingerprint in its own count frame.

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
        The steady stretches (sample ranges) whose edges are used (the fit's segments): one
        speed and load each, so the motion within is smooth.

    Returns
    -------
    WindowPrint, or None when a quadrature error makes the count untrustworthy or neither
    direction covers enough edges.
    """
    from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE

    t = np.asarray(t, dtype=float)
    q, step, qep = quadrature_counts(enc_a, enc_b)
    if qep:
        return None
    times, k, dirn = a_edges(t, enc_a, enc_b, q, step)
    quarter = poles * math.pi / N / 4.0
    fp = np.full(2 * N, np.nan)
    var = np.full(2 * N, np.nan)
    dirs = 0
    counts = [0, 0]
    used = np.zeros(len(times), bool)
    for d, bit in ((0, FP_FORWARD), (1, FP_REVERSE)):
        groups = []
        for a, b in ranges:
            sel = (dirn == (1 if d == 0 else -1)) & (times >= t[a]) & (times <= t[b - 1])
            if sel.sum():
                groups.append((times[sel], k[sel]))
                used |= sel
        res = _fit_direction(groups, N, quarter)
        if res is not None:
            fp[d::2], var[d::2] = res
            dirs |= bit
            counts[d] = sum(len(g[0]) for g in groups)
    if not dirs:
        return None
    # the grid phase: theta_fw at the edges used minus their boundaries' nominal angles
    th = np.interp(times[used], t, np.asarray(theta_fw, dtype=float))
    gp = float(np.angle(np.mean(np.exp(1j * (th - k[used] * quarter)))) % (2 * math.pi))
    return WindowPrint(fp, var, dirs, gp, q, (counts[0], counts[1]))


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


def merge_windows(prints: Sequence[WindowPrint | None], poles: int, N: int, min_margin: float = 0.25,
                  frac_tol: float = math.radians(2.0)) -> Fingerprint | None:
    """The windows' fingerprints in one frame: the first usable window's (None when there is none).

    Each other window is placed by the firmware's own rule (:func:`hypotheses` on the direction
    both measured, against the frame's running mean); one that does not pass ``min_margin`` and
    ``frac_tol`` is left out (its offset None).
    """
    usable = [i for i, p in enumerate(prints) if p is not None]
    offsets: list[int | None] = [None] * len(prints)
    scores: list[tuple[float, float] | None] = [None] * len(prints)
    if not usable:
        return None
    ref = prints[usable[0]]
    w = np.where(np.isfinite(ref.fp), 1.0 / np.maximum(ref.var, 1e-30), 0.0)
    acc = np.where(np.isfinite(ref.fp), ref.fp * w, 0.0)
    offsets[usable[0]] = 0
    scores[usable[0]] = (1.0, 1.0)
    for i in usable[1:]:
        p = prints[i]
        mean = np.where(w > 0, acc / np.maximum(w, 1e-300), 0.0)
        best = None
        for d in (0, 1):
            if np.isfinite(p.fp[d::2]).all() and (w[d::2] > 0).all():
                r, rho, margin, e = hypotheses(pitch_errors(p.fp, N)[d::2], pitch_errors(mean, N)[d::2],
                                               p.grid_phase - ref.grid_phase, poles, N)
                if best is None or margin > best[2]:
                    best = (r, rho, margin, e)
        if best is None or best[2] < min_margin or abs(best[3]) > frac_tol:
            scores[i] = None if best is None else (best[1], best[2])
            continue
        r = best[0]
        offsets[i], scores[i] = r, (best[1], best[2])
        # window pulse m is the frame's pulse (m + r): move its entries there
        idx = (2 * ((np.arange(N) + r) % N)[:, None] + np.arange(2)).reshape(-1)
        ok = np.isfinite(p.fp)
        wi = np.where(ok, 1.0 / np.maximum(p.var, 1e-30), 0.0)
        acc[idx] += np.where(ok, p.fp * wi, 0.0)
        w[idx] += wi
    fp = np.where(w > 0, acc / np.maximum(w, 1e-300), 0.0)
    sigma = np.where(w > 0, 1.0 / np.sqrt(np.maximum(w, 1e-300)), np.inf)
    dirs = 0
    for d in (0, 1):
        if (w[d::2] > 0).all():
            dirs |= 1 << d
            fp[d::2] -= fp[d::2].mean()
        else:
            fp[d::2] = 0.0
    return Fingerprint(fp, sigma, dirs, ref.grid_phase, offsets, scores)


def predicted_margin(fp: np.ndarray, sigma: np.ndarray, dirs: int, poles: int, N: int, tick_hz: float,
                     ref_rpm: float = REF_RPM) -> tuple[float, float]:
    """The identification the firmware can expect after one revolution of samples at ``ref_rpm``.

    For each measured direction: the signal energy of the pitch errors ``S`` (their sum of squares
    less the measurement's noise), the field's noise energy ``N_f`` (the tick quantisation of one
    pitch, ``DELTA / sqrt(6) / ticks_per_pitch`` per sample); the true hypothesis' cosine
    ``S / sqrt((S + N_eol) (S + N_f))``, each pole-pair neighbour's (lags L with
    ``|wrap(L*DELTA)| < DELTA``) its autocorrelation scaled alike, and three standard deviations
    of the noise's share taken off the margin. Returns ``(cosine, margin)`` of the worse direction;
    ``(0, 0)`` when nothing was measured.
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
        S = max(float(x @ x) - n_eol, 0.0)
        Nf = N * sq * sq
        den = math.sqrt((S + n_eol) * (S + Nf))
        if den <= 0.0:
            return 0.0, 0.0
        rho = S / den
        wrong = max((float(x @ np.roll(x, -L)) / den for L in lags), default=0.0)
        noise = 3.0 * math.sqrt(2.0) * sq / math.sqrt(S + Nf)
        cand = (rho - 3.0 * sq / math.sqrt(S + Nf), rho - max(wrong, 0.0) - noise)
        out = cand if out is None or cand[1] < out[1] else out
    return out if out is not None else (0.0, 0.0)


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
