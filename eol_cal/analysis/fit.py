"""Per-motor torque-ripple fit: the contract's ripple model solved with optimistix in JAX.

Model (firmware contract section 2, plus the measurement's nuisances), per sample of segment s::

    T = T_avg[s] + drift_s(t) + mech_s(theta_m)
        - sum_h [ c_h sin(h (theta - omega_s tau) + phase_c_h)
                  + k_h i_qo[s] sin(h (theta - omega_s tau) + phase_k_h) ]

``theta`` is the electrical angle (rad) in the frame the firmware uses, ``h`` runs over the
requested harmonics (6, optionally 12 and 18), ``tau`` (s) is the torque transducer's delay: the
measured torque lags, so harmonic h is seen at phase ``h (theta - omega_e tau)``, a shift that
grows with the electrical speed ``omega_e`` (rad/s, signed). ``drift_s`` is a Legendre polynomial
in time per segment (degree ``drift_degree``, its constant term is T_avg), ``mech_s`` a cos/sin pair
at mechanical order 1 (``theta_m = theta / (P/2)``) per segment: its phase is unknown between
segments because halls only give the electrical angle.

A segment holds one load point (constant ``i_qo``), one speed and one direction, so within a
segment the model is linear in a handful of columns (Legendre terms, mechanical cos/sin, sin/cos
of h theta). Each segment is therefore compressed exactly into the Cholesky factor ``R`` of its
normal matrix and ``z = R^-T X^T y``: ``||y - X g||^2 = ||z - R g||^2 + floor``. The nonlinear
least-squares problem over the full parameter vector (tau and every cos/sin coefficient) then has
a residual of ``S * m`` rows instead of one per sample; it is the same objective, so the
Jacobian-based covariance is the same too. The delay enters only through a rotation of each
segment's harmonic coefficients by ``h omega_s tau`` (``omega_s`` is the segment's mean speed;
the dyno holds speed, so the per-sample speed ripple changes the phase by ``h d_omega tau``,
a few mrad at most).

The start is closed-form: for each tau on a grid the model is linear and solved by linear least
squares; the best grid point starts Levenberg-Marquardt on the full vector. Amplitudes are
parameterised as cos/sin pairs (well conditioned also for a small amplitude) and reported as
amplitude + phase with delta-method intervals.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from eol_cal.errors import InputError
from eol_cal.wrap import wrap_pi

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
        Include the mechanical order-1 term per segment.
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
    def n_cols(self) -> int:
        """Columns per segment: Legendre terms, mechanical cos/sin, sin/cos per harmonic."""
        return self.drift_degree + 3 + 2 * len(self.harmonics)

    @property
    def n_nuis(self) -> int:
        """Nuisance parameters per segment (drift polynomial and mechanical pair)."""
        return self.drift_degree + 3

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
    electrical revolutions long (:func:`eol_cal.analysis.fit_capture.capture_segments`); not a
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
        (:func:`eol_cal.mechanics.shaft_response` for a bench). The fitted ripple is the air-gap one;
        ``None`` takes the coupling as rigid (response 1).
    """

    theta: list[np.ndarray]
    t: list[np.ndarray]
    torque: list[np.ndarray]
    i_qo: np.ndarray
    omega_e: np.ndarray
    pole_pairs: int
    labels: list[str] = field(default_factory=list)
    path_response: Callable[[np.ndarray], np.ndarray] | None = None

    @property
    def n_segments(self) -> int:
        return len(self.theta)


def path_gain(seg: SteadySegments, spec: FitSpec) -> np.ndarray:
    """``seg.path_response`` at every segment's harmonics, shape (segments, harmonics), complex."""
    freq = np.outer(seg.omega_e, np.asarray(spec.harmonics, dtype=float))
    if seg.path_response is None:
        return np.ones(freq.shape, dtype=complex)
    return np.asarray(seg.path_response(freq), dtype=complex).reshape(freq.shape)


