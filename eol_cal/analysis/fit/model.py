"""The fit's model: what is fitted (FitSpec), its array-level input (SteadySegments), the design matrix.

Model (firmware contract section 2, plus the measurement's nuisances), per sample of segment s::

    T = T_avg[s] + drift_s(t) + mech_s(theta_m)
        - sum_h [ c_h sin(h (theta - omega_s tau) + phase_c_h)
                  + k_h i_qo[s] sin(h (theta - omega_s tau) + phase_k_h) ]
        + sum_h [ kt i_q ]_h (theta - omega_s tau)

``theta`` is the electrical angle (rad) in the frame the firmware uses, ``h`` runs over the
requested harmonics (6, optionally 12 and 18), ``[kt i_q]_h`` the h-th harmonic of the torque
the ECU's measured q current makes (known, where the captures carry it: ``SteadySegments.kt_iq``),
``tau`` (s) is the torque transducer's delay: the
measured torque lags, so harmonic h is seen at phase ``h (theta - omega_e tau)``, a shift that
grows with the electrical speed ``omega_e`` (rad/s, signed). ``drift_s`` is a Legendre polynomial
in time per segment (degree ``drift_degree``, its constant term is T_avg), ``mech_s`` a cos/sin pair
at mechanical order 1 (``theta_m = theta / (P/2)``) per segment: its phase is unknown between
segments because halls only give the electrical angle.

A segment holds one load point (constant ``i_qo``), one speed and one direction, so within a
segment the model is linear in a handful of columns (Legendre terms, mechanical cos/sin, sin/cos
of h theta): :func:`design_matrix`. The compression (:mod:`eol_cal.analysis.fit.compression`) and
the solver (:mod:`eol_cal.analysis.fit.solver`) build on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.errors import InputError
from eol_cal.numerics.expi import cpow_into, exp_i, step_powers

#: scale of the delay parameter inside the solver (s); keeps the parameter vector near O(1)
TAU_SCALE = 1e-4
#: z for a two-sided 95 % normal interval (n is in the thousands, so t ~ normal)
Z95 = 1.959963984540054


@dataclass(frozen=True)
class FitSpec:
    """What to fit and how.

    Attributes
    ----------
    harmonics : tuple of int
        Electrical orders of the ripple terms; always starts with 6; 12 and 18 optional.
    fit_c : bool
        Fit the load-independent (cogging) part c_h. Needs at least two load points together with
        ``fit_k``.
    fit_k : bool
        Fit the load-proportional part k_h (N*m/A).
    drift_degree : int
        Degree of the per-segment Legendre polynomial in time (0 = constant T_avg only).
    mech_order1 : bool
        Include the mechanical orders per segment (False: none).
    mech_orders : int
        How many mechanical orders (1..mech_orders) each segment carries as its own cos/sin pairs
        (default 3, what the block compensates): in the segment's nuisance, so that a mechanical
        order never leaks into the electrical harmonics; their phases are free per segment (the
        halls do not tell the pole pair), their shared values are fitted afterwards in the
        fingerprint's frame (:mod:`eol_cal.analysis.fit.mech_orders`).
    delay_s : float or None
        Known transducer delay (s); ``None`` estimates it (needs two different signed speeds).
    delay_max_s : float or None
        Upper end of the grid that starts the delay estimate (s); default 5 ms for the low-pass
        model, 1 ms for the pure delay (whose delay is unique only modulo ``2 pi / (6 d_omega)``,
        d_omega the difference of two segment speeds: 2.8 ms for +-600 rpm, 6 poles).
    transducer : {"delay", "lowpass"}
        How the torque transducer distorts harmonic h at electrical speed omega: a pure delay
        ``tau`` (phase ``-h omega tau``), or a first-order low-pass of time constant ``tau``
        (gain and phase of ``1 / (1 + i h omega tau)``).
    max_steps : int
        Levenberg-Marquardt step limit; hitting it means "not converged".
    rtol, atol : float
        Solver tolerances (Jacobi-scaled coordinates).
    solver : {"gn", "lm"}
        Gauss-Newton or Levenberg-Marquardt (optimistix).
    lm_init_step : float
        Levenberg-Marquardt's initial trust-region step (1 / initial damping).
    lack_of_fit : bool
        Widen the intervals by the between-segment lack of fit (Birge ratio) when it exceeds 1.
    """

    harmonics: tuple[int, ...] = (6, 12, 18)
    fit_c: bool = True
    fit_k: bool = True
    drift_degree: int = 2
    mech_order1: bool = True
    mech_orders: int = 3
    delay_s: float | None = None
    delay_max_s: float | None = None
    transducer: str = "lowpass"
    max_steps: int = 64
    rtol: float = 1e-6
    atol: float = 1e-8
    solver: str = "gn"
    lack_of_fit: bool = True
    lm_init_step: float = 1e3

    @property
    def n_mech(self) -> int:
        """Mechanical cos/sin pairs per segment (one pinned pair when switched off, as before)."""
        return self.mech_orders if self.mech_order1 else 1

    @property
    def n_cols(self) -> int:
        """Columns per segment: Legendre terms, mechanical cos/sin pairs, sin/cos per harmonic."""
        return self.n_nuis + 2 * len(self.harmonics)

    @property
    def n_nuis(self) -> int:
        """Nuisance parameters per segment (drift polynomial and mechanical pairs)."""
        return self.drift_degree + 1 + 2 * self.n_mech

    @property
    def n_glob(self) -> int:
        """Global cos/sin ripple coefficients."""
        return 2 * len(self.harmonics) * (int(self.fit_c) + int(self.fit_k))

    @property
    def delay_max(self) -> float:
        """Upper end of the delay start grid (s)."""
        if self.delay_max_s is not None:
            return self.delay_max_s
        return 5e-3 if self.transducer == "lowpass" else 1e-3

    @property
    def fit_delay(self) -> bool:
        return self.delay_s is None


@dataclass
class SteadySegments:
    """Samples of one motor, steady segment by steady segment (the fit's array-level input).

    A steady segment is a piece of a capture at one load point, speed and direction, whole
    electrical revolutions long (:func:`eol_cal.analysis.fit.capture.capture_segments`); not a
    test profile's segment (:class:`eol_cal.plant.profile.ProfileSegment`).

    Attributes
    ----------
    theta : list of ndarray
        Electrical angle per segment (rad, continuous, firmware frame).
    t : list of ndarray
        Sample times per segment (s).
    torque : list of ndarray
        Measured shaft torque per segment (N*m).
    i_qo : ndarray
        Nominal q current of each segment (A, signed).
    omega_e : ndarray
        Mean electrical speed of each segment (rad/s, signed).
    pole_pairs : int
        P/2.
    labels : list of str
        Where each segment came from (file and sample range), for messages and the result.
    path_response : callable, optional
        Complex response of the path from the motor's air-gap torque to the shaft torque the
        transducer sees, at angular frequencies (rad/s, signed): ``omega -> ndarray of complex``
        (:func:`eol_cal.domain.bench_mechanics.shaft_response` for a bench). The fitted ripple is the air-gap one;
        ``None`` takes the coupling as rigid (response 1).
    kt_iq : list of ndarray, optional
        Per segment, the air-gap torque the ECU's measured q current makes, ``kt * i_q`` (N*m),
        sample for sample with ``torque``. Its ripple (the current loop's own: its angle
        estimate's errors, the back-EMF's reaction to the speed ripple) is torque on the shaft
        too; given, the fit takes it as known, through the same path and transducer as the
        motor's ripple, so that ``c_h``, ``k_h`` are the motor's own (the paper's k6).
        ``None``: no current channel, the current's ripple is fitted as part of ``c_h``, ``k_h``.
    """

    theta: list[np.ndarray]
    t: list[np.ndarray]
    torque: list[np.ndarray]
    i_qo: np.ndarray
    omega_e: np.ndarray
    pole_pairs: int
    labels: list[str] = field(default_factory=list)
    path_response: Callable[[np.ndarray], np.ndarray] | None = None
    kt_iq: list[np.ndarray] | None = None

    @property
    def n_segments(self) -> int:
        return len(self.theta)


def path_gain(seg: SteadySegments, spec: FitSpec) -> np.ndarray:
    """``seg.path_response`` at every segment's harmonics, shape (segments, harmonics), complex."""
    freq = np.outer(seg.omega_e, np.asarray(spec.harmonics, dtype=float))
    if seg.path_response is None:
        return np.ones(freq.shape, dtype=complex)
    return np.asarray(seg.path_response(freq), dtype=complex).reshape(freq.shape)


def transducer_gain(spec: FitSpec, tau_s: float, omega: np.ndarray | float) -> np.ndarray:
    """The fit's transducer model (``spec.transducer``, time constant or delay ``tau_s`` in s) at
    angular frequencies ``omega`` (rad/s, signed): complex gain, numpy (the plots, the mechanical
    orders and the model check; the solver's JAX model spells it in its own columns)."""
    omega = np.asarray(omega, dtype=float)
    if spec.transducer == "lowpass":
        return 1.0 / (1.0 + 1j * omega * tau_s)
    return np.exp(-1j * omega * tau_s)


#: the neighbouring frequencies ``f + k / T`` of a segment (T its length) the noise at a line of
#: frequency f is measured on (the model check's 6th, the mechanical orders): 2 <= |k| <= NOISE_BINS
#: (|k| = 1 would hold the leakage of the mechanical order 1's sidebands at 60 rpm, 1 Hz beside the 6th)
NOISE_BINS = 9


def noise_bins() -> np.ndarray:
    """The bins ``k`` (float): every integer with ``2 <= |k| <=`` :data:`NOISE_BINS`."""
    return np.array([k for k in range(-NOISE_BINS, NOISE_BINS + 1) if abs(k) >= 2], dtype=float)


def bin_steps(b: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``exp(-i b k)`` (n, bins) for integer ``k`` (each at least 1 or at most -1): a line's bins are
    its turn ``exp(-i a)`` times them (:func:`line_noise`), the same for every line of a segment.
    Powers of ``exp(-i b)`` instead of one complex exponential per sample and bin (a refit's model
    check spent 30 % of its time in them); the same values within the rounding of the phase itself.
    Returned as the transpose of a contiguous (bins, n) array: a bin's column is one contiguous row
    (``.T[keep].T`` picks bins by a copy of whole rows; gathering and conjugating the columns of an
    (n, bins) array cost 8 ms of a 13 000-sample segment, 20x the products that read them)."""
    powers = step_powers(np.exp(-1j * b), int(np.max(np.abs(k))))
    ki = k.astype(int)
    rows = powers[np.abs(ki)]
    np.conjugate(rows, out=rows, where=(ki < 0)[:, None])  # exp(-i b)^-k = conj
    return rows.T


def line_noise(res: np.ndarray, cur_res: np.ndarray | None, a: np.ndarray, b: np.ndarray, k: np.ndarray,
               omega: np.ndarray, spec: FitSpec, tau_s: float,
               path: Callable[[np.ndarray], np.ndarray] | None, basis: tuple[np.ndarray, np.ndarray] | None = None,
               steps: np.ndarray | None = None) -> float:
    """The variance (N*m^2) noise alone puts on one cos/sin coefficient of a line's pair in a segment.

    Measured on the residual's phasors ``(2 / n) sum res exp(-i (a + b k))`` at the line's
    neighbouring bins ``k`` (:func:`noise_bins`; ``a`` the line's phase, ``b`` ``2 pi t / T`` per
    sample). With the ECU's current taken out of the fit (``cur_res``: ``kt * i_q`` less what the
    fit took as known, N*m) its noise reaches the shaft through the bench's response ``path``
    (None: 1) and the transducer (``spec``, ``tau_s`` in s) at the bins' rates ``omega`` (rad/s,
    signed): so it is taken out here too, bin by bin (the current's noise that reaches the shaft
    cancels, the current sensor's own does not). ``basis``: the columns the residual was fitted on,
    as rows (p, n), and the inverse of their normal matrix (p, p); each bin's power is divided by
    the share of it the fit left (a bin the drift polynomial or a fitted line half overlaps holds half
    the noise: read as it is, it made white noise at the 6th 7 % low on 0.05 s segments).
    ``steps``: :func:`bin_steps` of ``b`` and ``k``, when the caller measures several lines of one
    segment (the same bins about each).
    """
    if steps is None:
        steps = bin_steps(b, k)
    # the line's bins exp(-i (a + b k)) = exp(-i a) exp(-i b k), the line's turn applied once
    w = steps.T * np.exp(-1j * a)
    return bins_noise(res, cur_res, np.concatenate([w.real, w.imag]), omega, spec, tau_s, path, basis)


def bins_noise(res: np.ndarray, cur_res: np.ndarray | None, wri: np.ndarray, omega: np.ndarray, spec: FitSpec,
               tau_s: float, path: Callable[[np.ndarray], np.ndarray] | None,
               basis: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """:func:`line_noise` from the line's bins ``exp(-i (a + b k))`` as real rows ``wri`` (2 bins, n):
    the real part of every bin, then the imaginary (every sum over the samples below is one real
    product, the signals' and the basis', half the multiplications of complex ones on real operands).
    The other arguments as :func:`line_noise`'s."""
    n = len(res)
    nb = len(wri) // 2
    sig = res[None, :] if cur_res is None else np.stack([res, cur_res])
    X = (2.0 / n) * (sig @ wri.T)
    e = X[0, :nb] + 1j * X[0, nb:]
    if cur_res is not None:
        g = transducer_gain(spec, tau_s, omega)
        if path is not None:
            g = g * np.asarray(path(omega), dtype=complex)
        e = e - g * (X[1, :nb] + 1j * X[1, nb:])
    power = np.abs(e) ** 2
    if basis is not None:
        # |Q^T w|^2 of an orthonormal basis Q of the columns A: w^T A (A^T A)^-1 A^T w, re and im
        cols, g_inv = basis
        V = cols @ wri.T
        share = np.sum(V * (g_inv @ V), axis=0)
        power = power / np.maximum(1.0 - (share[:nb] + share[nb:]) / n, 0.1)
    return float(np.mean(power)) / 2.0


def check_identifiable(seg: SteadySegments, spec: FitSpec, source: str | None = None,
                       left_out: Sequence[tuple[str, str]] = ()) -> None:
    """Refuse a request the data cannot answer (InputError naming what is missing).

    Parameters
    ----------
    seg : SteadySegments
        The motor's segments.
    spec : FitSpec
        The request.
    source : str, optional
        File(s) named in the error.
    left_out : sequence of (str, str)
        Captures that gave no segment and why: a refusal names them, since they are often its
        real cause (a speed or a load point that is missing because its captures were too short).
    """
    why_left = "".join(f"; {src} left out: {why}" for src, why in left_out)
    if seg.n_segments == 0:
        raise InputError(source, "segments", "no usable segment (constant load, speed and direction) found" + why_left)
    if spec.harmonics[:1] != (6,) or any(h % 6 or h <= 0 for h in spec.harmonics):
        raise InputError(source, "harmonics", f"harmonics must start with 6 and be multiples of 6, got {spec.harmonics}")
    if not (spec.fit_c or spec.fit_k):
        raise InputError(source, "model", "nothing to fit: both c6 and k6 switched off")
    if not 1 <= spec.mech_orders <= 6:
        raise InputError(source, "mech_orders", f"must be 1..6 mechanical orders, got {spec.mech_orders}")
    if spec.fit_k and float(np.abs(seg.i_qo).max()) < 1e-6:
        raise InputError(source, "iq_ref", "k6 needs a load: every segment has i_qo = 0" + why_left)
    if spec.fit_c and spec.fit_k and load_points(seg.i_qo) < 2:
        raise InputError(
            source,
            "iq_ref",
            f"c6 and k6 are not identifiable from a single load point (i_qo = {seg.i_qo[0]:.4g} A in all "
            "segments): capture at two or more load points, or fit one of them only (c6 or k6 switched off)" + why_left,
        )
    if spec.fit_delay:
        w = seg.omega_e
        spread = float(w.max() - w.min())
        if spread < 0.1 * max(float(np.abs(w).max()), 1e-9):
            rpm = sorted({round(float(x) / seg.pole_pairs * 60.0 / (2 * math.pi), 1) for x in w})
            raise InputError(
                source,
                "speed",
                "the transducer delay is not identifiable from a single speed (it shifts the phase in "
                f"proportion to speed; the segments are all at {', '.join(f'{r:g}' for r in rpm)} rpm): capture at two "
                "speeds or in both directions, or give the transducer delay (s)" + why_left,
            )


def load_points(i_qo: Sequence[float] | np.ndarray) -> int:
    """How many distinct load points the segments' i_qo (A) hold: values within 5 % of the largest
    |i_qo| count as one. k6 and c6 are separable only from two or more."""
    i = np.asarray(i_qo, dtype=float)
    scale = max(float(np.abs(i).max()), 1e-9)
    return len(np.unique(np.round(i / (0.05 * scale))))


def legendre_rows(x: np.ndarray, degree: int, out: np.ndarray) -> None:
    """Legendre polynomials P_0..P_degree at x in [-1, 1], written into the rows of ``out``."""
    out[0] = 1.0
    if degree >= 1:
        out[1] = x
    for n in range(1, degree):
        # P_{n+1} = ((2n+1) x P_n - n P_{n-1}) / (n+1), in place (no temporaries of n samples)
        row = out[n + 1]
        np.multiply(x, out[n], out=row)
        row *= (2 * n + 1) / (n + 1)
        row -= (n / (n + 1)) * out[n - 1]


def mech_span(theta: np.ndarray, pole_pairs: int) -> float:
    """A segment's length in mechanical revolutions (``theta`` electrical, rad)."""
    return float(abs(theta[-1] - theta[0])) / (2 * math.pi * pole_pairs)


#: periods of a mechanical order a segment must span to carry its pair (a shorter piece of a sine
#: is all but the drift polynomial)
MECH_MIN_PERIODS = 1.0
#: how far short of :data:`MECH_MIN_PERIODS` a segment's span may fall and still count (periods): a
#: segment cut to whole electrical revolutions spans them less one sample's travel, and its cut
#: follows the edges under speed ripple (-3e-4 of a revolution on the plant). Without it an order
#: whose whole period the segment covers (order 1 in 3 electrical revolutions, order 3 in 1, with 3
#: pole pairs) was left to the drift polynomial on about every other segment, depending on the
#: sample count, and moved that speed band's c6 by up to 9 % and k6 by up to 2 % (issue 34)
MECH_SPAN_TOL = 0.01


def mech_resolved(spec: FitSpec, order: int, span: float) -> bool:
    """Whether a segment of ``span`` mechanical revolutions carries mechanical order ``order``'s pair:
    switched on and :data:`MECH_MIN_PERIODS` periods of it (less :data:`MECH_SPAN_TOL`)."""
    return spec.mech_order1 and order <= spec.mech_orders and order * span >= MECH_MIN_PERIODS - MECH_SPAN_TOL


def design_matrix_t(
    theta: np.ndarray,
    t: np.ndarray,
    pole_pairs: int,
    spec: FitSpec,
    t_span: tuple[float, float] | None = None,
    mech: float | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Columns of one segment, as rows: Legendre(t), cos/sin(m theta_m) for m = 1..spec.n_mech, then
    sin/cos(h theta) per harmonic.

    Parameters
    ----------
    theta : ndarray
        Continuous (unwrapped) electrical angle (rad).
    t : ndarray
        Sample times (s).
    pole_pairs : int
        P/2.
    spec : FitSpec
        Which columns.
    t_span : (float, float), optional
        First and last sample time of the whole segment (s), when ``theta``, ``t`` are a block of
        it (the Legendre time axis spans the segment); default ``(t[0], t[-1])``.
    mech : float, optional
        The segment's length in mechanical revolutions (:func:`mech_span`; default: that of
        ``theta``): order m's pair is a column where ``m`` times it is at least one
        (:func:`mech_resolved`).
    out : ndarray, optional
        Array of at least ``spec.n_cols`` rows and ``len(theta)`` columns to fill (its first
        ``spec.n_cols`` rows are returned); default: a new one.

    Returns
    -------
    ndarray, shape (spec.n_cols, n)
        The transposed design matrix (row-major, so X^T X is one contiguous product). Mechanical
        pairs the segment cannot resolve (less than one mechanical revolution, or switched off) are
        left as zero rows; :func:`compress_segment` pins them.
    """
    n = len(theta)
    XT = np.empty((spec.n_cols, n)) if out is None else out[: spec.n_cols]
    t_first, t_last = (t[0], t[-1]) if t_span is None else t_span
    if mech is None:
        mech = mech_span(theta, pole_pairs)
    design_rows(theta, unit_time(t, t_first, t_last), pole_pairs, spec, XT)
    unresolved_to_zero(XT, spec, mech)
    return XT


def unit_time(t: np.ndarray, t_first: float, t_last: float, out: np.ndarray | None = None) -> np.ndarray:
    """The Legendre columns' time axis: ``t`` (s) mapped to -1 at ``t_first`` and +1 at ``t_last``
    (:func:`design_matrix_t`'s; ``out``: where to write it, default a new array)."""
    tn = np.subtract(t, t_first, out=out)
    tn *= 2.0 / (t_last - t_first)
    tn -= 1.0
    return tn


def design_rows(theta: np.ndarray, tn: np.ndarray, pole_pairs: int, spec: FitSpec, out: np.ndarray,
                work: np.ndarray | None = None) -> None:
    """The columns of :func:`design_matrix_t` from the angle and the normalised time, every mechanical
    pair filled (:func:`unresolved_to_zero` clears those a segment does not carry).

    ``theta`` (rad, electrical, continuous) and ``tn`` (the segment's time mapped onto [-1, 1]) may
    hold the samples of several segments side by side: every column is a function of the sample
    alone, so one call builds them all (the batched compression's few long kernels).
    ``out``: at least ``spec.n_cols`` rows of ``len(theta)`` samples. ``work``: complex, 4 rows of at
    least ``len(theta)``, the powers' scratch (default: allocated; a caller that builds often keeps
    one: a fresh complex array of half a megabyte is mmap'ed and page-faulted anew on each call).
    """
    n = len(theta)
    q = spec.n_nuis
    nm = 2 * spec.n_mech
    w = np.empty((4, n), dtype=complex) if work is None else work[:4, :n]
    e_m, e, sq, spare = w
    legendre_rows(tn, spec.drift_degree, out[: q - nm])
    # one exp(i theta_m) per sample: everything else is a power of it (exact to ~1e-14); the first
    # harmonic's row holds theta_m until the harmonics are written
    np.divide(theta, pole_pairs, out=out[q])
    exp_i(out[q], e_m, e, sq, spare)
    e_j = e_m
    for j in range(spec.n_mech):
        if j:
            np.multiply(e_j, e_m, out=e)
            e_j = e
        out[q - nm + 2 * j] = e_j.real
        out[q - nm + 2 * j + 1] = e_j.imag
    # e: exp(6 i theta), a power of the highest mechanical order's (e_m^18 is e_3^6: 3 products, not 5)
    top = spec.n_mech if (6 * pole_pairs) % spec.n_mech == 0 else 1
    cpow_into(e_j if top > 1 else e_m, 6 * pole_pairs // top, e, sq)
    cur, order = e, 6
    for i, h in enumerate(spec.harmonics):
        if h != order:
            step = e if h - order == 6 else cpow_into(e, (h - order) // 6, spare, e_m)
            np.multiply(cur, step, out=sq)
            cur, order = sq, h
        out[q + 2 * i] = cur.imag
        out[q + 2 * i + 1] = cur.real


def unresolved_to_zero(XT: np.ndarray, spec: FitSpec, mech: float) -> None:
    """Zero the mechanical pairs of :func:`design_rows`' ``XT`` (columns as rows) that a segment of
    ``mech`` mechanical revolutions does not carry (:func:`mech_resolved`)."""
    top = spec.n_nuis - 2 * spec.n_mech
    for j in range(spec.n_mech):
        if not mech_resolved(spec, j + 1, mech):
            XT[top + 2 * j : top + 2 * j + 2] = 0.0


def design_matrix(theta: np.ndarray, t: np.ndarray, pole_pairs: int, spec: FitSpec) -> np.ndarray:
    """:func:`design_matrix_t` transposed: shape (n, spec.n_cols)."""
    return design_matrix_t(np.asarray(theta, dtype=float), np.asarray(t, dtype=float), pole_pairs, spec).T
