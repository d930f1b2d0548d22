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
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from eol_cal.analysis.fit.model import (FitSpec, SteadySegments, design_rows, mech_resolved, mech_span, path_gain,
                                        unresolved_to_zero)
from eol_cal.numerics.gemm import gram_halves


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


#: Samples per piece at most: a longer segment is compressed piece by piece, the pieces' products
#: summed (a piece is shorter where :data:`_SMALL_GEMM` asks).
_BLOCK = 8000
#: OpenBLAS's small-matrix GEMM (no packing of the operands) serves products of M*N*K up to 100^3:
#: a piece's ``[X y]^T [X y]`` as two halves of rows (numpy's ``A @ A.T`` is SYRK, which packs) of at
#: most this many multiplications each runs in 12 ns a sample against SYRK's 25 (16 columns).
_SMALL_GEMM = 100**3
#: Samples whose columns one numpy call builds: the pieces of several segments (of several motors)
#: side by side in one buffer (a few long kernels instead of ~30 short ones a segment: the GIL is
#: held between kernels only, so threads compress side by side), every piece's products in one
#: :func:`~eol_cal.numerics.gemm.gram_halves` call (BLAS, the GIL released).
_GROUP = 32768
_WORK = threading.local()


def _work_buffers(size: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """This thread's work buffers: at least ``size`` doubles, and 4 complex rows of ``n`` (kept for
    the next call: a fresh one of megabytes is mmap'ed and page-faulted afresh each time, ~2 us a
    page on this VM, as much as the arithmetic)."""
    buf, cbuf = getattr(_WORK, "buf", None), getattr(_WORK, "cbuf", None)
    if buf is None or buf.size < size:
        buf = _WORK.buf = np.empty(size)
    if cbuf is None or cbuf.shape[1] < n:
        cbuf = _WORK.cbuf = np.empty((4, n), dtype=complex)
    return buf, cbuf


@dataclass(frozen=True)
class _Segment:
    """One segment to compress: angle (rad), time (s), torque and ``kt * i_q`` (N*m, or None), its
    signals' means and its span in mechanical revolutions."""

    theta: np.ndarray
    t: np.ndarray
    torque: np.ndarray
    kt_iq: np.ndarray | None
    pole_pairs: int
    means: tuple[float, ...]
    mech: float
    #: every mechanical order's pair carried (:func:`unresolved_to_zero` clears nothing)
    all_resolved: bool


def _segment(theta: np.ndarray, t: np.ndarray, torque: np.ndarray, kt_iq: np.ndarray | None,
             pole_pairs: int, spec: FitSpec) -> _Segment:
    theta = np.asarray(theta, dtype=float)
    y = np.asarray(torque, dtype=float)
    c = None if kt_iq is None else np.asarray(kt_iq, dtype=float)
    # the mean as ndarray.mean takes it (the sum over the count), without its Python wrapper: a
    # twelfth of a compression thread's time under the GIL (py-spy --gil, issue 37)
    mean_y = float(np.add.reduce(y) / len(y))
    means = (mean_y,) if c is None else (mean_y, float(np.add.reduce(c) / len(c)))
    mech = mech_span(theta, pole_pairs)
    # order 1 carried means every higher one is (mech_resolved: the span times the order)
    return _Segment(theta, np.asarray(t, dtype=float), y, c, pole_pairs, means, mech, mech_resolved(spec, 1, mech))


def _groups(segs: list[_Segment], piece: int) -> Iterator[list[tuple[int, int, int]]]:
    """The segments' pieces ``(segment, first, end)`` (at most ``piece`` samples) in groups of at
    most :data:`_GROUP` samples (or one piece) of one pole-pair count."""
    group: list[tuple[int, int, int]] = []
    size = 0
    for i, sg in enumerate(segs):
        for a in range(0, len(sg.theta), piece):
            b = min(a + piece, len(sg.theta))
            if group and (size + b - a > _GROUP or segs[group[0][0]].pole_pairs != sg.pole_pairs):
                yield group
                group, size = [], 0
            group.append((i, a, b))
            size += b - a
    if group:
        yield group


def _products(segs: list[_Segment], spec: FitSpec, k: int) -> np.ndarray:
    """Per segment ``[X y]^T [X y]`` (segments, m+k, m+k): the columns ``X`` (:func:`design_rows`),
    the torque (and ``kt * i_q``, zeros where a segment has none) about their means. Each segment's
    products have its own width (``m + 1``, or ``m + 2`` with a current channel), whatever the
    others carry: its figures do not depend on the motors compressed beside it."""
    m = spec.n_cols
    G = np.zeros((len(segs), m + k, m + k))
    # the pieces sized for the widest product (a current channel's row too), whatever this batch
    # carries: a segment's figures do not depend on the motors compressed beside it
    longest = max(1, min(_BLOCK, _SMALL_GEMM // ((m + 3) // 2 * (m + 2))))
    for group in _groups(segs, longest):
        N = sum(b - a for _, a, b in group)
        buf, work = _work_buffers((m + k + 2) * N, N)
        XT = buf[: (m + k) * N].reshape(m + k, N)
        theta, tn = buf[(m + k) * N : (m + k + 1) * N], buf[(m + k + 1) * N : (m + k + 2) * N]
        o = 0
        for i, a, b in group:
            sg, piece = segs[i], slice(o, o + b - a)
            theta[piece] = sg.theta[a:b]
            tp = np.subtract(sg.t[a:b], sg.t[0], out=tn[piece])
            tp *= 2.0 / (sg.t[-1] - sg.t[0])
            np.subtract(sg.torque[a:b], sg.means[0], out=XT[m, piece])
            if sg.kt_iq is not None:
                np.subtract(sg.kt_iq[a:b], sg.means[1], out=XT[m + 1, piece])
            o += b - a
        tn -= 1.0
        design_rows(theta, tn, segs[group[0][0]].pole_pairs, spec, XT, work)
        spans, o = [], 0
        for i, a, b in group:
            w = m + 1 + (segs[i].kt_iq is not None)
            if not segs[i].all_resolved:
                unresolved_to_zero(XT[:w, o : o + b - a], spec, segs[i].mech)
            spans.append((o, o + b - a, w))
            o += b - a
        # each piece's X^T X, X^T y and y^T y in one product, as two halves of rows (:data:`_SMALL_GEMM`),
        # the GIL released (numpy's matmul held it: gram_halves' docstring); a narrower piece's
        # product (no current channel) zero beyond its width, and so below the second half's diagonal
        Gp = gram_halves(XT, spans, np.zeros((len(group), m + k, m + k)))
        for (i, _, _), Gw in zip(group, Gp, strict=True):
            G[i] += Gw  # in the pieces' order (np.add.at would, at 8x the time)
    low, high = np.tril_indices(m + k, -1)
    G[:, low, high] = G[:, high, low]  # the lower triangle from the upper (the kernel's products are symmetric)
    return G


@dataclass(frozen=True)
class Summaries:
    """The normal-equation summaries of segments compressed together, one row a segment (the
    fields of :class:`Compressed` of the same names; ``current``: :func:`current_phasor`, zeros
    without ``kt_iq``)."""

    R: np.ndarray
    z: np.ndarray
    floor: np.ndarray
    sst: np.ndarray
    ymean: np.ndarray
    n: np.ndarray
    n_nuis: np.ndarray
    current: np.ndarray


def _compress_all(segs: list[_Segment], spec: FitSpec) -> Summaries:
    """Each segment's normal-equation summary and the current's ripple phasor per harmonic, the
    small factorisations batched over the segments."""
    m = spec.n_cols
    k = 2 if any(sg.kt_iq is not None for sg in segs) else 1
    G = _products(segs, spec, k)
    XtX = np.array(G[:, :m, :m])
    empty = np.diagonal(XtX, axis1=1, axis2=2) == 0.0
    # a column without data is pinned to 0 by a unit diagonal: its residual row reads 0 - g_j
    seg_i, col = np.nonzero(empty)
    XtX[seg_i, col, col] = 1.0
    Lc = np.linalg.cholesky(XtX)
    z = np.linalg.solve(Lc, G[:, :m, m : m + 1])[..., 0]  # triangular, tiny
    yy = G[:, m, m]
    floor = yy - np.einsum("si,si->s", z, z)
    phasor = np.zeros((len(segs), len(spec.harmonics)), dtype=complex)
    cur = [i for i, sg in enumerate(segs) if sg.kt_iq is not None]
    if cur:
        coef = np.linalg.solve(XtX[cur], G[cur, :m, m + 1 : m + 2])[..., 0]
        phasor[cur] = [current_phasor(c, spec) for c in coef]
    return Summaries(R=Lc.transpose(0, 2, 1), z=z, floor=floor, sst=yy, ymean=np.array([sg.means[0] for sg in segs]),
                      n=np.array([len(sg.theta) for sg in segs]), n_nuis=spec.n_nuis - empty.sum(axis=1), current=phasor)


def compress_segment(theta: np.ndarray, t: np.ndarray, torque: np.ndarray, pole_pairs: int,
                     spec: FitSpec) -> tuple[np.ndarray, np.ndarray, float, float, float, int, int]:
    """Normal-equation summary of one segment: (R, z, floor, sst, ymean, n, n_nuis).

    ``theta`` must be continuous (unwrapped), as :mod:`eol_cal.analysis.angle` returns it.
    """
    one = _compress_all([_segment(theta, t, torque, None, pole_pairs, spec)], spec)
    return (one.R[0], one.z[0], float(one.floor[0]), float(one.sst[0]), float(one.ymean[0]), int(one.n[0]),
            int(one.n_nuis[0]))


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
    return compress_many([seg], spec, n_segments)[0]


#: one segment's arrays as :func:`summarise_segments` takes them: angle (rad), time (s), torque and
#: ``kt * i_q`` (N*m, or None), and the motor's pole pairs
SegmentArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, int]


#: what computes a block's :class:`Summaries` (:func:`summarise_segments`, or another process's)
Summarise = Callable[[Sequence[SegmentArrays], FitSpec], Summaries]


def summarise_segments(todo: Sequence[SegmentArrays], spec: FitSpec) -> Summaries:
    """The normal-equation summaries of the segments ``todo`` (:func:`_compress_all`): what
    :func:`compress_many` computes, here or in another process
    (:mod:`~eol_cal.analysis.fit.compress_process`)."""
    return _compress_all([_segment(*arrays, spec) for arrays in todo], spec)


def compress_many(motors: Sequence[SteadySegments], spec: FitSpec, n_segments: int | None = None,
                  summarise: Summarise = summarise_segments) -> list[Compressed]:
    """:func:`compress` of each motor, their segments' columns built side by side (a few long numpy
    kernels for them all: :data:`_GROUP`), their small factorisations batched and their results
    laid out for all the motors at once (:func:`_assemble`). ``summarise``: what computes the
    segments' summaries (:func:`summarise_segments`, or another process's)."""
    S = n_segments or max((seg.n_segments for seg in motors), default=0)
    memo = _SHARED.get()
    fresh: dict[tuple[Any, ...], int] = {}  # a segment's key -> its index in segs (a scope's only)
    segs: list[SegmentArrays] = []
    held: list[tuple[tuple[Any, ...], tuple[Any, ...]]] = []
    # per motor, per segment: (the summaries holding it, None for this call's; its row there)
    where: list[list[tuple[Summaries | None, int]]] = []
    for seg in motors:
        rows: list[tuple[Summaries | None, int]] = []
        for s in range(seg.n_segments):
            kt_iq = None if seg.kt_iq is None else seg.kt_iq[s]
            arrays = (seg.theta[s], seg.t[s], seg.torque[s], kt_iq)
            if memo is None:  # without a scope every segment is its own (the same arrays twice: twice)
                rows.append((None, len(segs)))
                segs.append((*arrays, seg.pole_pairs))
                continue
            key = (*map(id, arrays), seg.pole_pairs, spec.harmonics, spec.drift_degree, spec.mech_order1,
                   spec.mech_orders)
            if key in memo:
                rows.append(memo[key][0])
            else:
                if key not in fresh:
                    fresh[key] = len(segs)
                    segs.append((*arrays, seg.pole_pairs))
                    held.append((key, arrays))
                rows.append((None, fresh[key]))
        where.append(rows)
    done = summarise(segs, spec) if segs else None
    if memo is not None:
        for key, arrays in held:
            memo[key] = ((done, fresh[key]), arrays)  # the arrays held: no id of the key is reused while it lasts
    return _assemble(motors, [[(src or done, i) for src, i in rows] for rows in where], spec, S)


def _assemble(motors: Sequence[SteadySegments], where: list[list[tuple[Any, int]]], spec: FitSpec,
              S: int) -> list[Compressed]:
    """Each motor's :class:`Compressed`, padded to ``S`` segments, from its segments' rows ``where``
    (per motor, per segment: the :class:`Summaries` and the row holding it): every field laid out
    for all the motors in one array (each motor's :class:`Compressed` holds its slice), filled by
    one indexed assignment per summaries, not by a few small ones per segment."""
    M, m, H = len(motors), spec.n_cols, len(spec.harmonics)
    R = np.tile(np.eye(m), (M, S, 1, 1))
    z = np.zeros((M, S, m))
    vec = {k: np.zeros((M, S)) for k in ("floor", "sst", "ymean", "n", "n_nuis", "i_qo", "omega")}
    current = np.zeros((M, S, H), dtype=complex)
    gain = np.ones((M, S, H), dtype=complex)
    by_source: dict[int, tuple[Summaries, list[int], list[int], list[int]]] = {}
    for j, (seg, rows) in enumerate(zip(motors, where, strict=True)):
        for s, (src, i) in enumerate(rows):
            _, mj, ms, mi = by_source.setdefault(id(src), (src, [], [], []))
            mj.append(j)
            ms.append(s)
            mi.append(i)
        vec["i_qo"][j, : seg.n_segments], vec["omega"][j, : seg.n_segments] = seg.i_qo, seg.omega_e
        if seg.path_response is not None:  # else path_gain's ones
            gain[j, : seg.n_segments] = path_gain(seg, spec)
    for src, *lists in by_source.values():
        at_j, at_s, row = (np.array(a, dtype=np.intp) for a in lists)  # once: a list is converted at each use
        R[at_j, at_s], z[at_j, at_s], current[at_j, at_s] = src.R[row], src.z[row], src.current[row]
        for k in ("floor", "sst", "ymean", "n", "n_nuis"):
            vec[k][at_j, at_s] = getattr(src, k)[row]
    parts = dict(R=R, z=z, gain_re=gain.real.copy(), gain_im=gain.imag.copy(), cur_re=current.real.copy(),
                 cur_im=current.imag.copy(), **vec)
    return [Compressed(**{k: v[j] for k, v in parts.items()}) for j in range(M)]


COMPRESSED_KEYS = ("R", "z", "n", "i_qo", "omega", "gain_re", "gain_im", "cur_re", "cur_im")


def compressed_dict(c: Compressed) -> dict[str, np.ndarray]:
    return {k: getattr(c, k) for k in COMPRESSED_KEYS}
