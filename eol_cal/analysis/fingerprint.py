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
from typing import Any

import numpy as np
import scipy.linalg

from eol_cal.firmware.estimator import quadrature_phase
from eol_cal.firmware.mech_params import FP_FORWARD

#: speed (mechanical rpm) at which the field margin is predicted: the fastest of the range the
#: identification is tested over (noisier than slower speeds)
REF_RPM = 300.0
#: degree of each stretch's polynomial motion (Legendre in time)
POLY_DEGREE = 5
#: mechanical orders taken out of the fitted errors (the spline shares them)
LOW_ORDERS = 2
#: a joint fit of the edge errors: ``(fp (2N,), var (2N,), rss, dirs, dof)`` (:func:`joint_fit`)
_Fit = tuple[np.ndarray, np.ndarray, float, int, int]


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

    fp, sigma : (2N,) edge errors (rad electrical, mean 0 per direction, 0 where not measured) and
    their standard errors; dirs : FP_FORWARD | FP_REVERSE measured; grid_phase : rad, [0, 2*pi);
    offsets : per window, its offset r into the block's frame (None: not placed, not used);
    scores : per window, (fraction error rad, residual ratio of the next offset; NaN when the
    joint fit could not tell) of its placement.
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
    """Every level change of channel A: times (s, the midpoint of the two samples around), the
    boundary ``k`` it crosses (unwrapped; the estimator's numbering: ``q`` stepping forward,
    ``q + 1`` stepping back) and the direction of motion (+1/-1).

    A rises at ``k = 4m + 1`` and falls at ``4m + 3`` in forward rotation; in reverse the same
    boundaries are crossed the other way. The firmware's forward fingerprint is the edges at
    ``4m + 1`` (A rising forward), its reverse fingerprint those at ``4m + 3`` (A rising in
    reverse): both are measured whichever way the motor turns (fingerprint index ``k >> 1``).
    """
    a = np.asarray(enc_a).astype(np.int64) & 1
    a_changed = np.concatenate(([False], a[1:] != a[:-1]))
    moved = step != 0
    idx = np.flatnonzero(a_changed & moved)
    idx = idx[idx > 0]
    times = 0.5 * (t[idx - 1] + t[idx])
    fwd = step[idx] > 0
    k = np.where(fwd, q[idx], q[idx] + 1)
    return times, k, np.where(fwd, 1, -1)


@functools.lru_cache(maxsize=8)
def low_order_complement(N: int) -> np.ndarray:
    """Orthonormal basis (N, N - 1 - 2*LOW_ORDERS) of the errors without orders 0..LOW_ORDERS."""
    m = np.arange(N)
    cols = [np.ones(N)]
    for h in range(1, LOW_ORDERS + 1):
        cols += [np.cos(2 * np.pi * h * m / N), np.sin(2 * np.pi * h * m / N)]
    A = np.stack(cols, axis=1)
    q_full, _ = np.linalg.qr(np.concatenate([A, np.eye(N)], axis=1))
    basis = q_full[:, A.shape[1]:N]
    basis.flags.writeable = False
    return basis


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


