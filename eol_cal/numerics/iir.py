"""Zero-phase Butterworth low-pass in numpy alone: the ripple's filtered p-p without scipy.signal.

``scipy.signal`` imports ``scipy.stats`` and ``scipy.optimize`` (0.7-0.9 CPU s, more than the rest
of a one-capture ``eol-cal fit``) for the one filter the p-p figure uses. This module designs the
same second-order sections as ``scipy.signal.butter(order, f_c, fs=fs, output="sos")`` and filters
forward and backward as ``scipy.signal.sosfiltfilt`` does (odd extension of ``3 * (2 * sections + 1)``
samples, each pass started in the step response's steady state).

The recursion is not run sample by sample: the cascade is written as one state-space system
(:func:`state_space`) and the signal cut into blocks of :data:`BLOCK` samples; inside a block the
output is the block's input convolved with the impulse response (one matrix product for all
blocks) plus the response to the state the block starts in, and the states are carried from block
to block in log2(blocks) doubling steps. The result is the same linear filter in another order of
rounding: it agrees with scipy's to 1e-14 of the signal's range at a cut-off of 5e-2 x fs, 4e-11
at 2e-3 x fs (tests/test_numerics_filters.py).
"""

from __future__ import annotations

import functools

import numpy as np

#: samples per block: the Toeplitz product costs ``BLOCK`` multiplies a sample
BLOCK = 64


def butter_lowpass_sos(order: int, cutoff_hz: float, fs_hz: float) -> np.ndarray:
    """Second-order sections of a digital Butterworth low-pass (bilinear transform, pre-warped).

    The sections of ``scipy.signal.butter(order, cutoff_hz, fs=fs_hz, output="sos")``: the poles
    farthest from the unit circle first, both zeros of every section at z = -1, the gain in the first.

    Parameters
    ----------
    order : int
        Filter order (at least 1).
    cutoff_hz : float
        -3 dB frequency (Hz), between 0 and ``fs_hz / 2``.
    fs_hz : float
        Sample rate (Hz).

    Returns
    -------
    ndarray, shape (ceil(order / 2), 6)
        Rows ``b0, b1, b2, 1, a1, a2``.
    """
    if order < 1 or not 0.0 < cutoff_hz < fs_hz / 2.0:
        raise ValueError(f"Butterworth low-pass: order {order} >= 1 and 0 < cutoff {cutoff_hz} Hz < fs/2 {fs_hz / 2} Hz")
    # analog prototype, pre-warped cut-off (scipy's buttap, lp2lp_zpk and bilinear_zpk with fs = 2)
    p = -np.exp(1j * np.pi * np.arange(-order + 1, order, 2) / (2 * order))
    warped = 4.0 * np.tan(np.pi * (2.0 * cutoff_hz / fs_hz) / 2.0)
    p = warped * p
    k = warped**order
    p_z = (4.0 + p) / (4.0 - p)
    k_z = float(k * np.real(1.0 / np.prod(4.0 - p)))
    # one section per conjugate pair (and one for the real pole of an odd order), the poles
    # closest to the unit circle last
    is_real = np.abs(np.imag(p_z)) <= 1e-14 * np.abs(p_z)
    rows = [(1.0, 2.0, 1.0, 1.0, -2.0 * q.real, abs(q) ** 2) for q in map(complex, p_z[~is_real & (np.imag(p_z) > 0)])]
    rows += [(1.0, 2.0, 1.0, 1.0, -r, 0.0) for r in map(float, np.real(p_z[is_real]))]
    # the farthest poles from the unit circle first (the radius is sqrt(a2), or |a1| for the real one)
    sos = np.array(sorted(rows, key=lambda r: -abs(1.0 - (np.sqrt(r[5]) if r[5] else abs(r[4])))))
    if order % 2:  # the pole padded at z = 0 pairs with a zero at 0: the last section keeps one zero
        sos[-1, :3] = (1.0, 1.0, 0.0)
    sos[0, :3] *= k_z
    return sos


