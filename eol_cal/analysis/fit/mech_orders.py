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

Intervals: the least-squares covariance of the joint fit, the residual variance scaled by the
residual's lag-one correlation ((1 + r1) / (1 - r1), the samples are not independent).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.analysis import fingerprint as fpr
from eol_cal.analysis.fit import path_gain
from eol_cal.analysis.fit.fp_angle import edge_residual_correlation, window_prints
from eol_cal.analysis.fit.model import legendre_rows, transducer_gain
from eol_cal.analysis.fit.plot import fitted_ripple
from eol_cal.analysis.motor_result import MECH_OFF, MECH_OK, MechOrder, MechResult, ValueCi
from eol_cal.firmware.mech_params import ORDERS, SWITCH_MARGIN, SWITCH_MIN_SCORE

if TYPE_CHECKING:
    from eol_cal.analysis.fit import FitSpec, MotorFit
    from eol_cal.analysis.fit.motor_input import MotorInput

#: z of a two-sided 95 % interval
_Z95 = 1.959963984540054


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
        if seg.kt_iq is not None:
            y = y - current_orders(np.asarray(seg.kt_iq[s], dtype=float), W[:nd], e, g)
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
    res = np.concatenate(res_parts)
    n_coef = nd * len(used) + 2 * H
    r1 = float(np.dot(res[1:], res[:-1]) / max(np.dot(res, res), 1e-300))
    inflate = (1.0 + r1) / max(1.0 - r1, 1e-3)
    s2 = float(res @ res) / max(1, len(res) - n_coef) * max(inflate, 1.0)
    M_inv = np.linalg.inv(M)
    # lack of fit between segments (the main fit's Birge ratio, for the orders): each segment's
    # share of the normal equations at the joint solution, g_s = r_s - M_s sol, has covariance
    # s2 M_s when the model holds; more scatter than that widens the intervals by the ratio. The
    # residual's own variance misses what differs from segment to segment and not from sample to
    # sample (the drift polynomial's misfit to the dyno's speed loop, the ECU's current at each
    # load point): over plant motors the least-squares intervals held the truth for a third of them.
    chi2, dof = 0.0, -2 * H
    for Ms, rs in shares:
        g = rs - Ms @ sol
        w, V = np.linalg.eigh(Ms)
        keep = w > 1e-9 * max(float(w.max()), 1e-300)
        chi2 += float(np.sum((V[:, keep].T @ g) ** 2 / w[keep]))
        dof += int(keep.sum())
    birge = chi2 / dof / s2 if dof >= 1 and s2 > 0 else 1.0
    cov = s2 * max(1.0, birge) * M_inv
    out = []
    for i, h in enumerate(ORDERS):
        a, b = sol[2 * i], sol[2 * i + 1]
        c = math.hypot(a, b)
        phase = math.atan2(b, a)
        C = cov[2 * i: 2 * i + 2, 2 * i: 2 * i + 2]
        u = np.array([math.cos(phase), math.sin(phase)])
        v = np.array([-math.sin(phase), math.cos(phase)])
        sd_c = math.sqrt(max(float(u @ C @ u), 0.0))
        sd_p = math.sqrt(max(float(v @ C @ v), 0.0)) / c if c > 0 else math.pi
        out.append(MechOrder(h, ValueCi(c, _Z95 * sd_c), ValueCi(phase, min(_Z95 * sd_p, math.pi))))
    return tuple(out)


def current_orders(kt_iq: np.ndarray, drift: np.ndarray, e: dict[int, np.ndarray], g: np.ndarray) -> np.ndarray:
    """The mechanical orders of ``kt * i_q`` (N*m) as the transducer sees them: known air-gap torque.

    The current loop answers the angle estimate's errors at the mechanical orders (the encoder's
    pulse placement) with current, torque the motor's own orders (unbalance, eccentricity) must not
    be credited with. Each order's air-gap phasor is fitted to ``kt_iq`` with the segment's drift
    rows (``drift``) and ``e[h] = exp(i h theta_m)``, then taken through the path and transducer
    response ``g`` (one complex per order, as the orders' own columns).
    """
    cols = [drift] + [np.stack([e[h].imag, e[h].real]) for h in ORDERS]
    A = np.concatenate(cols).T
    coef, *_ = np.linalg.lstsq(A, kt_iq, rcond=None)
    nd = drift.shape[0]
    out = np.zeros_like(kt_iq)
    for i, h in enumerate(ORDERS):
        a, b = coef[nd + 2 * i], coef[nd + 2 * i + 1]  # a sin + b cos = Re((b - i a) e^(i h theta_m))
        out += (g[i] * (b - 1j * a) * e[h]).real
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
        The identification margin and least cosine the block will require: below them the
        block's ``MECH_COMP_ENABLE`` stays off.
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
                          tuple([None] * len(prints)), 0.0, 0.0, threshold, fpr.REF_RPM, ())
    score, margin = fpr.predicted_margin(fp.fp, fp.sigma, fp.dirs, mi.poles, N, tick_hz)
    if margin < threshold or score < min_score:
        reasons.append(f"fingerprint too weak to identify: predicted margin {margin:.3f} (least {threshold:g}), "
                       f"cosine {score:.3f} (least {min_score:g}) after a revolution at {fpr.REF_RPM:g} rpm")
    orders = fit_orders(mi, fit, spec, prints, fp) if fit.converged else None
    if orders is None:
        reasons.append("mechanical orders not fitted (no segment in an identified window, or the ripple fit did not converge)")
    # the reported standard errors widened for the edges' correlated residuals (AR(1): the rotor's
    # speed ripple within a stretch); the predicted margin above keeps the fit's own, which the
    # identification threshold was calibrated on
    r1 = edge_residual_correlation(fp, prints, mi.poles, N)
    widen = math.sqrt(max(1.0, (1.0 + r1) / max(1.0 - r1, 1e-3)))
    sigma = tuple(None if not math.isfinite(x) else float(x) * widen for x in fp.sigma)
    # a window that could not be placed is left out of the fingerprint and the orders, no reason to switch off
    return MechResult(
        status=MECH_OFF if reasons else MECH_OK, reasons=tuple(reasons),
        fingerprint=tuple(float(x) for x in fp.fp), sigma=sigma, dirs=int(fp.dirs), grid_phase=float(fp.grid_phase),
        windows=tuple(None if w is None else int(w) for w in fp.offsets), score=float(score), margin=float(margin),
        threshold=float(threshold),
        ref_rpm=fpr.REF_RPM, orders=orders or ())
