"""Compression of a motor's segments into their normal equations (the fit's numpy half).

Each segment is compressed exactly into the Cholesky factor ``R`` of its normal matrix and
``z = R^-T X^T y``: ``||y - X g||^2 = ||z - R g||^2 + floor``. The nonlinear least-squares problem
over the full parameter vector (tau and every cos/sin coefficient) then has a residual of
``S * m`` rows instead of one per sample; it is the same objective, so the Jacobian-based
covariance is the same too.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.fit.model import FitSpec, SteadySegments, design_matrix_t, mech_span, path_gain


@dataclass
class Compressed:
    """One motor's segments reduced to their normal equations (see the module docstring).

    Attributes
    ----------
    R : ndarray, (S, m, m)
        Upper Cholesky factor of each segment's X^T X (columns: nuisance, then harmonics).
    z : ndarray, (S, m)
        R^-T X^T y (N*m * sqrt(samples)).
    floor : ndarray, (S,)
        Sum of squares no coefficient choice can remove (N*m^2).
    sst : ndarray, (S,)
        Sum of squares about the segment mean (N*m^2).
    ymean : ndarray, (S,)
        Segment mean torque (N*m).
    n : ndarray, (S,)
        Samples per segment.
    n_nuis : ndarray, (S,)
        Free nuisance parameters per segment.
    i_qo, omega : ndarray, (S,)
        Segment load (A) and electrical speed (rad/s).
    gain_re, gain_im : ndarray, (S, harmonics)
        The air-gap-to-shaft response at each segment's harmonics (:func:`path_gain`).
    """

    R: np.ndarray
    z: np.ndarray
    floor: np.ndarray
    sst: np.ndarray
    ymean: np.ndarray
    n: np.ndarray
    n_nuis: np.ndarray
    i_qo: np.ndarray
    omega: np.ndarray
    gain_re: np.ndarray
    gain_im: np.ndarray


#: Samples per block of the compression. The design matrix of a block lives in one reused
#: per-thread buffer and every temporary (complex: 16 B x 8000 = 125 KiB) stays under glibc's mmap
#: threshold (128 KiB): whole-segment arrays were mmap'ed and page-faulted afresh on every call
#: (about 700 faults and 1.5 ms per 20000-sample capture, more than the arithmetic).
_BLOCK = 8000
_WORK = threading.local()


def _block_buffer(rows: int) -> np.ndarray:
    """This thread's block buffer, at least ``rows * _BLOCK`` doubles (kept for the next call)."""
    buf = getattr(_WORK, "buf", None)
    if buf is None or buf.size < rows * _BLOCK:
        buf = _WORK.buf = np.empty(rows * _BLOCK)
    return buf


def compress_segment(theta: np.ndarray, t: np.ndarray, torque: np.ndarray, pole_pairs: int,
                     spec: FitSpec) -> tuple[np.ndarray, np.ndarray, float, float, float, int, int]:
    """Normal-equation summary of one segment: (R, z, floor, sst, ymean, n, n_nuis).

    ``theta`` must be continuous (unwrapped), as :mod:`eol_cal.analysis.angle` returns it.
    """
    theta = np.asarray(theta, dtype=float)
    t = np.asarray(t, dtype=float)
    y = np.asarray(torque, dtype=float)
    n = len(y)
    m = spec.n_cols
    ymean = float(y.mean())
    mech = mech_span(theta, pole_pairs)
    buf = _block_buffer(m + 1)
    # [X y]^T [X y] accumulated block by block: X^T X, X^T y and y^T y in one GEMM per block, on
    # the (n, m+1) Fortran view (numpy's ``A @ A.T`` dispatches to SYRK, which OpenBLAS runs 2x
    # slower for these narrow products)
    from scipy.linalg.blas import dgemm  # heavy: not at `eol-cal run`'s start (tests/test_imports.py)

    G = np.zeros((m + 1, m + 1), order="F")
    for a in range(0, n, _BLOCK):
        b = min(a + _BLOCK, n)
        XTa = buf[: (m + 1) * (b - a)].reshape(m + 1, b - a)
        design_matrix_t(theta[a:b], t[a:b], pole_pairs, spec, t_span=(t[0], t[-1]), mech=mech, out=XTa)
        np.subtract(y[a:b], ymean, out=XTa[m])
        G = dgemm(1.0, XTa.T, XTa.T, beta=1.0, c=G, trans_a=1, overwrite_c=True)
    XtX = np.array(G[:m, :m], order="C")
    Xty = np.array(G[:m, m])
    yy = float(G[m, m])
    empty = np.diag(XtX) == 0.0
    # a column without data is pinned to 0 by a unit diagonal: its residual row reads 0 - g_j
    XtX[empty, empty] = 1.0
    Lc = np.linalg.cholesky(XtX)
    z = np.linalg.solve(Lc, Xty)  # triangular, tiny
    return Lc.T, z, yy - float(z @ z), yy, ymean, n, spec.n_nuis - int(empty.sum())


def compress(seg: SteadySegments, spec: FitSpec, n_segments: int | None = None) -> Compressed:
    """Compress every segment of one motor, padded to ``n_segments`` (padding: R = I, z = 0, n = 0)."""
    S = n_segments or seg.n_segments
    m = spec.n_cols
    R = np.tile(np.eye(m), (S, 1, 1))
    z = np.zeros((S, m))
    vec = {k: np.zeros(S) for k in ("floor", "sst", "ymean", "n", "n_nuis", "i_qo", "omega")}
    for s in range(seg.n_segments):
        R[s], z[s], fl, sst, ym, n, nn = compress_segment(seg.theta[s], seg.t[s], seg.torque[s], seg.pole_pairs, spec)
        vec["floor"][s], vec["sst"][s], vec["ymean"][s], vec["n"][s], vec["n_nuis"][s] = fl, sst, ym, n, nn
        vec["i_qo"][s], vec["omega"][s] = seg.i_qo[s], seg.omega_e[s]
    gain = np.ones((S, len(spec.harmonics)), dtype=complex)
    gain[: seg.n_segments] = path_gain(seg, spec)
    return Compressed(R=R, z=z, gain_re=gain.real.copy(), gain_im=gain.imag.copy(), **vec)


COMPRESSED_KEYS = ("R", "z", "n", "i_qo", "omega", "gain_re", "gain_im")


def compressed_dict(c: Compressed) -> dict[str, np.ndarray]:
    return {k: getattr(c, k) for k in COMPRESSED_KEYS}
