"""One pass over a motor's segments side by side: what the noise at the harmonics
(:func:`~eol_cal.analysis.fit.segment_noise.segment_noise`) reads that is a function of the sample
alone, built for every segment by a few long numpy calls.

Segment by segment, the columns, the bins' exponentials and each line's turn took ~60 numpy calls
of a few thousand samples each (issue 37 item 2). Here each is one call over the segments' samples
side by side, each segment's samples one contiguous piece (:class:`Layout`); the few operations that
take a segment's own scalar (its first sample, its length) are one call a segment. Every operation
is elementwise, the same on every sample as the per-segment construction's (:func:`~eol_cal.analysis.
fit.model.design_matrix_t`, :func:`~eol_cal.analysis.fit.model.bin_steps`, :func:`~eol_cal.analysis.
fit.model.line_noise`'s turn): the same values bit for bit, but for the exponentials ``exp(-i x)``,
taken from :func:`~eol_cal.numerics.expi.exp_i` (within ~1 ulp of numpy's complex ``exp``, which
was a fifth of the noise's time): the noise within 1e-13 relative of the per-segment construction's
(tests/test_fit_segment_noise.py).

The arrays are written into buffers this thread keeps for the next motor (a fresh array of
megabytes is mmap'ed and page-faulted afresh on every call, ~2 us a page on this VM: as much as the
arithmetic, the compression's reason too; up to :data:`KEEP_BYTES` each); what a function returns is
valid until its next call in the same thread.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.fit.model import FitSpec, SteadySegments, design_rows, mech_span, unit_time, unresolved_to_zero
from eol_cal.numerics.expi import exp_i, step_powers
from eol_cal.numerics.gemm import gram_halves

_BUFFERS = threading.local()
#: the largest buffer a thread keeps (bytes): a refit's serial (six segments of 3333 samples) needs
#: 3.2 MB at most; a station capture's motor (170 000 samples) gets fresh arrays, as segment by
#: segment before, rather than ~80 MB held for the process' life
KEEP_BYTES = 8 << 20


def _buffer(name: str, size: int, dtype: type = float) -> np.ndarray:
    """This thread's buffer ``name``: a flat array of at least ``size`` elements (grown, never shrunk;
    a fresh one, not kept, above :data:`KEEP_BYTES`)."""
    buf = getattr(_BUFFERS, name, None)
    if buf is None or buf.size < size:
        buf = np.empty(max(size, 1), dtype=dtype)
        if buf.nbytes <= KEEP_BYTES:
            setattr(_BUFFERS, name, buf)
    return buf


@dataclass(frozen=True)
class Layout:
    """A motor's segments side by side: segment ``s``'s samples are ``offsets[s]:offsets[s + 1]``.

    Attributes
    ----------
    theta, t : list of ndarray
        Each segment's electrical angle (rad) and time (s), float64.
    offsets : ndarray of int, (segments + 1,)
        Where each segment's samples start in the side-by-side arrays (the last: all samples).
    T : ndarray, (segments,)
        Each segment's length ``t[-1] - t[0]`` (s).
    """

    theta: list[np.ndarray]
    t: list[np.ndarray]
    offsets: np.ndarray
    T: np.ndarray

    def pieces(self) -> list[slice]:
        """Each segment's samples in the side-by-side arrays."""
        return [slice(int(a), int(b)) for a, b in zip(self.offsets[:-1], self.offsets[1:], strict=True)]


def layout(seg: SteadySegments) -> Layout:
    """:class:`Layout` of ``seg``'s segments."""
    theta = [np.asarray(x, dtype=float) for x in seg.theta]
    t = [np.asarray(x, dtype=float) for x in seg.t]
    offsets = np.concatenate([[0], np.cumsum([len(x) for x in t])]).astype(int)
    return Layout(theta, t, offsets, np.array([float(x[-1] - x[0]) for x in t]))


