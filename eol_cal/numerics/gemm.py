"""``x @ x.T`` of a few long rows by numpy's own BLAS calls, made with the GIL released.

numpy's ``matmul`` is a generalized ufunc: it releases the GIL only for an iteration of 500
elements or more, and it counts the output's (``NPY_BEGIN_THREADS_THRESHOLDED`` in numpy's
``ufunc_object.c``). The fit's compression multiplies 16-17 rows of thousands of samples into
outputs of 8 x 16 (:func:`eol_cal.analysis.fit.compression._products`): each product, 20-50 us, ran
under the GIL, a quarter of a compression thread's time (py-spy ``--gil``, issue 37). :func:`gram_halves`
makes the calls numpy's ``matmul`` makes (the same ``cblas_dgemm`` of the same library with the same
arguments: the same products, bit for bit) through ctypes, which releases the GIL during each; where
numpy's BLAS does not export the symbol (another build of numpy) or a call would differ, ``np.matmul``.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Sequence
from typing import Any

import numpy as np
try:  # numpy 2's extension module; numpy 1.x (pyproject allows >= 1.26) names it numpy.core's: np.matmul then
    from numpy._core import _multiarray_umath  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - numpy 1.x
    _multiarray_umath = None

#: CBLAS's enums: row-major order, no transpose, transpose
_ROW_MAJOR, _NO_TRANS, _TRANS = 101, 111, 112
#: the ILP64 ``cblas_dgemm`` of numpy's wheels (scipy-openblas64, its symbols renamed): 64-bit integers
_SYMBOLS = ("scipy_cblas_dgemm64_", "cblas_dgemm64_")


@functools.cache
def _dgemm() -> Any | None:
    """numpy's ``cblas_dgemm`` as a ctypes function (the GIL released during the call), or None where
    it is not found or does not give ``np.matmul``'s products bit for bit on a probe."""
    try:
        # numpy's extension module's handle: dlsym searches the libraries it was linked with, its BLAS
        lib = ctypes.CDLL(_multiarray_umath.__file__)
    except (OSError, TypeError, AttributeError):  # AttributeError: numpy 1.x, no module (np.matmul)
        return None
    fn = next((getattr(lib, name) for name in _SYMBOLS if hasattr(lib, name)), None)
    if fn is None:
        return None
    i64, f64, ptr = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, i64, i64, i64, f64, ptr, i64, ptr, i64, f64, ptr, i64]
    fn.restype = None
    # a probe of two spans of 7 and 5 rows, columns apart (the leading dimension beyond the width)
    probe, spans = np.random.default_rng(0).standard_normal((7, 45))[:, 3:], [(0, 37, 7), (2, 30, 5)]
    got, want = (halves(probe, spans, np.zeros((2, 7, 7))) for halves in (functools.partial(_blas_halves, fn),
                                                                          _numpy_halves))
    return fn if np.array_equal(got, want) else None


def gram_halves(x: np.ndarray, spans: Sequence[tuple[int, int, int]], out: np.ndarray) -> np.ndarray:
    """Each span's ``x[:w, first:end] @ x[:w, first:end].T``, its upper triangle, into ``out[j, :w, :w]``,
    as two products of half the rows each, with the GIL released where numpy's BLAS is reachable
    (module docstring); bit for bit ``np.matmul``'s.

    Two halves, not one product: numpy's ``x @ x.T`` is SYRK, which packs its operands; a half's
    product of at most 100^3 multiplications is OpenBLAS's small-matrix GEMM, which does not (12 ns
    a sample against 25 at 16 rows, :data:`eol_cal.analysis.fit.compression._SMALL_GEMM`). The
    second half's rows start one column left of the diagonal (``x[h:] @ x[h - 1:].T``): numpy sends
    a product of the same rows on both sides to SYRK. Every span in one call: the arrays' addresses
    are looked up once (a lookup costs as much as the call, and both hold the GIL).

    Parameters
    ----------
    x : ndarray, (rows, N)
        float64, rows of unit stride (rows of a larger array are fine).
    spans : sequence of (first, end, w)
        Columns ``first:end`` of ``x``'s first ``w`` rows (``w`` >= 4) for ``out[j]``.
    out : ndarray, (len(spans), W, W)
        float64, C-contiguous, apart from ``x``, ``W`` >= every ``w``. Written: of ``out[j]``, the
        first ``h = (w + 1) // 2`` rows up to column ``w`` and the others from column ``h - 1`` to
        ``w``; the rest left as it is.

    Returns
    -------
    ndarray
        ``out``.
    """
    fn = _dgemm()
    # what numpy's matmul sends to gemm: matrices (no dimension of 1: those go to gemv or its own
    # loop), float64, unit strides along the rows, rows at least as far apart as they are long
    plain = (fn is not None and x.dtype == out.dtype == np.float64 and out.flags.c_contiguous
             and x.strides[1] == 8 and x.strides[0] % 8 == 0 and x.strides[0] >= 8 * x.shape[1]
             and all(w >= 4 and end - first >= 2 for first, end, w in spans))
    return _blas_halves(fn, x, spans, out) if plain else _numpy_halves(x, spans, out)


def _blas_halves(fn: Any, x: np.ndarray, spans: Sequence[tuple[int, int, int]], out: np.ndarray) -> np.ndarray:
    """:func:`_numpy_halves` by the calls numpy's matmul makes: row-major, the left rows as they are,
    the right ones transposed, the leading dimensions the row strides (elements)."""
    px, po = x.__array_interface__["data"][0], out.__array_interface__["data"][0]
    ldx, ldo = x.strides[0] // 8, out.shape[2]
    for j, (first, end, w) in enumerate(spans):
        h, a, c = (w + 1) // 2, px + 8 * first, po + out.strides[0] * j
        fn(_ROW_MAJOR, _NO_TRANS, _TRANS, h, w, end - first, 1.0, a, ldx, a, ldx, 0.0, c, ldo)
        fn(_ROW_MAJOR, _NO_TRANS, _TRANS, w - h, w - h + 1, end - first, 1.0, a + 8 * h * ldx, ldx,
           a + 8 * (h - 1) * ldx, ldx, 0.0, c + 8 * (h * ldo + h - 1), ldo)
    return out


def _numpy_halves(x: np.ndarray, spans: Sequence[tuple[int, int, int]], out: np.ndarray) -> np.ndarray:
    """:func:`gram_halves` by ``np.matmul`` (the GIL held)."""
    for j, (first, end, w) in enumerate(spans):
        xs, h = x[:w, first:end], (w + 1) // 2
        np.matmul(xs[:h], xs.T, out=out[j, :h, :w])
        np.matmul(xs[h:], xs[h - 1 :].T, out=out[j, h:w, h - 1 : w])
    return out
