"""The encoder's fingerprint measured before the ripple fit, and the fit's angle corrected by it.

The offline angle (:mod:`eol_cal.analysis.angle`) runs through every quadrature edge at its
nominal angle, so it carries the encoder's pitch errors: each edge fires where its magnet pole
actually is, ``nominal + error``. Fitted on that angle, the 6th harmonic is modulated by the
errors (sidebands the segments' finite length leaks back into k6). The fingerprint
(:mod:`eol_cal.analysis.fingerprint`) measures the A edges' errors from the edge times alone,
so before the fit every sample of an identified window gets ``theta + error`` at its position
between edges: the fit then works on the rotor's own angle, in the same frame (the block's,
layout 2) in which the mechanical orders are reported.

The errors' mechanical orders 1..2, which the fingerprint cannot tell from the motion
(:mod:`eol_cal.analysis.fingerprint`), are measured against the halls instead
(:func:`hall_low_orders`): a hall transition and the encoder's angle at its instant are two
position readings of the same rotor, so the motion drops out; the halls' own switching errors
repeat every electrical revolution (one constant per boundary and direction), the encoder's orders
1..2 do not (pole pairs >= 3). Left uncorrected, they move each segment's mean angle by up to
0.1 electrical degree, as each segment covers a different part of a mechanical revolution, and
the 6th's phase six times that: the speed bands and directions then disagree (the model check's
false mismatches, issue 34). Order 0 is a frame offset, the same for every segment. B's edges are
taken to carry the error of the A edge of the same wheel transition a quarter pitch before (B
reads the same wheel: ``eol_cal.firmware.kinematics``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.analysis import fingerprint as fpr
from eol_cal.analysis.angle import nominal_transitions
from eol_cal.analysis.fingerprint_fit import LOW_ORDERS, POLY_DEGREE
from eol_cal.analysis.steady import IQ_TOL_A, IQ_TOL_REL
from eol_cal.numerics.median import median

if TYPE_CHECKING:
    from eol_cal.analysis.fit.motor_input import MotorInput

#: a steady segment's stretch for the fingerprint extends while the speed stays within this
#: fraction of the segment's (the motion only needs to be smooth, not steady: the reverse
#: segments of eol-default settle slowly after their ramp)
EXTEND_TOL = 0.1

#: the encoder errors' mechanical orders measured against the halls: those the fingerprint leaves
#: out but a frame offset (order 0)
HALL_ORDERS = tuple(range(1, LOW_ORDERS + 1))

#: fewest hall transitions per fitted parameter for :func:`hall_low_orders`
MIN_PER_PARAM = 4

#: a hall transition whose residual is this many median absolute deviations out is dropped (a
#: glitch to a neighbouring state); the timing noise of a clean one is bounded (a sample period)
OUTLIER_MADS = 8.0


def fingerprint_ranges(mi: MotorInput, ci: int) -> list[tuple[int, int]]:
    """The stretches of window ``ci`` whose edges the fingerprint uses: each steady segment of the
    fit, extended both ways while the direction and the load point (``iq_ref``) are the segment's
    and the speed within :data:`EXTEND_TOL` of its; overlapping stretches merged
    (:func:`every_fingerprint_range`'s for that window).

    A stretch never spans a load step: the step moves the rotor in a way no stretch's polynomial
    follows, and where the dyno holds the speed within the tolerance through it the speed does not
    show it (two of eol-default's segments merged across one made a fingerprint's error several
    times the other motors', which the split of the stretches did not see: firmware_params/MECH.md).
    """
    return every_fingerprint_range(mi)[ci]


#: samples next to a segment judged in the first round of :func:`every_fingerprint_range` (then
#: four times as many beyond them, and so on, only for the stretches not yet stopped)
FIRST_SPAN = 2048


def every_fingerprint_range(mi: MotorInput) -> list[list[tuple[int, int]]]:
    """:func:`fingerprint_ranges` of every window of ``mi`` (a list per window), the samples of all
    of them judged together (issue 37: not two passes a segment).

    A stretch extends from its segment to the nearest sample that stops it (:func:`_stops`), each
    sample judged against its own segment's median speed and load point, elementwise: the verdict
    it has alone. Only the samples next to each segment are judged, in rounds: :data:`FIRST_SPAN`
    on either side of every segment side by side, then, for the sides not stopped yet, four times
    as many beyond, and so on (each round's nearest stop found by two searches). A long window of
    many segments is judged near its segments, not once for each of them (the 24 segments of one
    continuous 172 000-sample ``eol-cal simulate`` capture judged all its samples 24 times: 13 ms of
    its fit)."""
    omega = [np.asarray(ang.omega_r, dtype=float) for ang in mi.angles]
    iqs = [np.asarray(cap.iq_ref(), dtype=float) for cap in mi.captures]
    segs = list(zip(mi.info, mi.capture_of_segment, strict=True))
    if not segs:
        return [[] for _ in mi.angles]
    ws = [median(omega[ci][info.start:info.stop]) for info, ci in segs]
    judge = [(ws[k], info.i_qo, max(IQ_TOL_A, IQ_TOL_REL * abs(info.i_qo))) for k, (info, _) in enumerate(segs)]
    # each side of each segment: (segment, +1 after / -1 before, the edge its scan goes on from, its bound)
    sides = [(k, d, info.start if d < 0 else info.stop, 0 if d < 0 else len(omega[ci]))
             for k, (info, ci) in enumerate(segs) for d in (-1, 1)]
    found: dict[tuple[int, int], int] = {}  # (segment, side) -> the stretch's end there
    span = FIRST_SPAN
    while sides:
        chunks = [(k, d, edge, bound, max(bound, edge - span) if d < 0 else min(bound, edge + span))
                  for k, d, edge, bound in sides]
        # each chunk [lo, hi) of its window: before a segment (edge - span .. edge), after (edge .. edge + span)
        los = [min(edge, far) for _, _, edge, _, far in chunks]
        sizes = [abs(far - edge) for _, _, edge, _, far in chunks]
        per = np.array([judge[k] for k, *_ in chunks]).reshape(-1, 3)
        at = [np.repeat(per[:, j], sizes) for j in range(3)]
        where = [(segs[k][1], lo, lo + n) for (k, *_), lo, n in zip(chunks, los, sizes, strict=True)]
        stops = np.flatnonzero(_stops(np.concatenate([omega[c][lo:hi] for c, lo, hi in where]),
                                      np.concatenate([iqs[c][lo:hi] for c, lo, hi in where]), *at))
        ends = np.cumsum([0, *sizes])
        last = np.searchsorted(stops, ends[1:]) - 1  # each chunk's last stop, if inside it
        first = np.searchsorted(stops, ends[:-1])  # each chunk's first stop, if inside it
        sides = []
        for j, (k, d, _, bound, far) in enumerate(chunks):
            if d < 0 and last[j] >= 0 and stops[last[j]] >= ends[j]:
                found[k, d] = los[j] + int(stops[last[j]] - ends[j]) + 1
            elif d > 0 and first[j] < len(stops) and stops[first[j]] < ends[j + 1]:
                found[k, d] = los[j] + int(stops[first[j]] - ends[j])
            elif far == bound:
                found[k, d] = bound
            else:
                sides.append((k, d, far, bound))
        span *= 4
    out: list[list[tuple[int, int]]] = [[] for _ in mi.angles]
    for k, (_, ci) in enumerate(segs):
        a, b = found[k, -1], found[k, 1]
        got = out[ci]
        if got and a <= got[-1][1]:
            got[-1] = (got[-1][0], max(got[-1][1], b))
        else:
            got.append((a, b))
    return out


def _stops(w: np.ndarray, iq: np.ndarray, ws: np.ndarray | float, i_qo: np.ndarray | float,
           iq_tol: np.ndarray | float) -> np.ndarray:
    """Which samples end a fingerprint stretch (:func:`fingerprint_ranges`) of a segment of median
    speed ``ws`` (rad/s) and load point ``i_qo`` (A): another direction, a speed beyond
    :data:`EXTEND_TOL` of the segment's, or the load point beyond ``iq_tol`` (A) of its (each a
    value, or one a sample)."""
    bad = ~((np.sign(w) == np.sign(ws)) & (np.abs(w - ws) <= EXTEND_TOL * np.abs(ws)))
    # ... nor while the load point differs from the segment's beyond the steady segments' own
    # tolerance: a load step ends a stretch
    bad |= np.abs(iq - i_qo) > iq_tol
    return bad


def window_prints(mi: MotorInput) -> list[fpr.WindowEdges | None]:
    """Each capture window's edges over its fingerprint stretches (None: no usable one)."""
    out: list[fpr.WindowEdges | None] = []
    for cap, ang, ranges in zip(mi.captures, mi.angles, every_fingerprint_range(mi), strict=True):
        if not ranges or not cap.has("enc_b"):
            out.append(None)
            continue
        theta_fw = np.asarray(ang.theta_r, dtype=float) + mi.frame_offset_rad
        out.append(fpr.window_edges(cap.t, cap["enc_a"], cap["enc_b"], theta_fw, mi.poles, mi.encoder_ppr, ranges))
    return out


def boundary_errors(fp: np.ndarray, N: int) -> np.ndarray:
    """The error of every quadrature boundary ``k`` of the frame (4N,), rad electrical, from the
    fingerprint's A edges: ``4m+1`` (A rising forward) and ``4m+2`` (B, the same transition a
    quarter pitch later) carry ``fp[2m]``, ``4m+3`` and ``4m+4`` carry ``fp[2m+1]``."""
    f = np.asarray(fp, dtype=float).reshape(N, 2)
    out = np.empty((N, 4))
    out[:, 1] = out[:, 2] = f[:, 0]
    out[:, 3] = f[:, 1]
    out[:, 0] = np.roll(f[:, 1], 1)  # boundary 4m is 4(m-1)+4
    return out.reshape(-1)


def boundary_position(q: np.ndarray, r: int | np.ndarray, grid_phase: float, theta_fw: np.ndarray, poles: int,
                      N: int) -> np.ndarray:
    """Each sample's position ``x`` in the block's frame, in quadrature boundaries (unwrapped:
    boundary ``k`` at ``x = k``), from its window count ``q``, the window's offset ``r`` (pulses;
    or one per sample, the samples of several windows), the frame's grid phase (rad) and the
    firmware-frame angle ``theta_fw`` (rad electrical), which places it between its boundaries."""
    quarter = poles * math.pi / N / 4.0
    k = np.asarray(q, dtype=np.int64) + 4 * np.asarray(r, dtype=np.int64)
    Ek = grid_phase + k * quarter
    return k + np.remainder(np.asarray(theta_fw, dtype=float) - Ek + math.pi, 2 * math.pi) / quarter - math.pi / quarter


def boundary_interp(x: np.ndarray, fp: np.ndarray, N: int) -> np.ndarray:
    """The boundary errors (:func:`boundary_errors`, rad electrical) interpolated linearly at positions ``x``."""
    return _interp_table(fp, N)(x)


def _interp_table(fp: np.ndarray, N: int) -> Callable[[np.ndarray], np.ndarray]:
    """:func:`boundary_interp` of ``fp`` as a function of ``x``: the table built once for every
    segment of a motor."""
    M = 4 * N
    err = boundary_errors(fp, N)
    xp, yp = np.arange(M + 1), np.append(err, err[0])
    return lambda x: np.interp(np.mod(x, M), xp, yp)


def bracketing_samples(t: np.ndarray, t_q: np.ndarray) -> np.ndarray:
    """The samples of increasing ``t`` that ``np.interp(t_q, t, f)`` reads: the two around each of
    ``t_q`` and both ends. ``np.interp(t_q, t[i], f[i])`` is then ``np.interp(t_q, t, f)`` bit for bit
    (the same pair, the same arithmetic), with ``f`` computed at those samples only."""
    j = np.clip(np.searchsorted(t, t_q, side="right") - 1, 0, len(t) - 1)
    return np.unique(np.concatenate(([0, len(t) - 1], j, np.minimum(j + 1, len(t) - 1))))


def order_columns(x: np.ndarray, orders: tuple[int, ...], N: int) -> np.ndarray:
    """``cos(m phi), sin(m phi)`` per order ``m`` (columns, in that order) at positions ``x``
    (quadrature boundaries), ``phi = 2 pi x / (4 N)`` the mechanical angle from boundary 0."""
    phi = 2.0 * math.pi * np.asarray(x, dtype=float) / (4 * N)
    out = np.empty((len(phi), 2 * len(orders)))
    if not orders:
        return out
    # the orders as powers of one exp(i phi) a sample (a complex product each, not a cos and a sin:
    # half a refit's time of the angle correction; the same values within 3e-16)
    z = np.exp(1j * phi)
    zm = z
    for m in range(1, max(orders) + 1):
        if m > 1:
            zm = zm * z
        if m in orders:
            j = 2 * orders.index(m)
            out[:, j], out[:, j + 1] = zm.real, zm.imag
    return out


def hall_low_orders(mi: MotorInput, prints: list[fpr.WindowEdges | None], fp: fpr.Fingerprint
                    ) -> tuple[tuple[int, ...], np.ndarray, np.ndarray, int] | str:
    """The encoder errors' mechanical orders :data:`HALL_ORDERS` (those the fingerprint cannot see),
    measured on the placed windows' hall transitions.

    At each transition the encoder's angle (the offline angle, the fingerprint's correction added)
    less the boundary's nominal angle is the hall's switching error, the same every electrical
    revolution (a constant per boundary and direction: hysteresis included), less the encoder's
    low orders at that mechanical angle; least squares over both, the windows together (each in
    the block's frame: its hall-anchored fraction taken out, as for its segments), so that windows
    shorter than a mechanical revolution add up to one. The rotor's motion is in neither reading.
    An order that is a multiple of the pole pairs repeats every electrical revolution like the
    halls' errors and cannot be told from them: left out. Assumed: the halls' switching points
    repeat every electrical revolution (the contract's hall table; a magnet's pole-to-pole
    tolerance would put mechanical orders into them, which this would take for the encoder's).

    Returns ``(orders, coef, cov, n)``: ``coef`` (2 per order: cos, sin; rad electrical) such that
    ``order_columns(x) @ coef`` is what to subtract from the angle at positions ``x``, its
    covariance, and the transitions used; or, when it cannot be measured, why not.
    """
    pp = mi.poles // 2
    orders = tuple(m for m in HALL_ORDERS if m % pp)
    if not orders:
        return f"orders {HALL_ORDERS} repeat every electrical revolution ({pp} pole pairs): not separable from the halls"
    N = mi.encoder_ppr
    xs, angles, nominals, groups = [], [], [], []
    for ci, (cap, ang, edges, r) in enumerate(zip(mi.captures, mi.angles, prints, fp.offsets, strict=True)):
        if edges is None or r is None:
            continue
        t = np.asarray(cap.t, dtype=float)
        t_h, nominal, direction, begins = nominal_transitions(cap, ang)
        inside = (t_h >= max(ang.t_span[0], t[0])) & (t_h <= min(ang.t_span[1], t[-1]))
        t_h, nominal, direction, begins = t_h[inside], nominal[inside], direction[inside], begins[inside]
        frac = mi.window_frac[ci] if mi.window_frac else 0.0
        # the positions at the transitions only: from the samples around each (not the window's every sample)
        i = bracketing_samples(t, t_h)
        theta = np.asarray(ang.theta_r, dtype=float)[i] - frac
        x = np.interp(t_h, t[i], boundary_position(edges.q[i], r, fp.grid_phase, theta + mi.frame_offset_rad,
                                                   mi.poles, N))
        xs.append(x)
        angles.append(np.interp(t_h, t[i], theta))
        nominals.append(nominal)
        groups.append(2 * (begins - 1) + (direction < 0))
    if not xs:
        return "no placed window"
    x, g = np.concatenate(xs), np.concatenate(groups)
    # the fingerprint's correction at every window's transitions at once (elementwise: each value as alone)
    y = np.concatenate(angles) + boundary_interp(x, fp.fp, N) - np.concatenate(nominals)
    y = np.angle(np.exp(1j * (y - np.angle(np.mean(np.exp(1j * y))))))
    got = _orders_lstsq(x, y, g, orders, N)
    if isinstance(got, str):
        return got
    # a hall glitch to a neighbouring state is a transition far from its boundary: out, and again
    res = got[2]
    mad = median(np.abs(res - median(res)))
    keep = np.abs(res) <= OUTLIER_MADS * max(mad, 1e-9)
    if not keep.all():
        got = _orders_lstsq(x[keep], y[keep], g[keep], orders, N)
        if isinstance(got, str):
            return got
    return orders, got[0], got[1], len(got[2])


def _orders_lstsq(x: np.ndarray, y: np.ndarray, g: np.ndarray, orders: tuple[int, ...], N: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """:func:`hall_low_orders`' least squares: a constant per group ``g`` and the orders' columns at
    ``x``; ``(the orders' coefficients, their covariance, the residuals)`` or why it cannot."""
    _, gi = np.unique(g, return_inverse=True)
    ng = int(gi.max()) + 1
    X = np.hstack([np.eye(ng)[gi], order_columns(x, orders, N)])
    n, p = X.shape
    if n < MIN_PER_PARAM * p:
        return f"{n} hall transitions for {p} parameters (at least {MIN_PER_PARAM} a parameter)"
    Q, R = np.linalg.qr(X)
    if np.linalg.matrix_rank(R) < p:
        return f"the {n} hall transitions do not span the mechanical revolution"
    beta = np.linalg.solve(R, Q.T @ y)
    res = y - X @ beta
    Rinv = np.linalg.inv(R)
    cov = float(res @ res) / (n - p) * (Rinv @ Rinv.T)
    return beta[ng:], cov[ng:, ng:], res


def measure_fingerprint(mi: MotorInput) -> None:
    """Measure the motor's fingerprint (set ``mi.prints``, ``mi.fingerprint``) and correct the
    angle of every segment in a window it placed (``mi.segments.theta``; ``mi.angle_correction``
    says what was done, or why not). Needs the firmware frame (:func:`measure_firmware_frames`)."""
    if mi.frame != "firmware":
        mi.angle_correction = "none: no firmware frame, no fingerprint"
        return
    prints = window_prints(mi)
    fp = fpr.merge_windows(prints, mi.poles, mi.encoder_ppr)
    mi.prints, mi.fingerprint = prints, fp
    if fp is None:
        mi.angle_correction = "none: no window holds a revolution and a half of steady edges"
        return
    if fp.dirs != 3:
        # one half only: the other's boundaries would be corrected by zeros, half of each pitch wrong
        mi.angle_correction = "none: the fingerprint holds one edge direction only"
        return
    seg = mi.segments
    # each window's angle is anchored on its own halls: windows of one dyno capture sit a
    # fraction of a degree apart, which moves the 6th's phase from window to window. The count
    # puts them in one frame: a placed window's grid phase is the block's plus its offset in
    # pulses plus that fraction (``scores[w][0]``), which is taken out of its angle here (and out
    # of its part of the firmware frame offset, measured against the angle before)
    frac = [0.0 if sc is None or r is None else float(sc[0]) for sc, r in zip(fp.scores or [None] * len(prints),
                                                                             fp.offsets, strict=True)]
    mi.window_frac = frac
    low = hall_low_orders(mi, prints, fp)
    n = _correct_segments(mi, prints, fp, frac, None if isinstance(low, str) else low[:2])
    if mi.frame_parts is not None and any(frac):
        total = sum(part[0] * np.exp(1j * frac[ci]) for ci, part in enumerate(mi.frame_parts) if part is not None)
        mi.frame_offset_rad = float(np.angle(total))
    aligned = sum(1 for f, r in zip(frac, fp.offsets, strict=True) if r is not None)
    if isinstance(low, str):
        lows = f"its mechanical orders {', '.join(map(str, HALL_ORDERS))} not corrected: {low}"
    else:
        pp = mi.poles // 2
        amp = ", ".join(f"{m}: {math.degrees(math.hypot(*low[1][2 * j:2 * j + 2])) / pp:.4f}"
                        for j, m in enumerate(low[0]))
        lows = f"its mechanical orders from {low[3]} hall transitions (mech deg {amp})"
    mi.angle_correction = (f"fingerprint ({n} of {seg.n_segments} segments, {aligned} window(s) in one frame; "
                           f"{lows})")


def _correct_segments(mi: MotorInput, prints: list[fpr.WindowEdges | None], fp: fpr.Fingerprint, frac: list[float],
                      low: tuple[tuple[int, ...], np.ndarray] | None) -> int:
    """Correct the angle of every segment in a placed window (``mi.segments.theta``, in place):
    its window's fraction ``frac`` (rad) taken out, the fingerprint's boundary errors and the
    orders ``low`` (orders, coefficients; None: not measured) at each sample's position added.
    Returns how many segments it corrected.

    The segments' samples in one pass (issue 37: one call of each step for the serial, not one a
    segment; every step elementwise, so each sample's value is the one it had alone), but the
    orders' product, one a segment on its own rows (a matrix product's last bits may depend on
    its height)."""
    seg = mi.segments
    todo = [(s, info, mi.capture_of_segment[s]) for s, info in enumerate(mi.info)
            if prints[mi.capture_of_segment[s]] is not None and fp.offsets[mi.capture_of_segment[s]] is not None]
    if not todo:
        return 0
    thetas = [np.asarray(seg.theta[s], dtype=float) - frac[ci] for s, _, ci in todo]
    sizes = [len(th) for th in thetas]
    q = np.concatenate([prints[ci].q[info.start:info.stop] for _, info, ci in todo])  # type: ignore[union-attr]
    r = np.repeat(np.array([fp.offsets[ci] for _, _, ci in todo], dtype=np.int64), sizes)
    x = boundary_position(q, r, fp.grid_phase, np.concatenate(thetas) + mi.frame_offset_rad, mi.poles,
                          mi.encoder_ppr)
    corr = _interp_table(fp.fp, mi.encoder_ppr)(x)
    cols = None if low is None else order_columns(x, low[0], mi.encoder_ppr)
    ends = np.cumsum([0, *sizes]).tolist()
    for j, (s, _, _) in enumerate(todo):
        c = corr[ends[j]:ends[j + 1]]
        if cols is not None and low is not None:
            c = c - cols[ends[j]:ends[j + 1]] @ low[1]
        seg.theta[s] = thetas[j] + c
    return len(todo)


def edge_residual_correlation(fp: fpr.Fingerprint, prints: list[fpr.WindowEdges | None], poles: int, N: int) -> float:
    """Lag-one correlation of the fingerprint fit's edge residuals, pooled over every stretch of the
    placed windows (each stretch: the edges' nominal angles plus their fitted errors, less the
    stretch's polynomial motion). The fit's standard errors take the residuals as independent;
    the rotor's speed ripple within a stretch, which the polynomial cannot follow, makes
    neighbouring edges' residuals alike."""
    quarter = poles * math.pi / N / 4.0
    num = den = 0.0
    for w, r in zip(prints, fp.offsets, strict=True):
        if w is None or r is None:
            continue
        for times, k in w.stretches:
            kk = k + 4 * r
            idx = 2 * ((kk >> 2) % N) + ((kk >> 1) & 1)
            halves_ok = np.isfinite(fp.sigma[idx])
            if halves_ok.sum() < 2 * (POLY_DEGREE + 2):
                continue
            t, kk, idx = times[halves_ok], kk[halves_ok], idx[halves_ok]
            x = (t - t[0]) / max(t[-1] - t[0], 1e-12) * 2.0 - 1.0
            Q, _ = np.linalg.qr(np.polynomial.legendre.legvander(x, POLY_DEGREE))
            y = (kk - kk[0]) * quarter + fp.fp[idx]
            res = y - Q @ (Q.T @ y)
            num += float(res[1:] @ res[:-1])
            den += float(res @ res)
    return num / den if den > 0 else 0.0


def frame_sd(mi: MotorInput) -> float:
    """Standard error of the firmware frame offset (rad electrical) from the scatter of its parts:
    each window's own offset (its estimator against its angle, in the common frame when the windows
    were put in one), weighted by its samples, over the effective number of windows. With one
    window its segments are the parts: the estimator's lag moves with speed, so its frame differs
    from segment to segment (60 rpm against 120 rpm: +-0.1 deg electrical on plant motors), and
    how far the offset recomputed from the capture sits from the ECU's own is as uncertain as
    their scatter says (bench/bench_coverage.py: the frame's error 0.025 deg sd over 80 motors,
    the segments' standard error 0.015-0.04; left out, phase_k6's interval covered 80 %). 0 with
    one part."""
    parts = [(ci, p) for ci, p in enumerate(mi.frame_parts or []) if p is not None and p[1] > 0]
    frac = mi.window_frac or [0.0] * len(mi.frame_parts or [])
    if len(parts) == 1 and mi.frame_segment_parts is not None:
        ci = parts[0][0]
        # one window: its fraction moves every segment alike (no scatter of its own)
        parts = [(ci, p) for p in mi.frame_segment_parts[ci] or [] if p[1] > 0]
    if len(parts) < 2:
        return 0.0
    n = np.array([p[1] for _, p in parts], dtype=float)
    fo = np.array([np.angle(p[0]) + frac[ci] for ci, p in parts])
    d = np.angle(np.exp(1j * (fo - mi.frame_offset_rad)))
    n_eff = n.sum() ** 2 / float((n * n).sum())
    var = float((n * d * d).sum() / n.sum()) * n_eff / max(n_eff - 1.0, 1.0)
    return math.sqrt(var / n_eff)