def step_cascade(sos: np.ndarray, s: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One sample of the cascade in transposed direct form II (scipy's ``sosfilt`` recursion).

    Parameters
    ----------
    sos : ndarray, shape (n, 6)
        Sections, ``a0 = 1``.
    s : ndarray, shape (2n, k)
        States ``z0, z1`` of each section, for ``k`` systems side by side.
    x : ndarray, shape (k,)
        Inputs.

    Returns
    -------
    new_state : ndarray, shape (2n, k)
    y : ndarray, shape (k,)
    """
    new = np.empty_like(s)
    y = x
    for i, (b0, b1, b2, _a0, a1, a2) in enumerate(sos):
        out = b0 * y + s[2 * i]
        new[2 * i] = b1 * y - a1 * out + s[2 * i + 1]
        new[2 * i + 1] = b2 * y - a2 * out
        y = out
    return new, y


def state_space(sos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``A, B, C, D`` of the cascade: ``s' = A s + B x``, ``y = C s + D x`` (the recursion is linear:
    its columns are its response to unit states and a unit input)."""
    m = 2 * len(sos)
    A, C = step_cascade(sos, np.eye(m), np.zeros(m))
    B, D = step_cascade(sos, np.zeros((m, 1)), np.ones(1))
    return A, B[:, 0], C, float(D[0])


@functools.lru_cache(maxsize=32)
def _blocks(sos_key: bytes, n_sections: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The block matrices of one cascade: Toeplitz impulse response ``T`` (L, L), state to output
    ``Ob`` (L, m), input to end state ``G`` (m, L), state over a block ``AL`` (m, m)."""
    sos = np.frombuffer(sos_key).reshape(n_sections, 6)
    A, B, C, D = state_space(sos)
    m = len(A)
    powers = np.empty((BLOCK + 1, m, m))  # A^0 .. A^L
    powers[0] = np.eye(m)
    for k in range(BLOCK):
        powers[k + 1] = A @ powers[k]
    Ob = np.einsum("j,kjl->kl", C, powers[:BLOCK])  # C A^k
    h = np.concatenate(([D], Ob[:-1] @ B))  # impulse response: D, C B, C A B, ...
    lag = np.arange(BLOCK)[:, None] - np.arange(BLOCK)[None, :]
    T = np.where(lag >= 0, h[np.clip(lag, 0, None)], 0.0)
    G = np.einsum("kjl,l->jk", powers[BLOCK - 1 :: -1], B)  # A^(L-1-j) B, column j
    # A fast-decaying response ends in subnormal numbers, which make the products ~1000x slower;
    # below 1e-200 of a unit input a term is far under the rounding of every output.
    return tuple(np.where(np.abs(M) < 1e-200, 0.0, M) for M in (T, Ob, G, powers[BLOCK]))  # type: ignore[return-value]


def sosfilt(sos: np.ndarray, x: np.ndarray, zi: np.ndarray) -> np.ndarray:
    """The cascade ``sos`` run over ``x`` from the states ``zi`` (shape (n, 2)); the output."""
    T, Ob, G, AL = _blocks(np.ascontiguousarray(sos, dtype=float).tobytes(), len(sos))
    n = len(x)
    nb = -(-n // BLOCK)
    flat = np.zeros(nb * BLOCK)
    flat[:n] = x
    X = flat.reshape(nb, BLOCK)
    # the state each block leaves: s_b+1 = AL s_b + U_b, a linear recurrence taken in log2(blocks)
    # doubling steps (Hillis-Steele) instead of a Python loop over the blocks
    P = X @ G.T  # each block's own contribution to the state it leaves
    P[0] += AL @ np.asarray(zi, dtype=float).reshape(-1)
    power, d = AL, 1
    while d < nb:
        P[d:] = P[d:] + P[:-d] @ power.T
        power, d = power @ power, 2 * d
    S = np.concatenate((np.asarray(zi, dtype=float).reshape(1, -1), P[:-1]))  # the state each block starts in
    return (X @ T.T + S @ Ob.T).reshape(-1)[:n]


def sosfilt_zi(sos: np.ndarray) -> np.ndarray:
    """Initial states (shape (n, 2)) for a unit step's steady state (scipy's ``sosfilt_zi``)."""
    zi = np.empty((len(sos), 2))
    scale = 1.0
    for i, (b0, b1, b2, a0, a1, a2) in enumerate(sos):
        b = np.array([b0, b1, b2]) / a0
        a = np.array([a0, a1, a2]) / a0
        i_minus_a = np.array([[1.0 + a[1], -1.0], [a[2], 1.0]])  # I - companion(a).T
        zi[i] = scale * np.linalg.solve(i_minus_a, b[1:] - a[1:] * b[0])
        scale *= b.sum() / a.sum()
    return zi


def sosfiltfilt(sos: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Forward-backward filtering of ``x`` with ``sos`` (scipy's ``sosfiltfilt``, ``padtype="odd"``).

    Raises
    ------
    ValueError
        ``x`` no longer than the padding (``3 * (2 * sections + 1)`` samples, less the sections
        without a second zero or pole).
    """
    x = np.asarray(x, dtype=float)
    ntaps = 2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    edge = 3 * ntaps
    if len(x) <= edge:
        raise ValueError(f"The length of the input vector x must be greater than padlen, which is {edge}.")
    ext = np.concatenate((2 * x[0] - x[edge:0:-1], x, 2 * x[-1] - x[-2 : -(edge + 2) : -1]))
    zi = sosfilt_zi(sos)
    y = sosfilt(sos, ext, zi * ext[0])
    y = sosfilt(sos, y[::-1], zi * y[-1])[::-1]
    return y[edge:-edge]


def lowpass_zero_phase(x: np.ndarray, fs_hz: float, cutoff_hz: float, order: int = 6) -> np.ndarray:
    """Zero-phase Butterworth low-pass (forward-backward, so the magnitude is squared).

    Parameters
    ----------
    x : ndarray
        Signal (any unit), sampled uniformly at ``fs_hz``.
    fs_hz : float
        Sample rate (Hz).
    cutoff_hz : float
        -3 dB frequency of one pass (Hz); the forward-backward response is -6 dB there.
    order : int
        Order of one pass.

    Returns
    -------
    y : ndarray
        Filtered signal (unit of ``x``); ``x`` unchanged when the cut-off is at or above
        0.9 times the Nyquist frequency (nothing to remove that the samples can hold).
    """
    if cutoff_hz >= 0.45 * fs_hz:
        return np.asarray(x, dtype=float).copy()
    return sosfiltfilt(butter_lowpass_sos(order, cutoff_hz, fs_hz), x)