def check_identifiable(seg: SteadySegments, spec: FitSpec, source: str | None = None) -> None:
    """Refuse a request the data cannot answer (InputError naming what is missing).

    Parameters
    ----------
    seg : SteadySegments
        The motor's segments.
    spec : FitSpec
        The request.
    source : str, optional
        File(s) named in the error.
    """
    if seg.n_segments == 0:
        raise InputError(source, "segments", "no usable segment (constant load, speed and direction) found")
    if spec.harmonics[:1] != (6,) or any(h % 6 or h <= 0 for h in spec.harmonics):
        raise InputError(source, "harmonics", f"harmonics must start with 6 and be multiples of 6, got {spec.harmonics}")
    if not (spec.fit_c or spec.fit_k):
        raise InputError(source, "model", "nothing to fit: both c6 and k6 switched off")
    i_abs = np.abs(seg.i_qo)
    scale = max(float(i_abs.max()), 1e-9)
    loads = np.unique(np.round(seg.i_qo / (0.05 * scale)))
    if spec.fit_k and float(i_abs.max()) < 1e-6:
        raise InputError(source, "iq_ref", "k6 needs a load: every segment has i_qo = 0")
    if spec.fit_c and spec.fit_k and len(loads) < 2:
        raise InputError(
            source,
            "iq_ref",
            f"c6 and k6 are not identifiable from a single load point (i_qo = {seg.i_qo[0]:.4g} A in all "
            "segments): capture at two or more load points, or fit one of them only (c6 or k6 switched off)",
        )
    if spec.fit_delay:
        w = seg.omega_e
        spread = float(w.max() - w.min())
        if spread < 0.1 * max(float(np.abs(w).max()), 1e-9):
            raise InputError(
                source,
                "speed",
                "the transducer delay is not identifiable from a single speed (it shifts the phase in "
                "proportion to speed): capture at two speeds or in both directions, or give the transducer delay (s)",
            )


def _legendre_rows(x: np.ndarray, degree: int, out: np.ndarray) -> None:
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


def _cpow(e: np.ndarray, n: int) -> np.ndarray:
    """e**n for a complex array and a positive integer n, by repeated squaring."""
    out = None
    while n:
        if n & 1:
            out = e if out is None else out * e
        n >>= 1
        if n:
            e = e * e
    return out


