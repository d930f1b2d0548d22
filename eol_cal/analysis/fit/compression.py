"""Compression of a motor's segments into their normal equations (the fit's numpy half).

Each segment is compressed exactly into the Cholesky factor ``R`` of its normal matrix and
``z = R^-T X^T y``: ``||y - X g||^2 = ||z - R g||^2 + floor``. The nonlinear least-squares problem
over the full parameter vector (tau and every cos/sin coefficient) then has a residual of
``S * m`` rows instead of one per sample; it is the same objective, so the Jacobian-based
covariance is the same too.
"""

from __future__ import annotations

import contextlib
import contextvars
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

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
    cur_re, cur_im : ndarray, (S, harmonics)
        The ripple of ``kt * i_q`` per segment and harmonic as an air-gap phasor
        (:func:`current_phasor`, N*m): known torque, added to the motor's before the path; zero
        without a current channel (``SteadySegments.kt_iq`` None).
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
    cur_re: np.ndarray
    cur_im: np.ndarray


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


def _normal_equations(theta: np.ndarray, t: np.ndarray, signals: list[np.ndarray], pole_pairs: int,
                      spec: FitSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``X^T X`` (columns without data pinned by a unit diagonal), ``X^T y`` and ``y^T y`` of each
    signal about its mean, the signals' means, and which columns are empty: one pass over the samples."""
    n = len(theta)
    m = spec.n_cols
    k = len(signals)
    means = np.array([float(y.mean()) for y in signals])
    mech = mech_span(theta, pole_pairs)
    buf = _block_buffer(m + k)
    # [X y]^T [X y] accumulated block by block: X^T X, X^T y and y^T y in one GEMM per block, on
    # the (n, m+k) Fortran view (numpy's ``A @ A.T`` dispatches to SYRK, which OpenBLAS runs 2x
    # slower for these narrow products)
    from scipy.linalg.blas import dgemm  # heavy: not at `eol-cal run`'s start (tests/test_imports.py)

    G = np.zeros((m + k, m + k), order="F")
    for a in range(0, n, _BLOCK):
        b = min(a + _BLOCK, n)
        XTa = buf[: (m + k) * (b - a)].reshape(m + k, b - a)
        design_matrix_t(theta[a:b], t[a:b], pole_pairs, spec, t_span=(t[0], t[-1]), mech=mech, out=XTa)
        for j, y in enumerate(signals):
            np.subtract(y[a:b], means[j], out=XTa[m + j])
        G = dgemm(1.0, XTa.T, XTa.T, beta=1.0, c=G, trans_a=1, overwrite_c=True)
    XtX = np.array(G[:m, :m], order="C")
    empty = np.diag(XtX) == 0.0
    # a column without data is pinned to 0 by a unit diagonal: its residual row reads 0 - g_j
    XtX[empty, empty] = 1.0
    return XtX, np.array(G[:m, m:]), np.array(G[m:, m:]), means, empty


def compress_segment(theta: np.ndarray, t: np.ndarray, torque: np.ndarray, pole_pairs: int,
                     spec: FitSpec) -> tuple[np.ndarray, np.ndarray, float, float, float, int, int]:
    """Normal-equation summary of one segment: (R, z, floor, sst, ymean, n, n_nuis).

    ``theta`` must be continuous (unwrapped), as :mod:`eol_cal.analysis.angle` returns it.
    """
    summary, _ = _compress_one(theta, t, torque, None, pole_pairs, spec)
    return summary


def _compress_one(theta: np.ndarray, t: np.ndarray, torque: np.ndarray, kt_iq: np.ndarray | None, pole_pairs: int,
                  spec: FitSpec) -> tuple[tuple[np.ndarray, np.ndarray, float, float, float, int, int], np.ndarray]:
    """:func:`compress_segment`, and the current's ripple phasor per harmonic (:func:`current_phasor`;
    zeros without ``kt_iq``)."""
    theta = np.asarray(theta, dtype=float)
    t = np.asarray(t, dtype=float)
    signals = [np.asarray(torque, dtype=float)]
    if kt_iq is not None:
        signals.append(np.asarray(kt_iq, dtype=float))
    XtX, Xty, yy, means, empty = _normal_equations(theta, t, signals, pole_pairs, spec)
    Lc = np.linalg.cholesky(XtX)
    z = np.linalg.solve(Lc, Xty[:, 0])  # triangular, tiny
    phasor = np.zeros(len(spec.harmonics), dtype=complex)
    if kt_iq is not None:
        phasor = current_phasor(np.linalg.solve(XtX, Xty[:, 1]), spec)
    summary = (Lc.T, z, float(yy[0, 0]) - float(z @ z), float(yy[0, 0]), float(means[0]), len(theta),
               spec.n_nuis - int(empty.sum()))
    return summary, phasor


def current_phasor(coef: np.ndarray, spec: FitSpec) -> np.ndarray:
    """The ripple of ``kt * i_q`` as the model's air-gap phasor per harmonic (N*m, complex).

    ``coef``: the least-squares coefficients of ``kt * i_q`` on a segment's columns (nuisance, then
    sin/cos per harmonic). ``a sin(h theta) + b cos(h theta)`` is ``-Re(Z) sin - Im(Z) cos`` with
    ``Z = -(a + i b)``: the convention of the motor's ripple ``Z = c + k i_qo`` (subtracted from the
    torque), so the two add before the path and the transducer.
    """
    g = coef[spec.n_nuis:].reshape(-1, 2)
    return -(g[:, 0] + 1j * g[:, 1])


#: the segment compressions of :func:`shared_compression`'s scope (None: none shared)
_SHARED: contextvars.ContextVar[dict[tuple[Any, ...], Any] | None] = contextvars.ContextVar("compressions",
                                                                                          default=None)


@contextlib.contextmanager
def shared_compression() -> Iterator[None]:
    """Within it, each segment is compressed once: :func:`compress` of the same segment arrays (the
    same objects) and the same columns (harmonics, drift degree, mechanical orders: all the
    compression reads of a spec) gives the first call's figures again, bit for bit. The model
    check's speed bands are fitted on the joint fit's own segments (:func:`eol_cal.analysis.fit.
    model_check.check_model`): their compression is the joint fit's. The segments' arrays must not
    change in place while it lasts (a changed array under the same object would be taken for the
    one compressed); its compressions are dropped on leaving it."""
    token = _SHARED.set({})
    try:
        yield
    finally:
        _SHARED.reset(token)


def compress(seg: SteadySegments, spec: FitSpec, n_segments: int | None = None) -> Compressed:
    """Compress every segment of one motor, padded to ``n_segments`` (padding: R = I, z = 0, n = 0)."""
    S = n_segments or seg.n_segments
    m = spec.n_cols
    R = np.tile(np.eye(m), (S, 1, 1))
    z = np.zeros((S, m))
    vec = {k: np.zeros(S) for k in ("floor", "sst", "ymean", "n", "n_nuis", "i_qo", "omega")}
    current = np.zeros((S, len(spec.harmonics)), dtype=complex)
    memo = _SHARED.get()
    for s in range(seg.n_segments):
        kt_iq = None if seg.kt_iq is None else seg.kt_iq[s]
        arrays = (seg.theta[s], seg.t[s], seg.torque[s], kt_iq)
        key = (*map(id, arrays), seg.pole_pairs, spec.harmonics, spec.drift_degree, spec.mech_order1, spec.mech_orders)
        if memo is not None and key in memo:
            one = memo[key][0]
        else:
            one = _compress_one(*arrays, seg.pole_pairs, spec)
            if memo is not None:
                memo[key] = (one, arrays)  # the arrays held: no id of the key is reused while it lasts
        (R[s], z[s], fl, sst, ym, n, nn), current[s] = one
        vec["floor"][s], vec["sst"][s], vec["ymean"][s], vec["n"][s], vec["n_nuis"][s] = fl, sst, ym, n, nn
        vec["i_qo"][s], vec["omega"][s] = seg.i_qo[s], seg.omega_e[s]
    gain = np.ones((S, len(spec.harmonics)), dtype=complex)
    gain[: seg.n_segments] = path_gain(seg, spec)
    return Compressed(R=R, z=z, gain_re=gain.real.copy(), gain_im=gain.imag.copy(), cur_re=current.real.copy(),
                      cur_im=current.imag.copy(), **vec)


COMPRESSED_KEYS = ("R", "z", "n", "i_qo", "omega", "gain_re", "gain_im", "cur_re", "cur_im")


def compressed_dict(c: Compressed) -> dict[str, np.ndarray]:
    return {k: getattr(c, k) for k in COMPRESSED_KEYS}
