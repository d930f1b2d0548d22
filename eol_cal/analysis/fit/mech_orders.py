"""The fit's mechanical part (contract revision 1.2): the encoder's fingerprint, the mechanical
orders 1..3 in the frame the firmware identifies, the identification margin, and whether the
block may switch ``MECH_COMP_ENABLE`` on.

After the ripple fit (:mod:`eol_cal.analysis.fit`, whose per-segment mechanical pair has a phase of
its own in every segment: the halls cannot tell the pole pair) the fingerprint
(:mod:`eol_cal.analysis.fingerprint`) gives every sample of every identified window its mechanical
angle in the block's frame. The torque left after the fitted electrical ripple is then fitted,
all segments together, with a drift polynomial per segment and one sine/cosine pair per
mechanical order h = 1..3 shared by all: each order seen through the bench's response and the
transducer's lag at the segment's speed, as the ripple fit models them. The orders are
load-independent (N*m; the plant's unbalance is); the block's per-ampere part is 0.

Intervals: the joint fit's covariance at the noise each order actually has in each segment
(:func:`order_noise`: the residual's phasors at the order's neighbouring frequencies, as the
model check measures the 6th's) and the delete-one-segment jackknife's (the segments' scatter: what
differs from segment to segment and not from sample to sample), with Student's t of the noise plus
the scatter's excess (Welch-Satterthwaite, as the electrical quantities'). An order not resolved from
zero (its phasor's 95 % region, Hotelling's T^2 at those degrees of freedom on the noise plus the
excess direction by direction, :func:`pair_covariance`, holds the origin) reports an amplitude
interval that reaches zero and no phase bound (:func:`order_estimate`); a resolved one's amplitude
and phase take the wider of the two by the pair's trace
(:func:`eol_cal.analysis.fit.motor_fit.wider_per_quantity`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.analysis import fingerprint as fpr
from eol_cal.analysis.fit import path_gain
from eol_cal.analysis.fit.fp_angle import edge_residual_correlation, window_prints
from eol_cal.analysis.fit.model import Z95, bin_steps, legendre_rows, line_noise, noise_bins, transducer_gain
from eol_cal.analysis.fit.motor_fit import amp_phase, excess_t, wider_per_quantity
from eol_cal.analysis.fit.plot import fitted_ripple
from eol_cal.analysis.motor_result import MECH_OFF, MECH_OK, MechOrder, MechResult, ValueCi
from eol_cal.firmware.mech_params import ORDERS, SWITCH_MARGIN, SWITCH_MIN_SCORE

if TYPE_CHECKING:
    from collections.abc import Callable

    from eol_cal.analysis.fit import FitSpec, MotorFit
    from eol_cal.analysis.fit.motor_input import MotorInput

#: chi-square with 2 degrees of freedom at 95 % (-2 ln 0.05): a phasor's 95 % region
_CHI2_2_95 = -2.0 * math.log(0.05)
#: the fewest segments whose scatter (the delete-one-segment jackknife, S - 1 degrees of freedom) an
#: order's interval may rest on: the noise's interval alone does not cover (orders 1-2's errors
#: 1.3-1.8x it on plant motors), and two segments give one degree of freedom (Student's t 12.7: order
#: 1 +-54 N*m on the typed golden one_load), an interval that says nothing; fewer: no interval
MIN_SEGMENTS = 3


def fit_orders(mi: MotorInput, fit: MotorFit, spec: FitSpec, prints: list[fpr.WindowEdges | None],
               fp: fpr.Fingerprint) -> tuple[MechOrder, ...] | None:
    """Mechanical orders 1..3 (N*m, phase in the block's mechanical frame) from the segments of
    the identified windows; None when no segment's window is identified."""
    seg = mi.segments
    pp = seg.pole_pairs
    H = len(ORDERS)
    deg = spec.drift_degree
    nd = deg + 1
    gains6 = path_gain(seg, spec)
    used = [s for s in range(seg.n_segments) if fp.offsets[mi.capture_of_segment[s]] is not None]
    if not used:
        return None
    # Each segment's drift polynomial is eliminated from its own normal equations (the order block
    # of inv(X^T X) is the Schur complement): a (2H x 2H) system instead of one dense least squares
    # with (deg + 1) columns per segment; the same solution, residual and covariance.
    parts = []
    lines = []  # per segment: what order_noise needs
    shares: list[tuple[np.ndarray, np.ndarray]] = []
    M = np.zeros((2 * H, 2 * H))
    rhs = np.zeros(2 * H)
    for s in used:
        ci = mi.capture_of_segment[s]
        info = mi.info[s]
        theta = np.asarray(seg.theta[s], dtype=float)
        y = np.asarray(seg.torque[s], dtype=float) - fitted_ripple(mi, fit, spec, s, theta, gains6)
        edges, offset = prints[ci], fp.offsets[ci]
        # used: segments of windows placed in the fingerprint, and merge_windows places only windows with edges
        assert edges is not None and offset is not None
        q = edges.q[info.start:info.stop]
        th_m = fpr.block_frame_mech_angle(q, offset, fp.grid_phase, theta + mi.frame_offset_rad,
                                          mi.poles, mi.encoder_ppr)
        w_m = seg.omega_e[s] / pp
        freqs = np.asarray(ORDERS, dtype=float) * w_m
        g = transducer_gain(spec, fit.delay_s, freqs)
        if seg.path_response is not None:
            g = g * np.asarray(seg.path_response(freqs), dtype=complex)
        t = np.asarray(seg.t[s], dtype=float)
        # columns: the drift's Legendre rows, the orders' (sin, cos) pairs, the torque
        W = np.empty((nd + 2 * H + 1, len(t)))
        legendre_rows((t - t[0]) * (2.0 / max(t[-1] - t[0], 1e-12)) - 1.0, deg, W[:nd])
        # the ripple -c sin(h th + phase) = -(A sin(h th) + B cos(h th)), A = c cos phase, B = c sin phase,
        # through the response g: columns -|g| sin(h th + arg g), -|g| cos(...) = Im, Re of -g exp(i h th)
        e1 = np.exp(1j * th_m)
        e = {1: e1}
        for h in range(2, max(ORDERS) + 1):
            e[h] = e[h - 1] * e1
        for i, h in enumerate(ORDERS):
            z = e[h] * -g[i]
            W[nd + 2 * i] = z.imag
            W[nd + 2 * i + 1] = z.real
        cur_res = None
        if seg.kt_iq is not None:
            known, cur_res = current_orders(np.asarray(seg.kt_iq[s], dtype=float), W[:nd], e, g)
            y = y - known
        lines.append((th_m, t, float(w_m), cur_res, seg.path_response))
        W[-1] = y
        Gs = W @ W.T
        D_inv, B = np.linalg.inv(Gs[:nd, :nd]), Gs[:nd, nd:-1]
        Ms, rs = Gs[nd:-1, nd:-1] - B.T @ D_inv @ B, Gs[nd:-1, -1] - B.T @ (D_inv @ Gs[:nd, -1])
        M += Ms
        rhs += rs
        parts.append((W, D_inv))
        shares.append((Ms, rs))
    sol = np.linalg.solve(M, rhs)
    res_parts = []
    for W, D_inv in parts:
        e = W[-1] - W[nd:-1].T @ sol     # the torque less the orders, then less its own best drift
        res_parts.append(e - W[:nd].T @ (D_inv @ (W[:nd] @ e)))
    # the noise: each segment's share of the normal equations has covariance D_s M_s D_s, D_s the
    # white-equivalent noise each order has there (per pair, order_noise) on the least squares' M_s
    C = np.zeros_like(M)
    for (Ms, _), e_s, (th_m, t, w_m, cur_res, path) in zip(shares, res_parts, lines, strict=True):
        d = np.repeat(np.sqrt(order_noise(e_s, cur_res, th_m, t, w_m, spec, fit.delay_s, path, pp)), 2)
        C += d[:, None] * Ms * d[None, :]
    M_inv = np.linalg.inv(M)
    cov = M_inv @ C @ M_inv
    # What differs from segment to segment and not from sample to sample (the drift polynomial's
    # misfit to the dyno's speed loop; the current's noise below the segment's resolution, which
    # the path takes to the shaft otherwise than at the line) is not in that noise: over plant
    # motors the errors of orders 1-2 were 1.3-1.8x its standard deviations. The segments' scatter
    # measures it: the delete-one-segment jackknife, with Student's t of its S - 1 degrees of
    # freedom (8 segments: 2.36, not 1.96). A Birge ratio of the segments' normal-equation shares
    # measured it in their ill-determined directions (a third of a revolution of order 1 against
    # the drift), where that noise is largest and matters least: it widened the intervals 3-5x,
    # covering the truth for every motor
    S = len(shares)
    if S < MIN_SEGMENTS:
        why = (f"no interval: {S} segment{'s' if S != 1 else ''} in identified windows, the segments' scatter "
               f"needs at least {MIN_SEGMENTS} (fit more load points or speeds)")
        return tuple(MechOrder(h, ValueCi(math.hypot(sol[2 * i], sol[2 * i + 1]), None),
                               ValueCi(math.atan2(sol[2 * i + 1], sol[2 * i]), None), why) for i, h in enumerate(ORDERS))
    loo = np.array([np.linalg.lstsq(M - Ms, rhs - rs, rcond=None)[0] for Ms, rs in shares])
    dev = loo - loo.mean(axis=0)
    # Per order, whether it is resolved from zero rests on both directions of its pair: the noise plus
    # the scatter's excess over it in each direction (pair_covariance). A resolved order's amplitude
    # and phase are one direction each: they keep the electrical quantities' rule (the wider of the
    # two by the pair's trace, motor_fit.wider_per_quantity), which covered the orders 95.5-97.0 % of
    # 400 plant motors, where the per-direction covariance for them too covered 97.0-98.5 % (order 3's
    # phase 98.5: too wide; docs/benchmarks.md)
    scatter = (S - 1) / S * (dev.T @ dev)
    out = []
    for i, h in enumerate(ORDERS):
        b = slice(2 * i, 2 * i + 2)
        C, dof = pair_covariance(cov[b, b], scatter[b, b], S)
        one_d = wider_per_quantity(cov[b, b], scatter[b, b], [slice(0, 2)], S)
        out.append(MechOrder(h, *order_estimate(sol[2 * i], sol[2 * i + 1], C, dof, interval=one_d)))
    return tuple(out)


def pair_covariance(noise: np.ndarray, scatter: np.ndarray, S: int) -> tuple[np.ndarray, float]:
    """An order's pair covariance (N*m^2) from the noise's and the segments' scatter, in every
    direction the wider, and its degrees of freedom.

    The noise's ``V_n`` plus the scatter's excess over it direction by direction, ``B = (V_s - V_n)_+``
    (the positive part of the symmetric difference: its eigenvalues clipped at 0), so the result is at
    least each of the two along any direction. The whole scatter where its trace is the larger
    (:func:`~eol_cal.analysis.fit.motor_fit.wider_per_quantity`'s rule for the electrical quantities,
    which report one amplitude) took the jackknife's narrow direction too, which 8 segments estimate
    poorly: an order's region rests on both directions, and where an absent order's phasor lay along
    that one its region left zero out at chi-square 12-21 (resonant 250 Hz lot, seeds 1 and 8).
    Scaled by ``(t / 1.96)^2``, Student's t of the Welch-Satterthwaite degrees of freedom of the
    noise (known) plus the excess (``S - 1``), the two's traces
    (:func:`~eol_cal.analysis.fit.motor_fit.excess_t`; infinite without excess).
    """
    w, U = np.linalg.eigh(scatter - noise)
    excess = (U * np.maximum(w, 0.0)) @ U.T
    t, dof = excess_t(float(np.trace(noise)), float(np.trace(excess)), S)
    return (noise + excess) * t * t, dof  # without excess: t = 1 and the excess is zero


def region_scale(dof: float) -> float:
    """A phasor's 95 % region ``z^T C^-1 z <= region_scale(dof)`` on its covariance ``C`` as the fit
    reports it (already scaled by ``(t(dof) / 1.96)^2`` for the one-dimensional intervals).

    A covariance estimated with ``dof`` degrees of freedom makes ``z^T C^-1 z`` Hotelling's T^2, whose
    95 % point for a pair is ``dof (0.05^(-2 / (dof - 1)) - 1)`` (``2 dof / (dof - 1) F(2, dof - 1)``;
    the F quantile for 2 numerator degrees of freedom in closed form), not chi-square's 5.99 scaled by
    the one-dimensional t: with 7 (8 segments' jackknife) 12.0 against 8.7, a region that left an absent
    order out of its interval for 8.8 % of motors, not 5 % (tests/test_mech_order_estimate.py).
    Infinite ``dof``: chi-square with 2 degrees of freedom, 5.99.
    """
    if not math.isfinite(dof):
        return _CHI2_2_95
    from scipy.special import stdtrit  # heavy: not at `eol-cal run`'s start (tests/test_imports.py)

    t2 = dof * (0.05 ** (-2.0 / (dof - 1.0)) - 1.0)
    return t2 * (Z95 / float(stdtrit(dof, 0.975))) ** 2


def order_estimate(a: float, b: float, C: np.ndarray, dof: float = math.inf,
                   interval: np.ndarray | None = None) -> tuple[ValueCi, ValueCi]:
    """Amplitude (N*m) and phase (rad) of an order's phasor ``a cos + b sin`` with their 95 % intervals.

    A phasor resolved from zero gets the normal approximation: the amplitude's interval from the
    covariance ``C`` (N*m^2, scaled for the one-dimensional intervals: 1.96 C's standard deviation is
    the 95 % half-width) along the phasor, the phase's across it. One whose own 95 % region (an
    ellipse: chi-square with 2 degrees of freedom, or Hotelling's T^2 where ``C`` is estimated with
    ``dof`` degrees of freedom: :func:`region_scale`) holds the origin is not resolved from zero,
    and there the approximation fails: an absent order's amplitude is Rayleigh-distributed, and
    amplitude +- 1.96 sigma holds zero for only 85 % of them. Its amplitude's interval is that
    region's reach instead (half-width its largest radius, so the interval holds zero and every
    amplitude the region allows) and its phase gets no bound (+-180 deg). ``interval``: the
    covariance a resolved phasor's two one-dimensional intervals take, where it is not ``C`` (the
    region rests on both directions of the pair, an amplitude or a phase on one: see
    :func:`fit_orders`).
    """
    c = math.hypot(a, b)
    phase = math.atan2(b, a)
    z = np.array([a, b])
    region = region_scale(dof)
    if float(z @ np.linalg.pinv(C) @ z) <= region:
        reach = math.sqrt(region * max(float(np.linalg.eigvalsh(C)[-1]), 0.0))
        return ValueCi(c, reach), ValueCi(phase, math.pi)
    e = amp_phase(a, b, C if interval is None else interval)
    return ValueCi(e.value, e.ci95), ValueCi(e.phase, min(e.phase_ci95, math.pi))


def current_orders(kt_iq: np.ndarray, drift: np.ndarray, e: dict[int, np.ndarray],
                   g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mechanical orders of ``kt * i_q`` (N*m) as the transducer sees them: known air-gap torque.

    The current loop answers the angle estimate's errors at the mechanical orders (the encoder's
    pulse placement) with current, torque the motor's own orders (unbalance, eccentricity) must not
    be credited with. Each order's air-gap phasor is fitted to ``kt_iq`` with the segment's drift
    rows (``drift``) and ``e[h] = exp(i h theta_m)``, then taken through the path and transducer
    response ``g`` (one complex per order, as the orders' own columns).

    Returns
    -------
    known : ndarray
        The orders' torque at the transducer (N*m, per sample).
    residual : ndarray
        ``kt_iq`` less its fitted drift and orders (N*m, air gap): the current's noise, which the
        subtraction carries onto the orders (:func:`order_noise`).
    """
    cols = [drift] + [np.stack([e[h].imag, e[h].real]) for h in ORDERS]
    A = np.concatenate(cols).T
    coef, *_ = np.linalg.lstsq(A, kt_iq, rcond=None)
    nd = drift.shape[0]
    out = np.zeros_like(kt_iq)
    for i, h in enumerate(ORDERS):
        a, b = coef[nd + 2 * i], coef[nd + 2 * i + 1]  # a sin + b cos = Re((b - i a) e^(i h theta_m))
        out += (g[i] * (b - 1j * a) * e[h]).real
    return out, kt_iq - A @ coef


#: an order's noise is measured on the neighbouring frequencies ``h f_m + k / T`` of a segment
#: (T its length; :func:`eol_cal.analysis.fit.model.noise_bins`) less those within NOISE_GAP / T of
#: 0 Hz (the drift polynomial's band), of an order's line (+-h f_m: its leakage) or of a fitted
#: electrical harmonic's (its lack of fit)
NOISE_GAP = 1.5


def order_noise(res: np.ndarray, cur_res: np.ndarray | None, th_m: np.ndarray, t: np.ndarray, w_m: float,
                spec: FitSpec, tau_s: float, path: Callable[[np.ndarray], np.ndarray] | None,
                pole_pairs: int = 0) -> np.ndarray:
    """The white-equivalent noise variance (N*m^2) at each mechanical order of one segment.

    The residual's phasor ``(2 / n) sum e exp(-i (h theta_m + 2 pi k t / T))`` at the order's
    neighbouring frequencies (:func:`~eol_cal.analysis.fit.model.noise_bins`) has, per cos/sin coefficient, the variance
    noise alone puts on the order's pair there; times ``n / 2`` it is the variance of white noise
    that would do the same, which scales the pair's least-squares covariance. With the ECU's
    current taken out (``cur_res``, its residual) its noise reaches the orders through the path
    and transducer response: so here too, bin by bin (the current's noise that reaches the shaft
    cancels, the current sensor's own does not), as the model check measures the 6th's.

    Parameters
    ----------
    res : ndarray
        The segment's torque residual after the joint fit (N*m).
    cur_res : ndarray or None
        ``kt * i_q`` less its drift and orders (N*m), :func:`current_orders`.
    th_m, t : ndarray
        Mechanical angle (rad, the block's frame) and time (s) per sample.
    w_m : float
        The segment's mechanical speed (rad/s, signed).
    spec, tau_s, path
        The fit's transducer model and time constant (s), and the bench's response (None: 1).
    pole_pairs : int
        P/2: the fitted electrical harmonics ``spec.harmonics`` sit at ``h P/2 w_m``; their lines
        are no noise bins either (0: not excluded).

    Returns
    -------
    ndarray, (len(ORDERS),)
        Per order: ``n / 2`` times the mean variance of a coefficient over the bins (N*m^2); the
        residual's own variance for an order without a usable bin.
    """
    n, T = len(t), float(t[-1] - t[0])
    k = noise_bins()
    # the fit's lines (the drift at 0, the orders, the electrical harmonics) hold its lack of fit, not
    # noise: the 6th's, 4-11x the noise beside it on plant motors, sat in order 3's bins at 60 rpm
    # (18 f_m = 3 f_m + 5 / T on eol-default's 1/3 s segments) and widened its interval beyond its errors
    rates = list(ORDERS) + [h * pole_pairs for h in spec.harmonics if pole_pairs]
    lines = np.concatenate([[0.0], np.outer(rates, [w_m, -w_m]).ravel()])
    out = np.empty(len(ORDERS))
    b = 2 * math.pi * (t - t[0]) / T
    rows = bin_steps(b, k).T  # (bins, n), shared by the orders: an order's bins are whole rows
    for i, h in enumerate(ORDERS):
        omega = h * w_m + 2 * math.pi * k / T  # each bin's rate (rad/s, signed)
        ok = np.min(np.abs(omega[:, None] - lines[None, :]), axis=1) >= 2 * math.pi * NOISE_GAP / T
        if not ok.any():
            out[i] = float(res @ res) / n
            continue
        out[i] = line_noise(res, cur_res, h * (th_m - th_m[0]), b, k[ok], omega[ok], spec, tau_s, path,
                            steps=rows[ok].T) * n / 2.0
    return out

def fit_mech(mi: MotorInput, fit: MotorFit, spec: FitSpec, tick_hz: float, threshold: float = SWITCH_MARGIN,
             min_score: float = SWITCH_MIN_SCORE) -> MechResult:
    """The mechanical result of one motor (fingerprint, margin, orders, the block's switch).

    Parameters
    ----------
    mi, fit, spec
        The motor's inputs and its ripple fit (offline frame) with the model it was fitted with.
    tick_hz : float
        The firmware's tick rate (Hz), for the predicted margin.
    threshold, min_score : float
        The least predicted margin and cosine the switch requires: below them the block's
        ``MECH_COMP_ENABLE`` stays off (the block's runtime ``id_margin`` and ``id_min_score`` are
        the firmware's own, ``ID_MARGIN`` and ``ID_MIN_SCORE``).
    """
    N = mi.encoder_ppr
    reasons: list[str] = []
    prints: list[fpr.WindowEdges | None] = [None] * len(mi.captures)
    fp = None
    if mi.frame != "firmware":
        reasons.append("no firmware frame (enc_b missing or the estimator never anchored): no fingerprint")
    elif mi.prints is not None:  # measured with the inputs (measure_firmware_frames)
        prints, fp = mi.prints, mi.fingerprint
    else:
        prints = window_prints(mi)
        fp = fpr.merge_windows(prints, mi.poles, N)
    if fp is None:
        if not reasons:
            reasons.append("no capture window holds a revolution and a half of steady edges: no fingerprint")
        zeros = (0.0,) * (2 * N)
        return MechResult(MECH_OFF, tuple(reasons), zeros, (None,) * (2 * N), 0, 0.0,
                          tuple([None] * len(prints)), 0.0, 0.0, threshold, fpr.REF_RPM, (), min_score)
    # the fingerprint's error measured from its edges (a jackknife over the stretches), not its
    # standard errors (white and pooled over stretches: tens of times its pitch errors' actual error;
    # MECH.md "The switch")
    score, margin = fpr.predicted_margin(fp.fp, fp.sigma, fp.dirs, mi.poles, N, tick_hz,
                                         noise=fpr.split_noise(prints, fp, mi.poles, N))
    if margin < threshold or score < min_score:
        reasons.append(f"fingerprint too weak to identify: predicted margin {margin:.3f} (least {threshold:g}), "
                       f"cosine {score:.3f} (least {min_score:g}) after a revolution at {fpr.REF_RPM:g} rpm")
    orders = fit_orders(mi, fit, spec, prints, fp) if fit.converged else None
    if orders is None:
        reasons.append("mechanical orders not fitted (no segment in an identified window, or the ripple fit did not converge)")
    # the reported standard errors widened for the edges' correlated residuals (AR(1): the rotor's
    # speed ripple within a stretch); the predicted margin above does not use them
    r1 = edge_residual_correlation(fp, prints, mi.poles, N)
    widen = math.sqrt(max(1.0, (1.0 + r1) / max(1.0 - r1, 1e-3)))
    sigma = tuple(None if not math.isfinite(x) else float(x) * widen for x in fp.sigma)
    # a window that could not be placed is left out of the fingerprint and the orders, no reason to switch off
    return MechResult(
        status=MECH_OFF if reasons else MECH_OK, reasons=tuple(reasons),
        fingerprint=tuple(float(x) for x in fp.fp), sigma=sigma, dirs=int(fp.dirs), grid_phase=float(fp.grid_phase),
        windows=tuple(None if w is None else int(w) for w in fp.offsets), score=float(score), margin=float(margin),
        threshold=float(threshold),
        ref_rpm=fpr.REF_RPM, orders=orders or (), min_score=float(min_score))
