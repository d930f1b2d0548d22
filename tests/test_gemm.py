"""numpy's own dgemm called with the GIL released (eol_cal/numerics/gemm.py, issue 37): the products
are numpy's matmul's bit for bit, with its BLAS reached or not, and the call leaves the GIL."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from eol_cal.numerics import gemm

_blas_halves = gemm._blas_halves


def _spans(rng, lengths):
    """Pieces of the given lengths (columns), of 17, 16, 4, 5 and 9 rows in turn, a few columns apart."""
    spans, o = [], 0
    for j, n in enumerate(lengths):
        spans.append((o, o + n, (17, 16, 4, 5, 9)[j % 5]))
        o += n + int(rng.integers(0, 3))
    return spans


def _reference(x, spans, W):
    """The two halves as compression.py computed them before (np.matmul), each into its own array."""
    out = np.zeros((len(spans), W, W))
    for j, (a, b, w) in enumerate(spans):
        xs, h, Gw = x[:w, a:b], (w + 1) // 2, np.zeros((w, w))
        np.matmul(xs[:h], xs.T, out=Gw[:h])
        np.matmul(xs[h:], xs[h - 1 :].T, out=Gw[h:, h - 1 :])
        out[j, :w, :w] = Gw
    return out


#: pieces' lengths: numpy's gemm for all; and with a piece of one sample (numpy's special case: the
#: whole call left to np.matmul)
LENGTHS = {"gemm": [2, 3, 5000, 37, 2, 1200, 4, 6535, 8000], "one sample": [1200, 1, 5000, 2]}


@pytest.mark.parametrize("blas", [True, False])
@pytest.mark.parametrize("lengths", LENGTHS)
def test_the_halves_are_numpys_matmul_bit_for_bit(blas, lengths, monkeypatch):
    if not blas:
        monkeypatch.setattr(gemm, "_dgemm", lambda: None)  # another numpy build: np.matmul itself
    gemm._dgemm()  # its probe done before the spy below
    calls = []
    monkeypatch.setattr(gemm, "_blas_halves", lambda *a: calls.append(1) or _blas_halves(*a))
    rng = np.random.default_rng(11)
    x = (rng.standard_normal((17, 30000)) * 10 ** rng.uniform(-3, 3, (17, 30000)))[:, 7:]
    spans = _spans(rng, LENGTHS[lengths])
    got = gemm.gram_halves(x, spans, np.zeros((len(spans), 17, 17)))
    np.testing.assert_array_equal(got, _reference(x, spans, 17))
    assert len(calls) == (blas and lengths == "gemm" and gemm._dgemm() is not None)


def test_numpys_blas_is_reached_and_the_call_leaves_the_gil():
    """numpy's wheels bring scipy-openblas64, its cblas_dgemm exported under its own name; ctypes
    releases the GIL around a call of a CDLL's function (not a PyDLL's)."""
    if np.__config__.CONFIG["Build Dependencies"]["blas"].get("name") != "scipy-openblas":
        pytest.skip("numpy is not built with scipy-openblas: np.matmul serves (the test above)")
    fn = gemm._dgemm()
    assert fn is not None
    assert not fn._flags_ & ctypes._FUNCFLAG_PYTHONAPI  # type: ignore[attr-defined]


def test_a_view_of_other_strides_is_left_to_numpy():
    """Rows not of unit stride, or an output that is not C-contiguous: numpy's own path, the same figures."""
    rng = np.random.default_rng(2)
    x = rng.standard_normal((16, 400))
    xf = np.asfortranarray(x)
    spans = [(0, 200, 16), (200, 400, 16)]
    np.testing.assert_array_equal(gemm.gram_halves(xf, spans, np.zeros((2, 16, 16))), _reference(xf, spans, 16))
    out = np.zeros((2, 16, 32))[:, :, ::2]
    np.testing.assert_array_equal(gemm.gram_halves(x, spans, out), _reference(x, spans, 16))
