"""The noise each segment has at each harmonic's own frequency, measured beside the line.

The torque's noise is far from white at the ripple's harmonics (the current loop's answer to the
ECU's current noise reaches the shaft below the transducer's bandwidth), so neither the joint fit's
intervals nor the model check's speed bands take the residual's average for it: each segment is
fitted alone on its columns (nuisance and harmonics) and the residual's cos/sin coefficients at the
neighbouring frequencies ``h f_e + k / T`` (``2 <= |k| <=``
:data:`~eol_cal.analysis.fit.model.NOISE_BINS`: no ripple there, whatever the path does) are what
noise alone puts on harmonic h's pair (:func:`_clear_bins`: not where the drift polynomial or the
line itself took the residual). With the ECU's current (``seg.kt_iq``) the fit takes its
ripple as known through the path and the transducer: so here too, bin by bin (the current's noise
that reaches the shaft cancels, the current sensor's own does not).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.fit.model import FitSpec, SteadySegments, bins_noise, noise_bins
from eol_cal.analysis.fit.noise_pass import bin_powers, columns, layout, line_rows, line_turns


@dataclass(frozen=True)
class SegmentNoise:
    """Per segment and harmonic, the noise at the harmonic's own frequency.

    Attributes
    ----------
    harmonics : tuple of int
        The electrical orders measured (the fit's, in its order).
    var_pair : ndarray, (segments, harmonics)
        Variance (N*m^2) noise alone puts on one cos/sin coefficient of the harmonic's pair.
    var_white : ndarray, (segments,)
        The same for white noise of the segment's residual variance, ``2 s^2 / n`` (N*m^2).
    n : ndarray, (segments,)
        Samples of each segment.
    dof : ndarray of int, (segments, harmonics)
        Degrees of freedom of each ``var_pair`` (two a bin).
    """

    harmonics: tuple[int, ...]
    var_pair: np.ndarray
    var_white: np.ndarray
    n: np.ndarray
    dof: np.ndarray

    def ratio(self, segments: np.ndarray, h: int = 6) -> float:
        """How much the noise at harmonic ``h`` exceeds the white level over ``segments`` (indices),
        the segments weighted by their samples."""
        j = self.harmonics.index(h)
        w = self.n[segments]
        return float(np.sum(w * self.var_pair[segments, j] / self.var_white[segments]) / np.sum(w))

    def row_variance(self) -> np.ndarray:
        """(segments, 2 harmonics): the variance of each of the compressed fit's reduced rows (one
        cos/sin pair a harmonic; N*m^2 * samples): a unit-norm combination of the samples sees
        ``n / 2`` times a cos/sin coefficient's variance."""
        return np.repeat(self.var_pair * (self.n[:, None] / 2.0), 2, axis=1)