class _Stats:
    """One window's (or any list of stretches') share of the joint fit, by pulse: what a placement
    trial and the final fit need of its edges, computed once (a trial only moves it).

    For the edges of the halves kept, per stretch: ``Q`` the orthonormal basis of its polynomial
    motion and ``phi_res`` the edges' nominal angles less their projection on it. The fit needs per
    (half, pulse) the edge count, the sum of ``phi_res`` and the sum of ``Q``'s rows (the
    stretches' columns side by side), and ``|phi_res|^2``: with ``err`` the errors per (half,
    pulse), the residual is ``|phi_res|^2 + 2 r.err + counts.err^2 - |S^T err|^2``. Moving the
    window by ``r`` pulses (``k + 4r``: the same half, pulse ``m + r``; ``phi_res`` unchanged, the
    constant is in the motion) moves these to pulse ``m + r``.
    """

    def __init__(self, stretches: Sequence[tuple[np.ndarray, np.ndarray]], N: int, quarter: float):
        self.stretches = stretches
        self.N, self.quarter = N, quarter
        allk = np.concatenate([k for _, k in stretches]) if stretches else np.zeros(0, np.int64)
        #: every edge per (half, pulse), whatever is kept: which halves the fit can keep
        self.seen = np.bincount(((allk >> 1) & 1) * N + (allk >> 2) % N, minlength=2 * N).reshape(2, N)
        self._parts: dict[tuple[int, ...], tuple[list[Any], float, int]] = {}
        self._normal: dict[tuple[tuple[int, ...], int], tuple[np.ndarray, np.ndarray, float, int]] = {}

    def part(self, halves: tuple[int, ...]) -> tuple[list[tuple[np.ndarray, ...]], float, int]:
        """For the edges of ``halves``: per half, ``(pulses seen, counts, r, S rows)`` at those
        pulses; ``|phi_res|^2``; the number of edges."""
        if halves not in self._parts:
            N = self.N
            counts, r = np.zeros(2 * N), np.zeros(2 * N)
            cols, ss, n = [np.zeros((2 * N, 0))], 0.0, 0
            for times, k in self.stretches:
                if len(halves) < 2:
                    keep = ((k >> 1) & 1) == halves[0]
                    times, k = times[keep], k[keep]
                if not len(times):
                    continue
                n += len(times)
                x = (times - times[0]) / max(times[-1] - times[0], 1e-12) * 2.0 - 1.0
                Q, _ = np.linalg.qr(np.polynomial.legendre.legvander(x, POLY_DEGREE))
                phi = (k - k[0]) * self.quarter  # the constant is in the motion: small numbers, less rounding
                phi_res = phi - Q @ (Q.T @ phi)
                idx = ((k >> 1) & 1) * N + (k >> 2) % N
                counts += np.bincount(idx, minlength=2 * N)
                r += np.bincount(idx, weights=phi_res, minlength=2 * N)
                cols.append(np.stack([np.bincount(idx, weights=Q[:, j], minlength=2 * N)
                                      for j in range(Q.shape[1])], axis=1))
                ss += float(phi_res @ phi_res)
            S = np.concatenate(cols, axis=1)
            per_half = []
            for h in halves:
                J = np.flatnonzero(counts[h * N:(h + 1) * N])
                per_half.append((J, counts[h * N + J], r[h * N + J], S[h * N + J]))
            self._parts[halves] = (per_half, ss, n)
        return self._parts[halves]

    def normal(self, halves: tuple[int, ...], shift: int) -> tuple[np.ndarray, np.ndarray, float, int]:
        """This window's part of the normal equations in the errors' basis ``P`` (per half) for
        the edges of ``halves``, moved by ``shift`` pulses: ``(G, rhs, |phi_res|^2, edges)``."""
        if (halves, shift) in self._normal:  # placed at the offset a trial computed
            return self._normal[halves, shift]
        per_half, ss, n = self.part(halves)
        P = low_order_complement(self.N)
        nF = P.shape[1]
        G = np.zeros((len(halves) * nF, len(halves) * nF))
        rhs = np.zeros(len(halves) * nF)
        Ts = []
        for i, (J, counts, r, S) in enumerate(per_half):
            PJ = P[(J + shift) % self.N]  # only the pulses the window saw
            s = slice(i * nF, (i + 1) * nF)
            G[s, s] = PJ.T @ (counts[:, None] * PJ)
            rhs[s] = -PJ.T @ r
            Ts.append(PJ.T @ S)
        T = np.concatenate(Ts)
        G -= T @ T.T
        self._normal[halves, shift] = (G, rhs, ss, n)
        return G, rhs, ss, n


class _Sums:
    """The joint fit's normal equations (errors' basis ``P`` per half) over windows at their
    offsets, for the edges of ``halves``: ``G``, ``rhs``, ``|phi_res|^2``, edges and stretches."""

    def __init__(self, N: int, halves: tuple[int, ...]):
        nF = low_order_complement(N).shape[1]
        self.halves = halves
        self.G = np.zeros((len(halves) * nF, len(halves) * nF))
        self.rhs = np.zeros(len(halves) * nF)
        self.ss, self.n, self.n_stretches = 0.0, 0, 0

    def add(self, w: _Stats, shift: int) -> None:
        """Add window ``w`` moved by ``shift`` pulses."""
        G, rhs, ss, n = w.normal(self.halves, shift)
        self.G += G
        self.rhs += rhs
        self.ss += ss
        self.n += n
        self.n_stretches += len(w.stretches)


def _solve(G: np.ndarray, rhs: np.ndarray, ss: float, n: int, n_stretches: int, halves: tuple[int, ...],
           N: int, cov: bool) -> _Fit:
    """The joint fit from its normal equations: ``(fp (2N,), var (2N,), rss, dirs, dof)`` as
    :func:`joint_fit`, by a Cholesky factor ``G = L L^T``: with ``z = L^-1 rhs`` the solution is
    ``L^-T z`` and the residual ``|phi_res|^2 - |z|^2`` (a placement trial's figures are those of
    the full fit; ``cov`` adds the variances)."""
    P = low_order_complement(N)
    nF = P.shape[1]
    dof = n - ((POLY_DEGREE + 1) * n_stretches + nF * len(halves))
    L, info = scipy.linalg.lapack.dpotrf(G, lower=1)
    if info == 0:
        z, info = scipy.linalg.lapack.dtrtrs(L, rhs, lower=1)
    if info == 0:
        sol = scipy.linalg.lapack.dtrtrs(L, z, lower=1, trans=1)[0]
        rss = max(ss - float(z @ z), 0.0)
        G_inv = scipy.linalg.cho_solve((L, True), np.eye(len(rhs)), check_finite=False) if cov else None
    else:  # not positive definite (a pulse's errors not separable from the motions): least norm
        G_inv = np.linalg.pinv(G)
        sol = G_inv @ rhs
        # |phi_res|^2 + 2 r.err + counts.err^2 - |S^T err|^2 over every edge = ss - 2 rhs.sol + sol^T G sol
        rss = max(ss - 2.0 * float(rhs @ sol) + float(sol @ (G @ sol)), 0.0)
    fp = np.full(2 * N, np.nan)
    var = np.full(2 * N, np.nan)
    C = rss / max(1, dof) * G_inv if cov else None
    for i, d in enumerate(halves):
        s = slice(i * nF, (i + 1) * nF)
        fp[d::2] = P @ sol[s]
        if C is not None:
            var[d::2] = np.sum((P @ C[s, s]) * P, axis=1)
    return fp, var, rss, sum(FP_FORWARD << d for d in halves), dof


