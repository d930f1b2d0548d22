"""The mechanical fit before and after the refit's speed-up, side by side on the same inputs:
the fingerprint (values, sigma, directions, grid phase, offsets, scores), the joint fit's
residual (every placement trial and the final fit) and the mechanical orders (values and 95 %
intervals) must agree to ``--tol`` (relative, default 1e-9).

    python bench/check_mech_fit.py [--serials 24] [--no-motors]

Inputs: ``fit_mech``'s arguments recorded while fitting the lot of ``bench/bench_refit.py``
(``--serials`` serials) and the motors of tests/test_fit_mech.py (two plant motors on
eol-default, and the first one's capture cut into windows, as a dyno records it). The code before
(``joint_fit`` as a per-stretch projection redone for every trial, ``fit_orders`` as one
dense least squares, ``fitted_ripple`` one sine per part) is kept here, not in the library,
only for this comparison.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.analysis import fingerprint as fpr
from eol_cal.analysis.fingerprint_fit import LOW_ORDERS, POLY_DEGREE, joint_fit, low_order_complement  # noqa: F401
from eol_cal.analysis.fit import mech_orders as M
from eol_cal.analysis.fit.model import Z95
from eol_cal.analysis.motor_result import MechOrder, ValueCi
from eol_cal.firmware.mech_params import ORDERS

if TYPE_CHECKING:
    from eol_cal.analysis.fit import FitSpec, MotorFit
    from eol_cal.analysis.fit.motor_input import MotorInput

WindowEdges = fpr.WindowEdges

# ------------------------------------------------------------------------------------------
# the code before (main c92ccc8), verbatim but for the names


def old_joint_fit(stretches: list[tuple[np.ndarray, np.ndarray]], N: int, quarter: float, cov: bool = True):
    """Least squares of the edge errors shared by every stretch (each its own polynomial motion).

    ``stretches`` hold (times, A boundaries k in the common frame); edge ``k`` is fingerprint entry
    ``(k >> 1) mod 2N``: forward half (``k = 4m + 1``) and reverse half (``4m + 3``). Returns
    ``(fp (2N,), var (2N,), rss, dirs, dof)``; a half with a pulse never seen, or fewer than 1.25
    revolutions of edges, is left out (NaN entries, not in ``dirs``); ``dof`` = edges - unknowns.
    ``cov=False`` skips the variances (NaN): a placement trial needs the residual only.

    Each stretch's polynomial is projected out of its edges (Frisch-Waugh): the errors' normal
    equations are then ``(nF * dirs)`` square, summed per pulse from the edges, and cost
    O(edges x degree) instead of a dense edges x unknowns least squares (which took 90 % of a
    refit's CPU); the solution, the residual and the errors' covariance are the same.
    """
    from eol_cal.firmware.mech_params import FP_FORWARD

    P = low_order_complement(N)
    nF = P.shape[1]
    allk = np.concatenate([k for _, k in stretches]) if stretches else np.zeros(0, np.int64)

    def covered(d):
        kk = allk[((allk >> 1) & 1) == d]
        seen = np.bincount((kk >> 2) % N, minlength=N)
        return seen.min() >= 1 and seen.sum() >= N + N // 4

    dirs = [d for d in (0, 1) if covered(d)]
    if not dirs:
        return None
    nd = len(dirs)
    counts = np.zeros(nd * N)   # edges per (direction slot, pulse)
    r = np.zeros(nd * N)        # their motion-free angles summed per (slot, pulse)
    G = np.zeros((nd * nF, nd * nF))
    parts = []
    n_rows = 0
    for times, k in stretches:
        keep = np.isin((k >> 1) & 1, dirs)
        times, k = times[keep], k[keep]
        if not len(times):
            continue
        n_rows += len(times)
        x = (times - times[0]) / max(times[-1] - times[0], 1e-12) * 2.0 - 1.0
        Q, _ = np.linalg.qr(np.polynomial.legendre.legvander(x, POLY_DEGREE))
        phi = k * quarter
        phi_res = phi - Q @ (Q.T @ phi)
        idx = np.searchsorted(dirs, (k >> 1) & 1) * N + (k >> 2) % N
        counts += np.bincount(idx, minlength=nd * N)
        r += np.bincount(idx, weights=phi_res, minlength=nd * N)
        S = np.stack([np.bincount(idx, weights=Q[:, j], minlength=nd * N) for j in range(Q.shape[1])], axis=1)
        T = np.concatenate([P.T @ S[i * N:(i + 1) * N] for i in range(nd)])
        G -= T @ T.T
        parts.append((Q, idx, phi_res))
    rhs = np.zeros(nd * nF)
    for i in range(nd):
        s = slice(i * nF, (i + 1) * nF)
        G[s, s] += P.T @ (counts[i * N:(i + 1) * N, None] * P)
        rhs[s] = -P.T @ r[i * N:(i + 1) * N]
    try:
        G_inv = np.linalg.inv(G)
    except np.linalg.LinAlgError:
        G_inv = np.linalg.pinv(G)
    sol = G_inv @ rhs
    err = np.concatenate([P @ sol[i * nF:(i + 1) * nF] for i in range(nd)])  # per (slot, pulse)
    rss = 0.0
    for Q, idx, phi_res in parts:
        e = err[idx]
        res = phi_res + e - Q @ (Q.T @ e)
        rss += float(res @ res)
    dof = n_rows - ((POLY_DEGREE + 1) * len(stretches) + nF * nd)
    fp = np.full(2 * N, np.nan)
    var = np.full(2 * N, np.nan)
    C = rss / max(1, dof) * G_inv if cov else None
    for i, d in enumerate(dirs):
        fp[d::2] = err[i * N:(i + 1) * N]
        if C is not None:
            s = slice(i * nF, (i + 1) * nF)
            var[d::2] = np.einsum("ij,jk,ik->i", P, C[s, s], P)
    return fp, var, rss, sum(FP_FORWARD << d for d in dirs), dof



def old_merge_windows(windows: Sequence[WindowEdges | None], poles: int, N: int, min_ratio: float = 2.0,
                  frac_tol: float = math.radians(2.0)) -> fpr.Fingerprint | None:
    """The fingerprint of every window's edges in one frame: the window with most edges' (None
    when no window, or no direction, holds a revolution and a half of edges).

    Each other window is placed by the halls and the fingerprint together: of the P/2 offsets its
    grid phase allows (one per pole pair), the one whose joint fit leaves the smallest residual,
    when it agrees with the halls' fraction within ``frac_tol`` and the next offset's residual is
    ``min_ratio`` times larger; otherwise the window is left out (its offset None).
    """
    usable = [i for i, w in enumerate(windows) if w is not None]
    if not usable:
        return None
    ref = max(usable, key=lambda i: windows[i].n_edges)
    quarter = poles * math.pi / N / 4.0
    delta = 4 * quarter
    offsets: list[int | None] = [None] * len(windows)
    scores: list[tuple[float, float] | None] = [None] * len(windows)
    offsets[ref] = 0
    placed = list(windows[ref].stretches)
    todo = [i for i in sorted(usable, key=lambda j: -windows[j].n_edges) if i != ref]
    changed = True
    while todo and changed:  # a window that overlaps nothing placed yet may overlap what later windows add
        changed = False
        for i in list(todo):
            placement = old_place(windows[i], windows[ref].grid_phase, placed, poles, N, quarter, delta,
                               min_ratio, frac_tol)
            if placement is None:
                continue
            r, moved, score = placement
            scores[i] = score
            if r is not None:
                offsets[i] = r
                placed += moved
                todo.remove(i)
                changed = True
    fit = old_joint_fit(placed, N, quarter)
    if fit is None:
        return None
    fp, var, _, dirs, _ = fit
    sigma = np.sqrt(np.where(np.isfinite(var), np.maximum(var, 0.0), np.inf))
    for d in (0, 1):
        if dirs & (1 << d):
            fp[d::2] -= fp[d::2].mean()
        else:
            fp[d::2], sigma[d::2] = 0.0, np.inf
    return fpr.Fingerprint(fp, sigma, dirs, windows[ref].grid_phase, offsets, scores)


def old_place(w: WindowEdges, ref_phase: float, placed: list, poles: int, N: int, quarter: float, delta: float,
           min_ratio: float, frac_tol: float):
    """Where window ``w`` goes in the frame of the windows ``placed``: ``(r or None, its stretches
    moved there, (fraction error rad, residual ratio))``.

    The halls allow one offset per pole pair (the ``grid_phase`` difference); the one within
    ``frac_tol`` of its fraction is taken unless the fingerprint contradicts it: a joint fit with
    enough data to tell (N/2 more edges than unknowns) in which another offset leaves a residual
    ``min_ratio`` times smaller. Several offsets within ``frac_tol`` (pulses that divide evenly among
    the pole pairs) need the fingerprint to prefer one by ``min_ratio``.
    """
    dg = (w.grid_phase - ref_phase) % (2 * math.pi)
    trials = []
    for j in range(poles // 2):
        r = int(math.floor((dg + 2 * math.pi * j) / delta + 0.5)) % N
        e = math.remainder(dg - r * delta, 2 * math.pi)
        moved = [(t, k + 4 * r) for t, k in w.stretches]
        fit = old_joint_fit(placed + moved, N, quarter, cov=False)
        rss = fit[2] if fit is not None and fit[4] >= N // 2 else math.nan
        trials.append((rss, r, e, moved))
    frac_ok = sorted((x for x in trials if abs(x[2]) <= frac_tol), key=lambda x: abs(x[2]))
    if not frac_ok:
        return None, [], (float(min(abs(x[2]) for x in trials)), math.nan)
    told = [x for x in trials if math.isfinite(x[0])]
    if len(frac_ok) > 1:
        cands = sorted((x for x in frac_ok if math.isfinite(x[0])), key=lambda x: x[0])
        if len(cands) < 2 or cands[1][0] < min_ratio * cands[0][0]:
            return None, [], (float(frac_ok[0][2]), math.nan)  # neither the halls nor the fingerprint can tell
        best = cands[0]
    else:
        best = frac_ok[0]
    others = [x[0] for x in told if x is not best]
    ratio = min(others) / max(best[0], 1e-300) if others and math.isfinite(best[0]) else math.nan
    if math.isfinite(ratio) and ratio * min_ratio <= 1.0:
        return None, [], (float(best[2]), float(ratio))  # the fingerprint contradicts the halls
    return best[1], best[3], (float(best[2]), float(ratio))



def old_fitted_ripple(mi: MotorInput, fit: MotorFit, spec: FitSpec, s: int, theta: np.ndarray,
                  gains: np.ndarray | None = None) -> np.ndarray:
    """T_avg and the fitted ripple of segment ``s`` as the transducer sees it, at angles ``theta``.

    Parameters
    ----------
    mi, fit, spec
        The motor's inputs, its fit and the model it was fitted with.
    s : int
        Segment index.
    theta : ndarray
        Electrical angles (rad).
    gains : ndarray, optional
        :func:`eol_cal.analysis.fit.path_gain` of the segments (computed when not given).

    Returns
    -------
    ndarray
        Torque (N*m): through the bench's response and the transducer's lag at the segment's
        speed, as in the fit's own model.
    """
    from eol_cal.analysis.fit import path_gain

    seg = mi.segments
    gains = path_gain(seg, spec) if gains is None else gains
    curve = np.full_like(np.asarray(theta, dtype=float), fit.t_avg[s])
    for h, parts in fit.harmonics.items():
        a = h * seg.omega_e[s] * fit.delay_s
        gain = 1.0 / (1.0 + 1j * a) if spec.transducer == "lowpass" else np.exp(-1j * a)
        gain *= gains[s, spec.harmonics.index(h)]
        arg = h * theta + np.angle(gain)
        if "c" in parts:
            curve -= abs(gain) * parts["c"].value * np.sin(arg + parts["c"].phase)
        if "k" in parts:
            curve -= abs(gain) * parts["k"].value * seg.i_qo[s] * np.sin(arg + parts["k"].phase)
    return curve



def old_fit_orders(mi: MotorInput, fit: MotorFit, spec: FitSpec, prints: list[fpr.WindowEdges | None],
               fp: fpr.Fingerprint) -> tuple[MechOrder, ...] | None:
    """Mechanical orders 1..3 (N*m, phase in the block's mechanical frame) from the segments of
    the identified windows; None when no segment's window is identified."""
    from eol_cal.analysis.fit.model import legendre_rows
    from eol_cal.analysis.fit import path_gain

    seg = mi.segments
    pp = seg.pole_pairs
    H = len(ORDERS)
    deg = spec.drift_degree
    blocks, rhs = [], []
    gains6 = path_gain(seg, spec)
    used = [s for s in range(seg.n_segments) if fp.offsets[mi.capture_of_segment[s]] is not None]
    if not used:
        return None
    nb = (deg + 1) * len(used)
    for j, s in enumerate(used):
        ci = mi.capture_of_segment[s]
        info = mi.info[s]
        theta = np.asarray(seg.theta[s], dtype=float)
        y = np.asarray(seg.torque[s], dtype=float) - old_fitted_ripple(mi, fit, spec, s, theta, gains6)
        q = prints[ci].q[info.start:info.stop]
        th_m = fpr.block_frame_mech_angle(q, fp.offsets[ci], fp.grid_phase, theta + mi.frame_offset_rad,
                                          mi.poles, mi.encoder_ppr)
        w_m = seg.omega_e[s] / pp
        freqs = np.asarray(ORDERS, dtype=float) * w_m
        g = 1.0 / (1.0 + 1j * freqs * fit.delay_s) if spec.transducer == "lowpass" else np.exp(-1j * freqs * fit.delay_s)
        if seg.path_response is not None:
            g = g * np.asarray(seg.path_response(freqs), dtype=complex)
        t = np.asarray(seg.t[s], dtype=float)
        X = np.zeros((len(t), nb + 2 * H))
        legt = np.empty((deg + 1, len(t)))
        legendre_rows((t - t[0]) * (2.0 / max(t[-1] - t[0], 1e-12)) - 1.0, deg, legt)
        X[:, j * (deg + 1):(j + 1) * (deg + 1)] = legt.T
        for i, h in enumerate(ORDERS):
            arg = h * th_m + np.angle(g[i])
            # the ripple -c sin(h th + phase) = -(A sin(h th) + B cos(h th)), A = c cos phase, B = c sin phase
            X[:, nb + 2 * i] = -abs(g[i]) * np.sin(arg)
            X[:, nb + 2 * i + 1] = -abs(g[i]) * np.cos(arg)
        blocks.append(X)
        rhs.append(y)
    X = np.concatenate(blocks)
    y = np.concatenate(rhs)
    XtX = X.T @ X
    sol = np.linalg.solve(XtX, X.T @ y)
    res = y - X @ sol
    r1 = float(np.dot(res[1:], res[:-1]) / max(np.dot(res, res), 1e-300))
    inflate = (1.0 + r1) / max(1.0 - r1, 1e-3)
    s2 = float(res @ res) / max(1, len(y) - X.shape[1]) * max(inflate, 1.0)
    cov = s2 * np.linalg.inv(XtX)
    out = []
    for i, h in enumerate(ORDERS):
        a, b = sol[nb + 2 * i], sol[nb + 2 * i + 1]
        c = math.hypot(a, b)
        phase = math.atan2(b, a)
        C = cov[nb + 2 * i: nb + 2 * i + 2, nb + 2 * i: nb + 2 * i + 2]
        u = np.array([math.cos(phase), math.sin(phase)])
        v = np.array([-math.sin(phase), math.cos(phase)])
        sd_c = math.sqrt(max(float(u @ C @ u), 0.0))
        sd_p = math.sqrt(max(float(v @ C @ v), 0.0)) / c if c > 0 else math.pi
        out.append(MechOrder(h, ValueCi(c, Z95 * sd_c), ValueCi(phase, min(Z95 * sd_p, math.pi))))
    return tuple(out)



# ------------------------------------------------------------------------------------------
# the inputs


def _recording(run) -> list[tuple]:
    """fit_mech's arguments for every motor ``run()`` fits."""
    rec = []
    orig = M.fit_mech

    def spy(mi, fit, spec, tick_hz, *a, **k):
        rec.append((mi, fit, spec, tick_hz))
        return orig(mi, fit, spec, tick_hz, *a, **k)

    M.fit_mech = spy
    try:
        run()
    finally:
        M.fit_mech = orig
    return rec


def lot_inputs(n: int) -> list[tuple]:
    from bench_refit import make_lot

    from eol_cal.lot import refit

    def run():
        with tempfile.TemporaryDirectory() as d:
            rows = refit.refit_serials(make_lot(Path(d), n), bench="none")
            bad = [r["error"] for r in rows if r["error"]]
            if bad:
                raise RuntimeError(bad[0])

    return _recording(run)


def motor_inputs() -> list[tuple]:
    """The motors of tests/test_fit_mech.py (its fixture and its dyno windows), fitted the same way."""
    from eol_cal.analysis.fit import FitSpec
    from eol_cal.analysis.fit.motors import FitOptions, fit_motors
    from eol_cal.plant.profile import load_profile

    from eol_cal.sim.mech_motors import BEST, station_runs, station_windows

    _, runs = station_runs()
    joined = station_windows(runs[0].capture, load_profile("eol-default"))

    def run():
        fit_motors([r.capture for r in runs], FitOptions(spec=FitSpec(), capture_metrics=False, estimator_options=BEST))
        fit_motors([joined], FitOptions(capture_metrics=False, estimator_options=BEST))

    return _recording(run)


# ------------------------------------------------------------------------------------------
# the comparison


def _rel(new, old) -> float:
    """Largest difference relative to the largest magnitude (inf where finite-ness differs)."""
    a, b = np.asarray(new, dtype=float), np.asarray(old, dtype=float)
    if a.shape != b.shape or not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return math.inf
    f = np.isfinite(b)
    if not f.any():
        return 0.0
    scale = float(np.max(np.abs(b[f])))
    return float(np.max(np.abs(a[f] - b[f]))) / scale if scale > 0 else float(np.max(np.abs(a[f])))


def compare(inputs: Sequence[tuple], worst: dict[str, float]) -> None:
    def note(key: str, x: float) -> None:
        worst[key] = max(worst.get(key, 0.0), x)

    for mi, fit, spec, _tick in inputs:
        N, poles = mi.encoder_ppr, mi.poles
        prints = M.window_prints(mi) if mi.frame == "firmware" else [None] * len(mi.captures)
        old, new = old_merge_windows(prints, poles, N), fpr.merge_windows(prints, poles, N)
        worst["motors"] = worst.get("motors", 0) + 1
        if old is None or new is None:
            note("fingerprint None differs", float((old is None) != (new is None)))
            continue
        note("fingerprint", _rel(new.fp, old.fp))
        note("sigma", _rel(new.sigma, old.sigma))
        note("dirs, grid phase, offsets differ", float(new.dirs != old.dirs or new.grid_phase != old.grid_phase
                                                       or new.offsets != old.offsets))
        for a, b in zip(new.scores, old.scores, strict=True):
            if (a is None) != (b is None):
                note("scores", math.inf)
            elif a is not None:
                note("scores", _rel(a, b))
        # the joint fit itself: the final one over the windows placed, and every trial of a window
        # against the reference window
        quarter = poles * math.pi / N / 4.0
        placed = [(t, k + 4 * r) for w, r in zip(prints, old.offsets, strict=True) if r is not None for t, k in w.stretches]
        for cov in (True, False):
            a, b = joint_fit(placed, N, quarter, cov), old_joint_fit(placed, N, quarter, cov)
            note("joint fit fp", _rel(a[0], b[0]))
            note("joint fit var", _rel(a[1], b[1]))
            note("joint fit rss", _rel(a[2], b[2]))
            note("joint fit dirs, dof differ", float(a[3:] != b[3:]))
        ref = old.offsets.index(0)
        for i, w in enumerate(prints):
            if w is None or i == ref:
                continue
            for r in range(0, N, max(1, N // (poles // 2))):
                trial = list(prints[ref].stretches) + [(t, k + 4 * r) for t, k in w.stretches]
                a, b = joint_fit(trial, N, quarter, False), old_joint_fit(trial, N, quarter, False)
                if (a is None) != (b is None):
                    note("trial rss", math.inf)
                elif a is not None:
                    note("trial rss", _rel(a[2], b[2]))
                    worst["trials"] = worst.get("trials", 0) + 1
        if not fit.converged:
            continue
        oo, on = old_fit_orders(mi, fit, spec, prints, old), M.fit_orders(mi, fit, spec, prints, new)
        if (oo is None) != (on is None):
            note("orders None differs", 1.0)
            continue
        for a, b in zip(on or (), oo or (), strict=False):
            note("order value", _rel(a.c.value, b.c.value))
            note("order ci95", _rel(a.c.ci95, b.c.ci95))
            note("order phase (rad)", abs(math.remainder(a.phase_c.value - b.phase_c.value, 2 * math.pi)))
            note("order phase ci95", _rel(a.phase_c.ci95, b.phase_c.ci95))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--serials", type=int, default=24, help="serials of bench_refit.py's lot")
    ap.add_argument("--no-motors", action="store_true", help="leave out tests/test_fit_mech.py's plant motors")
    ap.add_argument("--tol", type=float, default=1e-9)
    a = ap.parse_args()
    worst: dict[str, float] = {}
    sets = [("bench_refit lot", lambda: lot_inputs(a.serials))]
    if not a.no_motors:
        sets.append(("test_fit_mech motors", motor_inputs))
    ok = True
    for name, make in sets:
        w: dict[str, float] = {}
        compare(make(), w)
        print(f"{name}: {int(w.pop('motors', 0))} motors, {int(w.pop('trials', 0))} extra trials")
        for k, v in w.items():
            bad = v > a.tol
            ok &= not bad
            print(f"  {k:<34} {v:.3g}{'  > tol' if bad else ''}")
        worst.update(w)
    print(f"{'all' if ok else 'NOT all'} within {a.tol:g} of the code before")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