def columns(seg: SteadySegments, spec: FitSpec, lay: Layout) -> tuple[np.ndarray, np.ndarray]:
    """Every segment's columns (:func:`~eol_cal.analysis.fit.model.design_matrix_t`, as rows) side by
    side, (spec.n_cols, samples), and each segment's normal matrix's upper triangle (segments, m, m;
    :func:`~eol_cal.numerics.gemm.gram_halves`, one call for all), ``m = spec.n_cols``."""
    m, N = spec.n_cols, int(lay.offsets[-1])
    XT = _buffer("columns", m * N)[: m * N].reshape(m, N)
    theta, tn = _buffer("theta", N)[:N], _buffer("tn", N)[:N]
    work = _buffer("work", 4 * N, complex)[: 4 * N].reshape(4, N)
    pieces = lay.pieces()
    for th, t, piece in zip(lay.theta, lay.t, pieces, strict=True):
        theta[piece] = th
        unit_time(t, t[0], t[-1], out=tn[piece])  # design_matrix_t's time axis, each segment its own
    design_rows(theta, tn, seg.pole_pairs, spec, XT, work)
    for th, piece in zip(lay.theta, pieces, strict=True):
        unresolved_to_zero(XT[:, piece], spec, mech_span(th, seg.pole_pairs))
    G = gram_halves(XT, [(p.start, p.stop, m) for p in pieces], np.zeros((len(pieces), m, m)))
    return XT, G


def bin_powers(lay: Layout, top: int) -> np.ndarray:
    """``exp(-i b)^j`` for ``j = 0..top`` (top + 1, samples), complex, ``b = 2 pi (t - t[0]) / T``
    per segment: :func:`~eol_cal.analysis.fit.model.bin_steps`' powers, every segment's side by side."""
    N = int(lay.offsets[-1])
    b = _buffer("b", N)[:N]
    for t, T, piece in zip(lay.t, lay.T, lay.pieces(), strict=True):
        # 2 pi (t - t[0]) / T, in that order
        bp = np.subtract(t, t[0], out=b[piece])
        np.multiply(2 * math.pi, bp, out=bp)
        np.divide(bp, T, out=bp)
    step = _exp_minus_i(b, _buffer("step", N, complex)[:N])
    return step_powers(step, top, _buffer("powers", (top + 1) * N, complex)[: (top + 1) * N].reshape(top + 1, N))


def line_turns(lay: Layout, harmonics: tuple[int, ...]) -> np.ndarray:
    """Each harmonic's turn ``exp(-i h (theta - theta[0]))`` (harmonics, samples), complex, per segment
    (:func:`~eol_cal.analysis.fit.model.line_noise`'s ``exp(-i a)``)."""
    N = int(lay.offsets[-1])
    turned, a = _buffer("turned", N)[:N], _buffer("angle", N)[:N]
    for th, piece in zip(lay.theta, lay.pieces(), strict=True):
        np.subtract(th, th[0], out=turned[piece])  # once for every harmonic
    turns = _buffer("turns", len(harmonics) * N, complex)[: len(harmonics) * N].reshape(len(harmonics), N)
    for j, h in enumerate(harmonics):
        np.multiply(h, turned, out=a)
        _exp_minus_i(a, turns[j])  # negates a in place: turned stays
    return turns


def _exp_minus_i(x: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``out = exp(-i x)`` for real ``x`` (rad; ``x`` is negated in place): :func:`~eol_cal.numerics.
    expi.exp_i`, within ~1 ulp of numpy's ``np.exp(-1j * x)`` at a quarter of its time (glibc's
    complex ``exp`` per sample, twice over the samples, was a fifth of the noise's time)."""
    n = len(x)
    w = _buffer("exp_work", 3 * n, complex)[: 3 * n].reshape(3, n)
    return exp_i(np.negative(x, out=x), out, w[0], w[1], w[2])


def line_rows(powers: np.ndarray, k: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """A line's bins ``exp(-i (a + b k))`` of one segment as real rows (2 bins, n): the real parts,
    then the imaginary (:func:`~eol_cal.analysis.fit.model.bins_noise`'s ``wri``). ``powers``: the
    segment's :func:`bin_powers` (up to ``max |k|``), ``k`` the bins (integers, none zero), ``turn``
    the segment's :func:`line_turns` of the line."""
    nb, n = len(k), len(turn)
    w = _buffer("bins", nb * n, complex)[: nb * n].reshape(nb, n)
    # bin by bin from the powers' rows (np.take copies a strided source whole first: a
    # tenth of the noise's time)
    for row, kj in zip(w, k.astype(int), strict=True):
        if kj > 0:
            np.multiply(powers[kj], turn, out=row)
        else:
            np.conjugate(powers[-kj], out=row)  # exp(-i b)^-k = conj
            np.multiply(row, turn, out=row)
    wri = _buffer("rows", 2 * nb * n)[: 2 * nb * n].reshape(2 * nb, n)
    np.copyto(wri[:nb], w.real)
    np.copyto(wri[nb:], w.imag)
    return wri