def _halves(seen: np.ndarray, N: int) -> tuple[int, ...]:
    """The halves the fit keeps: every pulse seen, and a revolution and a quarter of edges."""
    return tuple(d for d in (0, 1) if seen[d].min() >= 1 and seen[d].sum() >= N + N // 4)


class _Placed:
    """The windows placed so far (each :class:`_Stats` at its offset) and their normal equations
    per set of halves kept (built when first asked, kept up to date as windows are placed)."""

    def __init__(self, N: int):
        self.N = N
        self.windows: list[tuple[_Stats, int]] = []
        self.seen = np.zeros((2, N), np.int64)
        self._sums: dict[tuple[int, ...], _Sums] = {}

    def sums(self, halves: tuple[int, ...]) -> _Sums:
        if halves not in self._sums:
            s = _Sums(self.N, halves)
            for w, shift in self.windows:
                s.add(w, shift)
            self._sums[halves] = s
        return self._sums[halves]

    def add(self, w: _Stats, shift: int) -> None:
        self.windows.append((w, shift))
        self.seen += np.roll(w.seen, shift, axis=1)
        for s in self._sums.values():
            s.add(w, shift)

    def fit(self, extra: tuple[_Stats, int] | None = None, cov: bool = True) -> _Fit | None:
        """The joint fit of the windows placed, and ``extra`` (a window, its offset) if given;
        None when no half is covered."""
        seen = self.seen if extra is None else self.seen + np.roll(extra[0].seen, extra[1], axis=1)
        halves = _halves(seen, self.N)
        if not halves:
            return None
        s = self.sums(halves)
        if extra is None:
            return _solve(s.G, s.rhs, s.ss, s.n, s.n_stretches, halves, self.N, cov)
        G, rhs, ss, n = extra[0].normal(halves, extra[1])
        return _solve(s.G + G, s.rhs + rhs, s.ss + ss, s.n + n, s.n_stretches + len(extra[0].stretches),
                      halves, self.N, cov)


def joint_fit(stretches: list[tuple[np.ndarray, np.ndarray]], N: int, quarter: float,
               cov: bool = True) -> _Fit | None:
    """Least squares of the edge errors shared by every stretch (each its own polynomial motion).

    ``stretches`` hold (times, A boundaries k in the common frame); edge ``k`` is fingerprint entry
    ``(k >> 1) mod 2N``: forward half (``k = 4m + 1``) and reverse half (``4m + 3``). Returns
    ``(fp (2N,), var (2N,), rss, dirs, dof)``; a half with a pulse never seen, or fewer than 1.25
    revolutions of edges, is left out (NaN entries, not in ``dirs``); ``dof`` = edges - unknowns.
    ``cov=False`` skips the variances (NaN): a placement trial needs the residual only.

    Each stretch's polynomial is projected out of its edges (Frisch-Waugh): the errors' normal
    equations are then ``(nF * dirs)`` square, summed per pulse from the edges (:class:`_Stats`),
    instead of a dense edges x unknowns least squares; the solution, the residual and the errors'
    covariance are the same. :func:`merge_windows` keeps each window's sums, and the normal
    equations of the windows placed, and moves the window it places to each offset it tries.
    """
    placed = _Placed(N)
    placed.add(_Stats(stretches, N, quarter), 0)
    return placed.fit(cov=cov)


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
    stats = {i: _Stats(present[i].stretches, N, quarter) for i in usable}
    placed = _Placed(N)
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
    fit = placed.fit()
    if fit is None:
        return None
    fp, var, _, dirs, _ = fit
    sigma = np.sqrt(np.where(np.isfinite(var), np.maximum(var, 0.0), np.inf))
    for d in (0, 1):
        if dirs & (1 << d):
            fp[d::2] -= fp[d::2].mean()
        else:
            fp[d::2], sigma[d::2] = 0.0, np.inf
    return Fingerprint(fp, sigma, dirs, present[ref].grid_phase, offsets, scores)


def _place(w: WindowEdges, stats: _Stats, ref_phase: float, placed: _Placed, poles: int, N: int, delta: float,
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
    trials = []
    for j in range(poles // 2):
        r = int(math.floor((dg + 2 * math.pi * j) / delta + 0.5)) % N
        e = math.remainder(dg - r * delta, 2 * math.pi)
        fit = placed.fit((stats, r), cov=False)
        rss = fit[2] if fit is not None and fit[4] >= N // 2 else math.nan
        trials.append((rss, r, e))
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
