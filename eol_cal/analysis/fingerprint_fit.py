"""The encoder fingerprint's joint least squares: the edge errors shared by every stretch of
smooth motion, each stretch with its own polynomial motion (:func:`joint_fit`), and the same fit
over windows moved to trial offsets (:class:`PlacedWindows`, what
:func:`eol_cal.analysis.fingerprint.merge_windows` places windows with).

The errors are fitted orthogonal to the mechanical orders 0..:data:`LOW_ORDERS`, which the
polynomials over a revolution or so would otherwise share (:func:`low_order_complement`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from eol_cal.firmware.mech_params import FP_FORWARD

#: degree of each stretch's polynomial motion (Legendre in time)
POLY_DEGREE = 5
#: mechanical orders taken out of the fitted errors (the spline shares them)
LOW_ORDERS = 2
#: a joint fit of the edge errors: ``(fp (2N,), var (2N,), rss, dirs, dof)`` (:func:`joint_fit`)
JointFit = tuple[np.ndarray, np.ndarray, float, int, int]


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


class EdgeSums:
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
        return self.normals(halves, [shift])[0]

    def normals(self, halves: tuple[int, ...], shifts: Sequence[int]
                ) -> list[tuple[np.ndarray, np.ndarray, float, int]]:
        """:meth:`normal` at each of ``shifts`` (pulses), the products of every shift stacked in one
        pass (a placement's trials: one per pole pair); each shift's figures are those of its own
        products, bit for bit (numpy's stacked matmul calls BLAS on each shift's matrices as on one
        alone; tests/test_fingerprint_joint_fit.py checks it)."""
        todo = [shift for shift in dict.fromkeys(shifts) if (halves, shift) not in self._normal]
        if todo:  # each offset once: the window is placed at an offset its trials computed
            per_half, ss, n = self.part(halves)
            P = low_order_complement(self.N)
            nF = P.shape[1]
            G = np.zeros((len(todo), len(halves) * nF, len(halves) * nF))
            rhs = np.zeros((len(todo), len(halves) * nF))
            Ts = []
            moved = np.asarray(todo)[:, None]
            for i, (J, counts, r, S) in enumerate(per_half):
                PJ = P[(J + moved) % self.N]  # (shifts, pulses the window saw, nF)
                PJt = PJ.transpose(0, 2, 1)
                s = slice(i * nF, (i + 1) * nF)
                G[:, s, s] = PJt @ (counts[:, None] * PJ)
                rhs[:, s] = -PJt @ r
                Ts.append(PJt @ S)
            T = np.concatenate(Ts, axis=1)
            G -= T @ T.transpose(0, 2, 1)
            for j, shift in enumerate(todo):
                self._normal[halves, shift] = (G[j], rhs[j], ss, n)
        return [self._normal[halves, shift] for shift in shifts]


class NormalSums:
    """The joint fit's normal equations (errors' basis ``P`` per half) over windows at their
    offsets, for the edges of ``halves``: ``G``, ``rhs``, ``|phi_res|^2``, edges and stretches."""

    def __init__(self, N: int, halves: tuple[int, ...]):
        nF = low_order_complement(N).shape[1]
        self.halves = halves
        self.G = np.zeros((len(halves) * nF, len(halves) * nF))
        self.rhs = np.zeros(len(halves) * nF)
        self.ss, self.n, self.n_stretches = 0.0, 0, 0

    def add(self, w: EdgeSums, shift: int) -> None:
        """Add window ``w`` moved by ``shift`` pulses."""
        G, rhs, ss, n = w.normal(self.halves, shift)
        self.G += G
        self.rhs += rhs
        self.ss += ss
        self.n += n
        self.n_stretches += len(w.stretches)


def _solve(G: np.ndarray, rhs: np.ndarray, ss: float, n: int, n_stretches: int, halves: tuple[int, ...],
           N: int, cov: bool) -> JointFit:
    """The joint fit from its normal equations: ``(fp (2N,), var (2N,), rss, dirs, dof)`` as
    :func:`joint_fit`, by a Cholesky factor ``G = L L^T``: with ``z = L^-1 rhs`` the solution is
    ``L^-T z`` and the residual ``|phi_res|^2 - |z|^2`` (``cov`` adds the variances)."""
    from scipy.linalg import cho_solve
    from scipy.linalg.lapack import dtrtrs

    P = low_order_complement(N)
    nF = P.shape[1]
    dof = _dof(n, n_stretches, halves, nF)
    factor = _factor(G, rhs)
    G_inv: np.ndarray | None
    if factor is not None:
        L, z = factor
        sol = dtrtrs(L, z, lower=1, trans=1)[0]
        rss = max(ss - float(z @ z), 0.0)
        G_inv = cho_solve((L, True), np.eye(len(rhs)), check_finite=False) if cov else None
    else:
        G_inv, sol, rss = _least_norm(G, rhs, ss)
    fp = np.full(2 * N, np.nan)
    var = np.full(2 * N, np.nan)
    C = rss / max(1, dof) * G_inv if cov and G_inv is not None else None
    for i, d in enumerate(halves):
        s = slice(i * nF, (i + 1) * nF)
        fp[d::2] = P @ sol[s]
        if C is not None:
            var[d::2] = np.sum((P @ C[s, s]) * P, axis=1)
    return fp, var, rss, sum(FP_FORWARD << d for d in halves), dof


def _residual(G: np.ndarray, rhs: np.ndarray, ss: float) -> float:
    """:func:`_solve`'s residual alone (a placement trial's figure), the same bits: the errors
    themselves are not solved for where the Cholesky factor exists."""
    factor = _factor(G, rhs)
    if factor is None:
        return _least_norm(G, rhs, ss)[2]
    z = factor[1]
    return max(ss - float(z @ z), 0.0)


def _dof(n: int, n_stretches: int, halves: tuple[int, ...], nF: int) -> int:
    """Edges less unknowns: each stretch's polynomial, each half's errors."""
    return n - ((POLY_DEGREE + 1) * n_stretches + nF * len(halves))


def _factor(G: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(L, L^-1 rhs)`` of the Cholesky factor ``G = L L^T``; None where ``G`` is not positive definite."""
    # heavy: not at `eol-cal run`'s start, where the acquire step imports the windows' work on the
    # main thread before the shaft turns (tests/test_station_steps.py); the cycle's helper preloads it
    from scipy.linalg.lapack import dpotrf, dtrtrs

    L, info = dpotrf(G, lower=1)
    if info == 0:
        z, info = dtrtrs(L, rhs, lower=1)
    return (L, z) if info == 0 else None