def _fitted(XT: np.ndarray, Y: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The residual of ``Y`` (n, signals) fitted on the columns ``XT`` (as rows, (m, n), rows of unit
    stride), and the basis :func:`~eol_cal.analysis.fit.model.line_noise` reads the fit's share of a
    bin from: the non-empty columns (as rows) and the inverse of their normal matrix. From the normal
    equations' Cholesky factor (the columns are well conditioned): no orthonormal basis of the
    segment's samples is formed (a refit's model check spent a third of its noise in it). ``G``: the
    normal matrix's upper triangle (:func:`~eol_cal.analysis.fit.noise_pass.columns`: :func:`~eol_cal.
    numerics.gemm.gram_halves`, numpy's ``XT @ XT.T`` is SYRK, 2.5x its time on a 15 x 3333 segment)."""
    from scipy.linalg.lapack import dpotrf, dtrtri  # heavy: not at `eol-cal run`'s start (tests/test_imports.py)

    keep = np.diag(G) != 0.0  # an empty column (an unresolved mechanical pair) has a zero norm
    if not keep.all():
        XT, G = XT[keep], G[np.ix_(keep, keep)]
    R, info = dpotrf(G, lower=0)  # G = R^T R from its upper triangle
    if info == 0:
        R_inv, info = dtrtri(R, lower=0)
    if info != 0:
        raise np.linalg.LinAlgError(f"a segment's columns are not independent (LAPACK info {info})")
    g_inv = R_inv @ R_inv.T
    res = Y - XT.T @ (g_inv @ (XT @ Y))
    return res, (XT, g_inv)


def _clear_bins(bins: np.ndarray, f_line: float | np.ndarray, drift_degree: int) -> np.ndarray:
    """Which bins ``k`` (offsets from the line, in ``1 / T``) that hold the segment's noise: not within
    ``drift_degree + 2`` of zero frequency (the drift polynomial takes the residual there) nor within 2
    of the line (a bin below it at negative frequency mirrors the line), one bin a frequency.
    ``f_line``: the line's frequency times T (signed: the angle's direction); an array of lines gives
    one row of bins each (``f_line.shape + bins.shape``: every line of a motor in one call). On 0.05 s
    segments (the 6th at 90 Hz, bins 20 Hz apart) those bins made white noise read 15 % low."""
    f_line = np.asarray(f_line, dtype=float)[..., None]
    f = np.abs(f_line + bins)
    keep = (f >= drift_degree + 2) & (np.abs(f - np.abs(f_line)) >= 2)
    # one bin a frequency: the first of the bins of one half-integer frequency (np.unique's first)
    twice = np.round(f * 2)
    earlier = np.tri(len(bins), k=-1, dtype=bool)  # [j, i]: bin i comes before bin j
    seen = ((twice[..., :, None] == twice[..., None, :]) & earlier).any(axis=-1)
    return keep & ~seen


def segment_noise(seg: SteadySegments, spec: FitSpec, tau_s: float,
                  harmonics: tuple[int, ...] | None = None) -> SegmentNoise:
    """Measure :class:`SegmentNoise` on every segment (module docstring).

    Parameters
    ----------
    seg : SteadySegments
        The motor's segments.
    spec : FitSpec
        The model: its columns, harmonics and transducer.
    tau_s : float
        The transducer's time constant or delay (s): the current's noise reaches the shaft through it.
    harmonics : tuple of int, optional
        The harmonics to measure (default ``spec.harmonics``; the model check reads the 6th alone).
        Each is measured as it would be with the others: the segment is fitted on all the model's columns.

    Notes
    -----
    What is a function of the sample alone (the columns, the bins' exponentials, each line's turn)
    is built for every segment in one pass over their samples side by side
    (:mod:`~eol_cal.analysis.fit.noise_pass`: a few long numpy calls instead of ~60 short ones a
    segment, in buffers kept for the next motor), and every segment's normal matrix in one BLAS call;
    each segment's products are its own, as before. The figures are the per-segment construction's
    bit for bit with the same exponentials, within 1e-13 relative of numpy's complex ``exp``
    (tests/test_fit_segment_noise.py).
    """
    harmonics = tuple(spec.harmonics) if harmonics is None else tuple(harmonics)
    bins = noise_bins()
    S, H = seg.n_segments, len(harmonics)
    var_pair, var_white, n_s = np.zeros((S, H)), np.zeros(S), np.zeros(S)
    dof = np.zeros((S, H), dtype=int)
    lay = layout(seg)
    # every segment's and harmonic's clear bins at once, (S, H, bins)
    keeps = _clear_bins(bins, np.array([[h * float(seg.omega_e[s]) / (2 * math.pi) * lay.T[s] for h in harmonics]
                                        for s in range(S)]).reshape(S, H), spec.drift_degree)
    top = int(np.max(np.abs(bins) * keeps.any(axis=(0, 1)), initial=0))
    XT, G = columns(seg, spec, lay)
    powers = bin_powers(lay, top)
    turns = line_turns(lay, harmonics)
    for s in range(S):
        first, end = int(lay.offsets[s]), int(lay.offsets[s + 1])
        y = [np.asarray(seg.torque[s], dtype=float)]
        if seg.kt_iq is not None:
            y.append(np.asarray(seg.kt_iq[s], dtype=float))
        res, basis = _fitted(XT[:, first:end], np.column_stack(y), G[s])
        n, T = end - first, float(lay.T[s])
        cur = res[:, 1] if seg.kt_iq is not None else None
        for j, (h, keep) in enumerate(zip(harmonics, keeps[s], strict=True)):
            k = bins[keep]
            omega = h * float(seg.omega_e[s]) + 2 * math.pi * k / T  # each bin's rate (rad/s, signed)
            wri = line_rows(powers[:, first:end], k, turns[j, first:end])
            var_pair[s, j] = bins_noise(res[:, 0], cur, wri, omega, spec, tau_s, seg.path_response, basis=basis)
            dof[s, j] = 2 * len(k)
        var_white[s] = 2.0 * float(res[:, 0] @ res[:, 0]) / max(n - XT.shape[0], 1) / n
        n_s[s] = n
    return SegmentNoise(harmonics, var_pair, var_white, n_s, dof)