def design_matrix_t(
    theta: np.ndarray,
    t: np.ndarray,
    pole_pairs: int,
    spec: FitSpec,
    t_span: tuple[float, float] | None = None,
    mech: bool | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Columns of one segment, as rows: Legendre(t), cos/sin(theta_m), then sin/cos(h theta) per harmonic.

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
    mech : bool, optional
        Whether the segment resolves the mechanical pair; default: ``spec.mech_order1`` and at
        least one mechanical revolution in ``theta``.
    out : ndarray, optional
        Array of at least ``spec.n_cols`` rows and ``len(theta)`` columns to fill (its first
        ``spec.n_cols`` rows are returned); default: a new one.

    Returns
    -------
    ndarray, shape (spec.n_cols, n)
        The transposed design matrix (row-major, so X^T X is one contiguous product). A mechanical
        pair the segment cannot resolve (less than one mechanical revolution, or switched off) is
        left as zero rows; :func:`compress_segment` pins it.
    """
    n = len(theta)
    q = spec.n_nuis
    XT = np.empty((spec.n_cols, n)) if out is None else out[: spec.n_cols]
    t_first, t_last = (t[0], t[-1]) if t_span is None else t_span
    if mech is None:
        mech = spec.mech_order1 and abs(theta[-1] - theta[0]) >= 2 * math.pi * pole_pairs
    tn = t - t_first
    tn *= 2.0 / (t_last - t_first)
    tn -= 1.0
    _legendre_rows(tn, spec.drift_degree, XT[: q - 2])
    # one exp(i theta_m) per sample: everything else is a power of it (exact to ~1e-14)
    e_m = np.exp(1j * (theta / pole_pairs))
    if mech:
        XT[q - 2] = e_m.real
        XT[q - 1] = e_m.imag
    else:
        XT[q - 2 : q] = 0.0
    e6 = _cpow(e_m, 6 * pole_pairs)
    e, order = e6, 6
    for i, h in enumerate(spec.harmonics):
        if h != order:
            e = e * _cpow(e6, (h - order) // 6)
            order = h
        XT[q + 2 * i] = e.imag
        XT[q + 2 * i + 1] = e.real
    return XT


def design_matrix(theta: np.ndarray, t: np.ndarray, pole_pairs: int, spec: FitSpec) -> np.ndarray:
    """:func:`design_matrix_t` transposed: shape (n, spec.n_cols)."""
    return design_matrix_t(np.asarray(theta, dtype=float), np.asarray(t, dtype=float), pole_pairs, spec).T


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
    from scipy.linalg.blas import dgemm

    theta = np.asarray(theta, dtype=float)
    t = np.asarray(t, dtype=float)
    y = np.asarray(torque, dtype=float)
    n = len(y)
    m = spec.n_cols
    ymean = float(y.mean())
    mech = spec.mech_order1 and abs(theta[-1] - theta[0]) >= 2 * math.pi * pole_pairs
    buf = _block_buffer(m + 1)
    # [X y]^T [X y] accumulated block by block: X^T X, X^T y and y^T y in one GEMM per block, on
    # the (n, m+1) Fortran view (numpy's ``A @ A.T`` dispatches to SYRK, which OpenBLAS runs 2x
    # slower for these narrow products)
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


def _build(spec: FitSpec, S: int):
    """The jitted one-motor solver on compressed data, for a given spec and segment count.

    The per-segment nuisance (drift polynomial, mechanical pair) enters linearly and unconstrained
    through the leading block of the upper-triangular R, so it is projected out exactly: the top
    rows of each segment's residual can always be zeroed, the bottom ``2*len(harmonics)`` rows
    depend on the ripple parameters only. Levenberg-Marquardt / Gauss-Newton then runs on
    (delay, every cos/sin ripple coefficient), and its Jacobian gives the same covariance for them
    as the full problem would (Schur complement).
    """
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    H = jnp.asarray(spec.harmonics, dtype=float)
    nh = len(spec.harmonics)
    q = spec.n_nuis
    G = spec.n_glob
    n_tau = int(spec.fit_delay)

    def harm_coef(p, i_qo, omega, gre, gim):
        """Coefficients of the sin/cos(h theta) columns per segment, shape (S, 2 nh)."""
        tau = p[0] * TAU_SCALE if n_tau else spec.delay_s
        glob = p[n_tau : n_tau + G].reshape(-1, nh, 2)  # (part, harmonic, cos/sin)
        Zre = jnp.zeros((S, nh))
        Zim = jnp.zeros((S, nh))
        part = 0
        if spec.fit_c:
            Zre = Zre + glob[part, :, 0][None]
            Zim = Zim + glob[part, :, 1][None]
            part += 1
        if spec.fit_k:
            Zre = Zre + i_qo[:, None] * glob[part, :, 0][None]
            Zim = Zim + i_qo[:, None] * glob[part, :, 1][None]
        # air gap -> shaft (bench mechanics), then the transducer
        Zre, Zim = Zre * gre - Zim * gim, Zre * gim + Zim * gre
        a = H[None, :] * omega[:, None] * tau
        if spec.transducer == "lowpass":
            # first-order transducer: each segment's phasor times 1 / (1 + i h omega tau)
            den = 1.0 + a * a
            cr, sr = 1.0 / den, -a / den
        else:
            # pure delay: harmonic h is seen at h*(theta - omega*tau), a rotation by -h omega tau
            cr, sr = jnp.cos(a), -jnp.sin(a)
        Rre = Zre * cr - Zim * sr
        Rim = Zre * sr + Zim * cr
        # T = ... - Re(Z') sin(h theta) - Im(Z') cos(h theta)
        return jnp.stack([-Rre, -Rim], axis=-1).reshape(S, 2 * nh)

    def residual(p, args):
        Rhh, zh, i_qo, omega, gre, gim, valid = args
        g = harm_coef(p, i_qo, omega, gre, gim)
        r = zh - jnp.einsum("sij,sj->si", Rhh, g)
        return (r * valid[:, None]).reshape(-1)

    def linear_start(args, tau):
        p_tau = jnp.atleast_1d(tau / TAU_SCALE)[:n_tau]

        def res_lin(lin):
            return residual(jnp.concatenate([p_tau, lin]), args)

        zero = jnp.zeros(G)
        r0 = res_lin(zero)
        A = jax.jacfwd(res_lin)(zero)
        lin = jnp.linalg.solve(A.T @ A, -A.T @ r0)
        return jnp.concatenate([p_tau, lin]), jnp.sum((A @ lin + r0) ** 2)

    def solve(comp, tau_grid, max_steps):
        Rhh = comp["R"][:, q:, q:]
        zh = comp["z"][:, q:]
        valid = (comp["n"] > 0).astype(zh.dtype)
        args = (Rhh, zh, comp["i_qo"], comp["omega"], comp["gain_re"], comp["gain_im"], valid)
        if n_tau:
            starts, ssrs = jax.vmap(lambda tau: linear_start(args, tau))(tau_grid)
            p0 = starts[jnp.argmin(ssrs)]
        else:
            p0, _ = linear_start(args, 0.0)
        # Jacobi scaling: in u = (p - p0) / D every Jacobian column has unit norm, so the delay
        # (a tiny column) and the ripple coefficients start on the same footing.
        J0 = jax.jacfwd(residual)(p0, args)
        D = 1.0 / jnp.sqrt(jnp.maximum(jnp.sum(J0 * J0, axis=0), 1e-300))

        def residual_u(u, a):
            return residual(p0 + D * u, a)

        sol = optx.least_squares(
            residual_u, _make_solver(spec), jnp.zeros_like(p0), args=args, max_steps=max_steps, throw=False
        )
        p = p0 + D * sol.value
        r = residual(p, args)
        J = jax.jacfwd(residual)(p, args)
        return {
            "p": p,
            "cov_unscaled": jnp.linalg.inv(J.T @ J),
            "ssr_red": jnp.sum(r * r),
            "g": harm_coef(p, comp["i_qo"], comp["omega"], comp["gain_re"], comp["gain_im"]),
            "steps": sol.stats["num_steps"],
            "converged": sol.result == optx.RESULTS.successful,
        }

    return solve


def _make_solver(spec: FitSpec):
    """Gauss-Newton (default) or Levenberg-Marquardt with a small initial damping.

    Measured on synthetic motors: optimistix's LM tests for termination only after an accepted
    step, so when the closed-form start is already optimal to rounding every trial step is
    rejected and it runs to ``max_steps`` (2 of 256 motors); from the closed-form start
    Gauss-Newton needs 3-6 steps. LM stays available (``solver="lm"``) for poor starts; it starts
    at damping ``1 / lm_init_step`` instead of 1 (which costs ~20 creeping steps here).
    """
    import equinox as eqx
    import jax.numpy as jnp
    import optimistix as optx

    if spec.solver == "gn":
        return optx.GaussNewton(rtol=spec.rtol, atol=spec.atol)
    solver = optx.LevenbergMarquardt(rtol=spec.rtol, atol=spec.atol)
    try:  # private in optimistix 0.1: without it, the stock (slower-starting) LM still works
        from optimistix._solver.trust_region import _TrustRegionState
    except ImportError:  # pragma: no cover
        return solver

    class _Region(optx.ClassicalTrustRegion):
        init_step: float = eqx.field(static=True, default=1e3)

        def init(self, y, f_info_struct):
            return _TrustRegionState(step_size=jnp.array(self.init_step))

    return eqx.tree_at(lambda s: s.search, solver, _Region(init_step=spec.lm_init_step))


_SOLVERS: dict = {}

#: Where :func:`fit_many` keeps serialized (``jax.export``) one-motor solvers; ``None`` = off.
#: The CLI sets it next to JAX's persistent compilation cache: the compilation cache skips XLA
#: compiling, this skips tracing the solver (and importing optimistix), about 2 s of a short run.
EXPORT_DIR: str | None = None
_EXPORT_TAG = "eol-cal-fit-solve-2"


def _export_file(spec: FitSpec, S: int, n_grid: int) -> str | None:
    import hashlib
    import os

    import jax

    if not EXPORT_DIR:
        return None
    key = repr((_EXPORT_TAG, jax.__version__, spec, S, n_grid))
    return os.path.join(EXPORT_DIR, f"fit-{hashlib.sha256(key.encode()).hexdigest()[:20]}.jaxexport")


def _exported_solver(spec: FitSpec, S: int, n_grid: int):
    """A deserialized one-motor solver from EXPORT_DIR, or None (none yet, or unreadable)."""
    path = _export_file(spec, S, n_grid)
    if path is None:
        return None
    try:
        with open(path, "rb") as fh:
            blob = fh.read()
        from jax import export

        return export.deserialize(bytearray(blob)).call
    except Exception:  # noqa: BLE001 - a missing or stale cache entry only costs the tracing
        return None


def _save_exported(fn, spec: FitSpec, S: int, n_grid: int, args: tuple) -> None:
    """Serialize the jitted one-motor solver for the next process (best effort, atomic)."""
    import re

    path = _export_file(spec, S, n_grid)
    if path is None:
        return
    try:
        from jax import export

        # The LAPACK custom calls carry no cross-version guarantee; the file name holds the jax
        # version and the entry is only read back on this installation.
        names: set[str] = set()
        for _ in range(20):
            try:
                checks = [export.DisabledSafetyCheck.custom_call(n) for n in sorted(names)]
                exp = export.export(fn, disabled_checks=checks)(*args)
                break
            except ValueError as exc:
                new = set(re.findall(r"custom_call @(\w+)", str(exc))) - names
                if not new:
                    return
                names |= new
        else:
            return
        blob = exp.serialize()
        from eol_cal.atomic import atomic_write

        atomic_write(path, bytes(blob))
    except Exception:  # noqa: BLE001 - the cache is an optimisation, never a failure
        return


def _solver(spec: FitSpec, S: int, mode: str):
    """Jitted solver, cached per (spec, S, mode)."""
    import jax

    key = (spec, S, mode)
    if key not in _SOLVERS:
        solve = _build(spec, S)
        if mode == "one":
            fn = jax.jit(solve, static_argnums=(2,))
        elif mode == "vmap":
            fn = jax.jit(jax.vmap(solve, in_axes=(0, None, None)), static_argnums=(2,))
        elif mode == "map":
            fn = jax.jit(lambda comp, grid, steps: jax.lax.map(lambda c: solve(c, grid, steps), comp), static_argnums=(2,))
        else:
            raise ValueError(f"unknown batch mode {mode!r}")
        _SOLVERS[key] = fn
    return _SOLVERS[key]


def tau_grid(spec: FitSpec, omega_max: float) -> np.ndarray:
    """Start grid for the delay (s) over [0, delay_max_s].

    Spacing: the 6th harmonic at the highest speed moves at most 0.5 rad between grid points
    (8 to 64 points). With the low-pass model the phase ``atan(h omega tau)`` is monotone and
    bounded, so the best point is in the basin of the optimum; with the pure delay a shift of
    ``2 pi / (6 d_omega)`` would alias, which this spacing resolves for delays up to
    ``spec.delay_max``. Solver steps then refine every harmonic.
    """
    if not spec.fit_delay:
        return np.zeros(1)
    span = 6 * max(omega_max, 1.0) * spec.delay_max
    n = int(min(max(math.ceil(span / 0.5) + 1, 8), 64))
    # a power of two, so that nearby speeds share one compiled solver
    n = 1 << (n - 1).bit_length()
    return np.linspace(0.0, spec.delay_max, n)


@dataclass
class Estimate:
    """One amplitude/phase pair with 95 % half-widths."""

    value: float
    ci95: float
    phase: float
    phase_ci95: float


@dataclass
class MotorFit:
    """The fit of one motor (array-level result).

    Attributes
    ----------
    harmonics : dict[int, dict[str, Estimate]]
        Per order h: ``"c"`` (N*m, phase rad) and/or ``"k"`` (N*m/A, phase rad).
    delay_s, delay_ci95 : float
        Transducer delay and its 95 % half-width (s); the given value and 0 when fixed.
    t_avg : ndarray
        Mean torque per segment (N*m).
    rms : float
        Residual RMS (N*m).
    r2 : float
        1 - SSR / sum of squares about each segment's mean: the share of the ripple explained.
    converged : bool
    steps : int
    n_samples : int
    coef : ndarray, (segments, spec.n_cols)
        Every segment's column coefficients (nuisance then harmonics) for
        :func:`design_matrix`; the model of segment s is ``mean(y_s) + design_matrix(...) @ coef[s]``.
    """

    harmonics: dict
    delay_s: float
    delay_ci95: float
    t_avg: np.ndarray
    rms: float
    r2: float
    converged: bool
    steps: int
    n_samples: int
    coef: np.ndarray | None = None
    birge: float = 1.0


def shift_frame(fit: MotorFit, offset_rad: float) -> MotorFit:
    """The same fit with its phases in a frame ``theta' = theta + offset_rad`` (rad, electrical).

    ``sin(h theta + phi) = sin(h theta' - h offset + phi)``: harmonic h's phases move by
    ``-h * offset_rad``; amplitudes and intervals are unchanged.
    """
    import dataclasses

    harmonics = {
        h: {part: dataclasses.replace(e, phase=float(wrap_pi(e.phase - h * offset_rad))) for part, e in parts.items()}
        for h, parts in fit.harmonics.items()
    }
    return dataclasses.replace(fit, harmonics=harmonics)


def _amp_phase(a: float, b: float, cov2: np.ndarray) -> Estimate:
    """Amplitude/phase of a cos/sin pair (value*cos(phase), value*sin(phase)), delta method."""
    amp = math.hypot(a, b)
    if amp == 0.0:
        return Estimate(0.0, float("inf"), 0.0, float("inf"))
    g_amp = np.array([a, b]) / amp
    g_ph = np.array([-b, a]) / amp**2
    var_amp = float(g_amp @ cov2 @ g_amp)
    var_ph = float(g_ph @ cov2 @ g_ph)
    return Estimate(amp, Z95 * math.sqrt(max(var_amp, 0.0)), float(wrap_pi(math.atan2(b, a))), Z95 * math.sqrt(max(var_ph, 0.0)))


def unpack(out: dict, comp: Compressed, spec: FitSpec, S_valid: int) -> MotorFit:
    """Turn the solver's arrays for one motor into a :class:`MotorFit`.

    The covariance is ``s^2 (J^T J)^-1`` with ``s^2 = SSR / (n - n_parameters)``, counting the
    projected nuisance parameters; amplitude/phase intervals follow by the delta method.
    """
    p = np.asarray(out["p"], dtype=float)
    n_tau = int(spec.fit_delay)
    nh = len(spec.harmonics)
    q = spec.n_nuis
    valid = comp.n > 0
    n = float(comp.n.sum())
    ssr = float(out["ssr_red"]) + float(comp.floor[valid].sum())
    n_par = n_tau + spec.n_glob + float(comp.n_nuis[valid].sum())
    s2 = ssr / max(n - n_par, 1.0)
    # Lack of fit between segments (Birge ratio): the projected rows hold only what the ripple
    # model leaves unexplained from one segment to the next; with an exact model their mean
    # square is s2. More than that widens the intervals by the ratio.
    dof_red = float(valid.sum()) * 2 * nh - (n_tau + spec.n_glob)
    birge = float(out["ssr_red"]) / dof_red / s2 if dof_red >= 1 and s2 > 0 else 1.0
    inflate = max(1.0, birge) if spec.lack_of_fit else 1.0
    cov = inflate * s2 * np.asarray(out["cov_unscaled"], dtype=float)
    harmonics: dict = {h: {} for h in spec.harmonics}
    parts = [name for name, on in (("c", spec.fit_c), ("k", spec.fit_k)) if on]
    for ip, name in enumerate(parts):
        for ih, h in enumerate(spec.harmonics):
            i = n_tau + (ip * nh + ih) * 2
            harmonics[h][name] = _amp_phase(p[i], p[i + 1], cov[i : i + 2, i : i + 2])
    if n_tau:
        delay, delay_ci = p[0] * TAU_SCALE, Z95 * math.sqrt(max(cov[0, 0], 0.0)) * TAU_SCALE
    else:
        delay, delay_ci = float(spec.delay_s), 0.0
    # T_avg: back-substitute the projected nuisance (its first Legendre term is the mean offset)
    g = np.asarray(out["g"], dtype=float)[:S_valid]
    R = comp.R[:S_valid]
    rhs = comp.z[:S_valid, :q] - np.einsum("sij,sj->si", R[:, :q, q:], g)
    nuis = np.linalg.solve(R[:, :q, :q], rhs[..., None])[..., 0]
    t_avg = comp.ymean[:S_valid] + nuis[:, 0]
    coef = np.concatenate([nuis, g], axis=1)
    sst = float(comp.sst[valid].sum())
    finite = bool(np.all(np.isfinite(p)) and np.all(np.isfinite(np.diag(cov))))
    return MotorFit(
        harmonics=harmonics,
        delay_s=float(delay),
        delay_ci95=float(delay_ci),
        t_avg=t_avg,
        rms=math.sqrt(max(ssr, 0.0) / n),
        r2=1.0 - ssr / sst if sst > 0 else float("nan"),
        converged=bool(out["converged"]) and finite,
        steps=int(out["steps"]),
        n_samples=int(n),
        coef=coef,
        birge=birge,
    )


def fit_segments(seg: SteadySegments, spec: FitSpec = FitSpec(), source: str | None = None) -> MotorFit:
    """Fit one motor from its segments (all captures jointly).

    Parameters
    ----------
    seg : SteadySegments
        Electrical angle (rad), time (s), torque (N*m) per segment, with i_qo (A) and omega_e (rad/s).
    spec : FitSpec
        Model and solver settings.
    source : str, optional
        Named in errors.

    Returns
    -------
    MotorFit
    """
    return fit_many([seg], spec, mode="loop", sources=[source])[0]


#: ``fit_many(mode="auto")`` batches the solve from this many motors on (below, the compile of a
#: batched program costs more than the per-call dispatch it saves)
AUTO_BATCH_MIN = 16


def pick_mode(n_motors: int) -> str:
    """The batch mode ``fit_many(mode="auto")`` uses for ``n_motors``: ``loop`` or ``map``.

    ``map`` and ``vmap`` measure within a few per cent of each other (docs/benchmarks.md); ``map``
    is kept because it does not run every member to the slowest one's step count.
    """
    return "map" if n_motors >= AUTO_BATCH_MIN else "loop"


def fit_many(
    motors: list[SteadySegments],
    spec: FitSpec = FitSpec(),
    mode: str = "auto",
    chunk: int = 64,
    sources: list[str | None] | None = None,
    progress: Callable[[int], None] | None = None,
    threads: int = 0,
) -> list[MotorFit]:
    """Fit many motors: compression in numpy, the nonlinear solve batched in JAX.

    With ``threads`` > 0 the compression of every motor is queued on a thread pool at once, so
    the pool compresses the next chunks while this thread runs the JAX solve of the current one
    (XLA and the numpy kernels release the GIL) and unpacks its results.

    Parameters
    ----------
    motors : list of SteadySegments
        One entry per motor.
    spec : FitSpec
        Shared model and solver settings.
    mode : {"loop", "vmap", "map", "auto"}
        ``loop``: one jitted solve per motor; ``vmap``: one vectorised solve per chunk (every member
        iterates until the slowest has converged); ``map``: ``jax.lax.map`` inside one jitted call;
        ``auto``: :func:`pick_mode`.
    chunk : int
        Motors per batched call (vmap/map); also the progress granularity.
    sources : list, optional
        Per motor, named in errors.
    progress : callable, optional
        Called with the number of motors finished after each chunk.
    threads : int
        Worker threads that compress ahead of the solve (numpy releases the GIL in its kernels);
        0 (default) compresses in this thread, chunk by chunk. On the 2-core machine of
        docs/benchmarks.md 1 or 2 workers measured no faster than none: the kernels of an
        8000-sample block are short and the threads mostly wait for the GIL between them.

    Returns
    -------
    list of MotorFit
    """
    from concurrent.futures import ThreadPoolExecutor

    import jax

    if mode == "auto":
        mode = pick_mode(len(motors))
    sources = sources or [None] * len(motors)
    for seg, src in zip(motors, sources):
        check_identifiable(seg, spec, src)
    S = max(m.n_segments for m in motors)
    omega_max = max(float(np.abs(m.omega_e).max()) for m in motors)
    grid = tau_grid(spec, omega_max)
    results: list[MotorFit] = []
    pool = ThreadPoolExecutor(max_workers=threads) if threads > 0 and len(motors) > 1 else None
    try:
        # every compression queued up front (a few kB of result per motor): the workers run ahead
        futures = [pool.submit(compress, m, spec, S) for m in motors] if pool else None
        with jax.enable_x64(True):
            grid_j = jax.numpy.asarray(grid)
            exported = _exported_solver(spec, S, len(grid)) if mode == "loop" else None
            solve = (lambda c, g, _steps: exported(c, g)) if exported else _solver(spec, S, "one" if mode == "loop" else mode)
            save_export = mode == "loop" and exported is None and EXPORT_DIR is not None
            step = 1 if mode == "loop" else chunk
            for start in range(0, len(motors), step):
                block = motors[start : start + step]
                if futures:
                    comps = [f.result() for f in futures[start : start + step]]
                else:
                    comps = [compress(m, spec, S) for m in block]
                if mode == "loop":
                    args = (_as_dict(comps[0]), grid_j)
                    out = jax.device_get(solve(*args, spec.max_steps))
                    outs = [out]
                    if save_export:
                        save_export = False
                        _save_exported(jax.jit(lambda c, g: _build(spec, S)(c, g, spec.max_steps)), spec, S, len(grid), args)
                else:
                    # pad the last chunk to the chunk size: one compiled shape
                    padded = comps + [comps[-1]] * (chunk - len(comps)) if len(motors) > chunk else comps
                    batch = {k: np.stack([getattr(c, k) for c in padded]) for k in _DICT_KEYS}
                    out = jax.device_get(solve(batch, grid_j, spec.max_steps))
                    outs = [{k: v[j] for k, v in out.items()} for j in range(len(block))]
                for m, c, o in zip(block, comps, outs):
                    results.append(unpack(o, c, spec, m.n_segments))
                if progress:
                    progress(len(results))
    finally:
        if pool:
            pool.shutdown(cancel_futures=True)
    return results


_DICT_KEYS = ("R", "z", "n", "i_qo", "omega", "gain_re", "gain_im")


def _as_dict(c: Compressed) -> dict[str, np.ndarray]:
    return {k: getattr(c, k) for k in _DICT_KEYS}