def _least_norm(G: np.ndarray, rhs: np.ndarray, ss: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``(G^+, solution, residual)`` where ``G`` is not positive definite (a pulse's errors not
    separable from the motions): the least-norm solution."""
    G_inv = np.linalg.pinv(G)
    sol = G_inv @ rhs
    # |phi_res|^2 + 2 r.err + counts.err^2 - |S^T err|^2 over every edge = ss - 2 rhs.sol + sol^T G sol
    return G_inv, sol, max(ss - 2.0 * float(rhs @ sol) + float(sol @ (G @ sol)), 0.0)


def _halves(seen: np.ndarray, N: int) -> tuple[int, ...]:
    """The halves the fit keeps: every pulse seen, and a revolution and a quarter of edges."""
    return _halves_each(seen[None], N)[0]


def _halves_each(seen: np.ndarray, N: int) -> list[tuple[int, ...]]:
    """:func:`_halves` of each of a stack of edge counts ``seen`` (trials, 2, N): two reductions
    for all of them (a placement's trials, one per pole pair), not two a trial and a half."""
    ok = (seen.min(axis=2) >= 1) & (seen.sum(axis=2) >= N + N // 4)
    return [tuple(d for d in (0, 1) if row[d]) for row in ok.tolist()]


@dataclass(frozen=True)
class NormalEquations:
    """A joint fit's normal equations as they stood (:meth:`PlacedWindows.equations`): what its
    variances are solved from when first asked (:meth:`variances`), not with every fit."""

    G: np.ndarray
    rhs: np.ndarray
    ss: float
    n: int
    n_stretches: int
    halves: tuple[int, ...]
    N: int

    def variances(self) -> np.ndarray:
        """The errors' variances (2N,), rad^2 electrical: :func:`_solve`'s with ``cov``, the same bits."""
        return _solve(self.G, self.rhs, self.ss, self.n, self.n_stretches, self.halves, self.N, True)[1]


class PlacedWindows:
    """The windows placed so far (each :class:`EdgeSums` at its offset) and their normal equations
    per set of halves kept (built when first asked, kept up to date as windows are placed)."""

    def __init__(self, N: int):
        self.N = N
        self.windows: list[tuple[EdgeSums, int]] = []
        self.seen = np.zeros((2, N), np.int64)
        self._sums: dict[tuple[int, ...], NormalSums] = {}

    def sums(self, halves: tuple[int, ...]) -> NormalSums:
        if halves not in self._sums:
            s = NormalSums(self.N, halves)
            for w, shift in self.windows:
                s.add(w, shift)
            self._sums[halves] = s
        return self._sums[halves]

    def add(self, w: EdgeSums, shift: int) -> None:
        self.windows.append((w, shift))
        self.seen += np.roll(w.seen, shift, axis=1)
        for s in self._sums.values():
            s.add(w, shift)

    def fit(self, cov: bool = True) -> JointFit | None:
        """The joint fit of the windows placed; None when no half is covered."""
        halves = _halves(self.seen, self.N)
        if not halves:
            return None
        s = self.sums(halves)
        return _solve(s.G, s.rhs, s.ss, s.n, s.n_stretches, halves, self.N, cov)

    def equations(self) -> NormalEquations | None:
        """The normal equations of :meth:`fit` (a copy: later windows do not move it); None where
        :meth:`fit` is None."""
        halves = _halves(self.seen, self.N)
        if not halves:
            return None
        s = self.sums(halves)
        return NormalEquations(s.G.copy(), s.rhs.copy(), s.ss, s.n, s.n_stretches, halves, self.N)

    def trials(self, w: EdgeSums, shifts: Sequence[int]) -> list[tuple[float, int] | None]:
        """``(rss, dof)`` of the joint fit with window ``w`` added at each offset of ``shifts``:
        what a placement trial reads (the figures of that fit, bit for bit), the errors not solved
        for (a refit's motor tries ~18 placements), the window's products at every offset in one
        pass (:meth:`EdgeSums.normals`); None where no half is covered."""
        # the window's counts moved by each shift (np.roll's pulse m + shift), the trials stacked
        moved = (np.arange(self.N)[None, :] - np.asarray(shifts, dtype=np.int64)[:, None]) % self.N
        kept = _halves_each(self.seen[None] + w.seen[:, moved].transpose(1, 0, 2), self.N)
        nF = low_order_complement(self.N).shape[1]
        out: list[tuple[float, int] | None] = [None] * len(shifts)
        for halves in dict.fromkeys(h for h in kept if h):
            pick = [k for k, h in enumerate(kept) if h == halves]
            s = self.sums(halves)
            for k, (G, rhs, ss, n) in zip(pick, w.normals(halves, [shifts[k] for k in pick]), strict=True):
                out[k] = (_residual(s.G + G, s.rhs + rhs, s.ss + ss),
                          _dof(s.n + n, s.n_stretches + len(w.stretches), halves, nF))
        return out


def joint_fit(stretches: list[tuple[np.ndarray, np.ndarray]], N: int, quarter: float,
               cov: bool = True) -> JointFit | None:
    """Least squares of the edge errors shared by every stretch (each its own polynomial motion).

    ``stretches`` hold (times, A boundaries k in the common frame); edge ``k`` is fingerprint entry
    ``(k >> 1) mod 2N``: forward half (``k = 4m + 1``) and reverse half (``4m + 3``). Returns
    ``(fp (2N,), var (2N,), rss, dirs, dof)``; a half with a pulse never seen, or fewer than 1.25
    revolutions of edges, is left out (NaN entries, not in ``dirs``); ``dof`` = edges - unknowns.
    ``cov=False`` skips the variances (NaN).

    Each stretch's polynomial is projected out of its edges (Frisch-Waugh): the errors' normal
    equations are then ``(nF * dirs)`` square, summed per pulse from the edges (:class:`EdgeSums`),
    instead of a dense edges x unknowns least squares; the solution, the residual and the errors'
    covariance are the same. :func:`merge_windows` keeps each window's sums, and the normal
    equations of the windows placed, and moves the window it places to each offset it tries.
    """
    placed = PlacedWindows(N)
    placed.add(EdgeSums(stretches, N, quarter), 0)
    return placed.fit(cov=cov)
