"""The fit of one motor as numbers: amplitude/phase estimates with 95 % intervals (:class:`MotorFit`),
unpacked from the solver's arrays with delta-method intervals."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.fit.compression import Compressed
from eol_cal.analysis.fit.model import TAU_SCALE, Z95, FitSpec
from eol_cal.analysis.fit.solver import solver_result
from eol_cal.numerics.wrap import wrap_pi


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
    solver_result : str
        How the solver ended: the name of optimistix's ``RESULTS``
        (:data:`~eol_cal.analysis.fit.solver.SOLVER_RESULTS`: ``successful``, ``max_steps_reached``, ...).
    steps : int
    n_samples : int
    coef : ndarray, (segments, spec.n_cols)
        Every segment's column coefficients (nuisance then harmonics) for
        :func:`design_matrix`; the model of segment s is ``mean(y_s) + design_matrix(...) @ coef[s]``.
    current : ndarray, (segments, harmonics), complex, optional
        The ripple of ``kt * i_q`` per segment as an air-gap phasor (N*m,
        :func:`eol_cal.analysis.fit.compression.current_phasor`), known torque added to the fitted
        ripple's; None when the segments carried no current.
    finite : bool
        The parameters and their variances are finite numbers.
    cov6 : ndarray, (4, 4), optional
        Covariance of the 6th harmonic's cos/sin pairs ``(c, k)`` in the order the solver holds
        them (c's pair then k's, each ``(value cos(phase), value sin(phase))``; N*m and N*m/A),
        with the intervals' widening; the pairs of a part not fitted are absent (2 x 2). The
        amplitude/phase intervals of :attr:`harmonics` are its diagonal blocks; c6 and k6 of one
        fit are correlated through the load points (a slope and an intercept), which the model
        check needs (:mod:`eol_cal.analysis.fit.model_check`).
    parts : CovarianceParts, optional
        What the intervals are made of (:func:`at_line_noise` makes them again).
    """

    harmonics: dict
    delay_s: float
    delay_ci95: float
    t_avg: np.ndarray
    rms: float
    r2: float
    solver_result: str
    steps: int
    n_samples: int
    coef: np.ndarray | None = None
    birge: float = 1.0
    current: np.ndarray | None = None
    finite: bool = True
    cov6: np.ndarray | None = None
    parts: CovarianceParts | None = None

    @property
    def converged(self) -> bool:
        """The solver ended successfully with finite values: a fit that may be judged."""
        return self.solver_result == "successful" and self.finite


#: the least segments whose scatter (:func:`segment_scatter`) gives the intervals: fewer leave the
#: scatter's variance under 6 degrees of freedom (Student's t over 2.45) and the cluster estimate's
#: own small-sample bias large; there the lack of fit pooled over every harmonic's rows widens
#: every parameter alike
MIN_SEGMENTS_SCATTER = 7

def shift_frame(fit: MotorFit, offset_rad: float, offset_sd_rad: float = 0.0) -> MotorFit:
    """The same fit with its phases in a frame ``theta' = theta + offset_rad`` (rad, electrical).

    ``sin(h theta + phi) = sin(h theta' - h offset + phi)``: harmonic h's phases move by
    ``-h * offset_rad``; amplitudes are unchanged. ``offset_sd_rad``: the standard error of the
    offset, added to each phase's interval (``h`` times it, in quadrature).
    """
    def moved(h: int, e: Estimate) -> Estimate:
        ci = math.hypot(e.phase_ci95, Z95 * h * offset_sd_rad) if offset_sd_rad else e.phase_ci95
        return dataclasses.replace(e, phase=float(wrap_pi(e.phase - h * offset_rad)), phase_ci95=float(ci))

    harmonics = {h: {part: moved(h, e) for part, e in parts.items()} for h, parts in fit.harmonics.items()}
    cov6 = None
    if fit.cov6 is not None:
        # each cos/sin pair turns by -6 offset; the offset's own error turns them together
        a = -6.0 * offset_rad
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        n_pairs = fit.cov6.shape[0] // 2
        R = np.kron(np.eye(n_pairs), rot)
        # cov6 holds the fitted parts' pairs, as harmonics[6] holds their estimates (c's, then k's)
        z = np.concatenate([[e.value * math.cos(e.phase), e.value * math.sin(e.phase)]
                            for e in harmonics[6].values()])
        turn = np.kron(np.eye(n_pairs), np.array([[0.0, -1.0], [1.0, 0.0]])) @ z * 6.0 * offset_sd_rad
        cov6 = R @ fit.cov6 @ R.T + np.outer(turn, turn)
    return dataclasses.replace(fit, harmonics=harmonics, cov6=cov6)


def amp_phase(a: float, b: float, cov2: np.ndarray) -> Estimate:
    """Amplitude/phase of a cos/sin pair (value*cos(phase), value*sin(phase)) with 95 % half-widths from
    its covariance ``cov2`` (2 x 2), by the delta method: the amplitude's along the phasor, the phase's
    across it (rad; not capped: a caller that reports it caps it at pi)."""
    return amp_phase_pairs(np.array([[a, b]], dtype=float), np.asarray(cov2, dtype=float)[None])[0]


def amp_phase_pairs(ab: np.ndarray, cov2: np.ndarray) -> list[Estimate]:
    """:func:`amp_phase` of ``k`` pairs at once: ``ab`` (k, 2), their covariances ``cov2`` (k, 2, 2).

    One stacked product for every pair of a fit, not two small products a pair: the per-pair numpy
    calls were most of :func:`unpack`'s time (issue 37). The stacked matmul runs the same BLAS kernels
    per pair as the single products did, so the results are the same bit for bit
    (tests/test_fit_unpack.py); the amplitude is ``math.hypot``'s (``np.hypot`` rounds differently).
    """
    amp = np.array([math.hypot(a, b) for a, b in ab.tolist()])
    some = np.where(amp == 0.0, 1.0, amp)  # a zero pair is answered below without its gradient
    g_amp = ab / some[:, None]
    g_ph = g_amp[:, ::-1] * np.array([-1.0, 1.0]) / some[:, None]  # (-b, a) / amp^2 without overflowing amp^2
    var_amp = (g_amp[:, None, :] @ cov2 @ g_amp[:, :, None])[:, 0, 0]
    var_ph = (g_ph[:, None, :] @ cov2 @ g_ph[:, :, None])[:, 0, 0]
    ci_amp = Z95 * np.sqrt(np.maximum(var_amp, 0.0))
    ci_ph = Z95 * np.sqrt(np.maximum(var_ph, 0.0))
    phase = np.asarray(wrap_pi(np.array([math.atan2(b, a) for a, b in ab.tolist()])))  # math's atan2, as before
    return [Estimate(0.0, math.inf, 0.0, math.inf) if m == 0.0 else Estimate(m, ca, ph, cp)
            for m, ca, ph, cp in zip(amp.tolist(), ci_amp.tolist(), phase.tolist(), ci_ph.tolist(), strict=True)]


def segment_scatter(jac: np.ndarray, res: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The parameters' covariance from the segments' scatter (cluster-robust, each segment a cluster).

    ``C (sum_s u_s u_s^T) C S / (S - 1)``, ``C = (J^T J)^-1`` and ``u_s = J_s^T r_s`` segment s's
    share of the gradient (``jac``, ``res``: each segment's reduced rows' Jacobian and residuals,
    segments first): what differs from segment to segment, in the
    direction each parameter sees it. The noise at the harmonics is neither white (4-11x white
    beside the 6th) nor alike in every segment (its load and speed), and the model errs between
    segments (the path's and the transducer's gain against speed): a ratio of the residual rows to
    the white noise, spread over every direction and segment alike, widened the phases and the
    delay 1.2-1.8x beyond their errors (bench/bench_coverage.py).
    """
    u = np.einsum("sk,skp->sp", res, jac)
    S = u.shape[0]
    return C @ (u.T @ u) @ C * (S / max(S - 1, 1))


def _quantity_blocks(spec: FitSpec) -> list[slice]:
    """The parameter blocks of the reported quantities: the delay, then each part's cos/sin pair per harmonic."""
    n_tau = int(spec.fit_delay)
    return ([slice(0, 1)] if n_tau else []) + [slice(i, i + 2) for i in range(n_tau, n_tau + spec.n_glob, 2)]


def wider_per_quantity(noise: np.ndarray, scatter: np.ndarray, blocks: list[slice], S: int) -> np.ndarray:
    """Each reported quantity's block (its rows and columns) from the wider of ``noise`` and ``scatter``,
    scaled to Student's t of its Welch-Satterthwaite degrees of freedom over the normal's 1.96.

    The variance is the noise's ``V_n`` plus what the segments' scatter ``V_s`` (trace of the block)
    shows beyond it, ``B = max(0, V_s - V_n)``: the noise's from thousands of samples counted as
    known, the excess from the ``S - 1`` of the segments, so ``nu = (V_n + B)^2 (S - 1) / B^2``:
    ``S - 1`` when the scatter is all excess, the normal's when there is none. ``t(S - 1)`` on the
    whole scatter wherever it was the wider (before) counted the noise's share as estimated from 8
    segments: over 400 plant motors k6, c6 and the delay covered 98.25-98.75 %, the scatter's errors
    where it was the wider beyond t(7) in 1.1-1.9 %, not 5 % (docs/fit.md).
    """
    cov = scatter.copy()
    scale = np.ones(cov.shape[0])
    for b in blocks:
        v_n, v_s = float(np.trace(noise[b, b])), float(np.trace(scatter[b, b]))
        if v_n >= v_s:
            cov[b, :], cov[:, b] = noise[b, :], noise[:, b]
        else:
            scale[b] = excess_t(v_n, v_s - v_n, S)[0]
    return cov * np.outer(scale, scale)


def excess_t(v_known: float, v_excess: float, S: int) -> tuple[float, float]:
    """Student's t over the normal's 1.96 for a variance ``v_known`` (the noise's, from thousands of
    samples: counted as known) plus ``v_excess`` (what the segments' scatter shows beyond it, from
    its ``S - 1`` degrees of freedom), and their Welch-Satterthwaite degrees of freedom
    ``nu = (S - 1) ((v_known + v_excess) / v_excess)^2``: ``(1, inf)`` without excess. The one rule
    of the electrical quantities (:func:`wider_per_quantity`) and the mechanical orders
    (:func:`eol_cal.analysis.fit.mech_orders.pair_covariance`)."""
    if v_excess <= 0.0:
        return 1.0, math.inf
    from scipy.special import stdtrit  # heavy: not at `eol-cal run`'s start (tests/test_imports.py)

    nu = (S - 1) * ((v_known + v_excess) / v_excess) ** 2
    return float(stdtrit(nu, 0.975)) / Z95, nu


@dataclass(frozen=True)
class CovarianceParts:
    """What a fit's intervals are made of, kept so that :func:`at_line_noise` can make them again at
    the noise each harmonic has at its own frequency.

    p : the solver's parameters (delay, then each part's cos/sin pair per harmonic); cov_unscaled :
    ``(J^T J)^-1``; jac, res : each valid segment's reduced rows (one cos/sin pair a harmonic) and
    their Jacobian (segments, rows, parameters); s2 : the residual's variance (N*m^2); scatter : the
    segments' scatter (:func:`segment_scatter`; None below :data:`MIN_SEGMENTS_SCATTER` segments);
    dof_red : degrees of freedom of the reduced rows.
    """

    p: np.ndarray
    cov_unscaled: np.ndarray
    jac: np.ndarray
    res: np.ndarray
    s2: float
    scatter: np.ndarray | None
    dof_red: float


@functools.cache
def _pair_blocks(n_tau: int, n_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """The fancy index of the 2 x 2 diagonal blocks of ``n_pairs`` cos/sin pairs that lie one after
    another from ``n_tau`` on (each part's harmonics in turn): ``cov[rows, cols]`` is (n_pairs, 2, 2).
    The same few specs every call: built once (issue 37: the unpacking's per-motor numpy calls)."""
    first = n_tau + 2 * np.arange(n_pairs)
    pair = np.arange(2)
    rows, cols = first[:, None, None] + pair[None, :, None], first[:, None, None] + pair[None, None, :]
    rows.flags.writeable = cols.flags.writeable = False
    return rows, cols


def _intervals(parts: CovarianceParts, spec: FitSpec,
               row_var: np.ndarray | None) -> tuple[dict, np.ndarray, float, float, np.ndarray]:
    """The harmonics' estimates, cov6, the delay's half-width (s), the Birge ratio and the covariance.

    The noise's covariance is ``s^2 (J^T J)^-1`` with white noise, or with ``row_var`` (each reduced
    row's variance, segments x rows) the sandwich ``C (sum_r row_var_r J_r^T J_r) C``; with
    ``spec.lack_of_fit`` each reported quantity (the delay, each part's pair per harmonic) gets the
    wider of it and the segments' scatter (:func:`wider_per_quantity`), below
    :data:`MIN_SEGMENTS_SCATTER` segments the noise's widened by the pooled lack of fit (Birge ratio).
    """
    C = parts.cov_unscaled
    n_tau = int(spec.fit_delay)
    nh = len(spec.harmonics)
    ssr_red = float(np.sum(parts.res * parts.res))
    if row_var is None:
        cov = parts.s2 * C
        # Lack of fit between segments (Birge ratio): the projected rows hold only what the ripple
        # model leaves unexplained from one segment to the next; with an exact model their mean
        # square is s2. More than that widens the intervals by the ratio.
        chi2_red = ssr_red / parts.s2 if parts.s2 > 0 else math.nan
    else:
        info = np.einsum("sr,srp,srq->pq", row_var, parts.jac, parts.jac)
        cov = C @ info @ C
        chi2_red = float(np.sum(parts.res * parts.res / np.maximum(row_var, 1e-300)))
    birge = chi2_red / parts.dof_red if parts.dof_red >= 1 and math.isfinite(chi2_red) else 1.0
    if spec.lack_of_fit:
        # scipy.special alone: scipy.stats (whose t.ppf is this function) costs half a second of
        # every `eol-cal fit` to import (issue 37)
        from scipy.special import stdtrit  # heavy: not at `eol-cal run`'s start (tests/test_imports.py)

        if parts.scatter is not None:
            cov = wider_per_quantity(cov, parts.scatter, _quantity_blocks(spec), parts.jac.shape[0])
        elif parts.dof_red >= 1:
            # the wider of two: the noise's (from thousands of samples: the normal's 1.96) and the
            # pooled lack of fit's, whose variance has the projected rows' few degrees of freedom
            widen = max(1.0, math.sqrt(max(birge, 0.0)) * float(stdtrit(parts.dof_red, 0.975)) / Z95)
            cov = cov * widen * widen
    p = parts.p
    harmonics: dict = {h: {} for h in spec.harmonics}
    names = [name for name, on in (("c", spec.fit_c), ("k", spec.fit_k)) if on]
    rows, cols = _pair_blocks(n_tau, len(names) * nh)
    estimates = amp_phase_pairs(p[n_tau : n_tau + 2 * len(names) * nh].reshape(-1, 2), cov[rows, cols])
    for ip, name in enumerate(names):
        for ih, h in enumerate(spec.harmonics):
            harmonics[h][name] = estimates[ip * nh + ih]
    i6 = [n_tau + (ip * nh + spec.harmonics.index(6)) * 2 + j for ip in range(len(names)) for j in (0, 1)]
    delay_ci = Z95 * math.sqrt(max(cov[0, 0], 0.0)) * TAU_SCALE if spec.delay_s is None else 0.0
    i6_rows = np.array(i6)
    return harmonics, cov[i6_rows[:, None], i6_rows], delay_ci, birge, cov


def segment_coefficients(R: np.ndarray, z: np.ndarray, g: np.ndarray, ymean: np.ndarray,
                         q: int) -> tuple[np.ndarray, np.ndarray]:
    """Each segment's mean torque (N*m) and column coefficients (nuisance, then harmonics): the
    projected nuisance back-substituted from the segment's compression (``R`` (segments, m, m),
    ``z`` (segments, m), ``ymean`` (segments,) N*m: :class:`Compressed`'s) and its harmonics'
    coefficients ``g`` (segments, m - q) (the solver's), ``q`` nuisance columns. Its first Legendre
    term is the mean offset. The segments of one motor, or of a whole chunk's motors at once: each
    segment's figures are its own (:func:`unpack`'s, bit for bit)."""
    rhs = z[:, :q] - np.einsum("sij,sj->si", R[:, :q, q:], g)
    nuis = np.linalg.solve(R[:, :q, :q], rhs[..., None])[..., 0]
    return ymean + nuis[:, 0], np.concatenate([nuis, g], axis=1)


def unpack(out: dict, comp: Compressed, spec: FitSpec, S_valid: int,
           coefficients: tuple[np.ndarray, np.ndarray] | None = None) -> MotorFit:
    """Turn the solver's arrays for one motor into a :class:`MotorFit`.

    The intervals take the noise as white, ``s^2 = SSR / (n - n_parameters)`` counting the projected
    nuisance parameters (:func:`_intervals`); :func:`at_line_noise` makes them again at the noise each
    harmonic has at its own frequency, once it is measured. Amplitude/phase intervals follow by the
    delta method. ``coefficients``: the first ``S_valid`` segments' :func:`segment_coefficients`
    where the caller made them for many motors at once (default: made here).
    """
    p = np.asarray(out["p"], dtype=float)
    n_tau = int(spec.fit_delay)
    nh = len(spec.harmonics)
    q = spec.n_nuis
    valid = comp.n > 0
    n = float(comp.n.sum())
    ssr = float(out["ssr_red"]) + float(comp.floor[valid].sum())
    n_par = n_tau + spec.n_glob + float(comp.n_nuis[valid].sum())
    S = int(valid.sum())
    C = np.asarray(out["cov_unscaled"], dtype=float)
    jac, res = np.asarray(out["jac"], dtype=float)[valid], np.asarray(out["res"], dtype=float)[valid]
    parts = CovarianceParts(
        p=p, cov_unscaled=C, jac=jac, res=res, s2=ssr / max(n - n_par, 1.0),
        scatter=segment_scatter(jac, res, C) if spec.lack_of_fit and S >= MIN_SEGMENTS_SCATTER else None,
        dof_red=float(S) * 2 * nh - (n_tau + spec.n_glob))
    harmonics, cov6, delay_ci, birge, cov = _intervals(parts, spec, None)
    delay = p[0] * TAU_SCALE if spec.delay_s is None else float(spec.delay_s)  # fitted (n_tau = 1): p[0]
    t_avg, coef = coefficients or segment_coefficients(comp.R[:S_valid], comp.z[:S_valid],
                                                       np.asarray(out["g"], dtype=float)[:S_valid], comp.ymean[:S_valid], q)
    sst = float(comp.sst[valid].sum())
    # the arrays' own methods: np.all/np.any's dispatch was a tenth of unpack's time (issue 37)
    finite = bool(np.isfinite(p).all() and np.isfinite(np.diag(cov)).all())
    return MotorFit(
        harmonics=harmonics,
        delay_s=float(delay),
        delay_ci95=float(delay_ci),
        t_avg=t_avg,
        rms=math.sqrt(max(ssr, 0.0) / n),
        r2=1.0 - ssr / sst if sst > 0 else float("nan"),
        solver_result=solver_result(int(out["result"])),
        steps=int(out["steps"]),
        n_samples=int(n),
        coef=coef,
        birge=birge,
        current=(comp.cur_re + 1j * comp.cur_im)[:S_valid] if comp.cur_re.any() or comp.cur_im.any() else None,
        finite=finite,
        cov6=cov6,
        parts=parts,
    )


def at_line_noise(fit: MotorFit, spec: FitSpec, row_var: np.ndarray) -> MotorFit:
    """The same fit with its intervals at the noise each harmonic has at its own frequency.

    ``row_var`` (segments x reduced rows, N*m^2 * samples; :meth:`~eol_cal.analysis.fit.
    segment_noise.SegmentNoise.row_variance`): the variance of each segment's rows of each harmonic,
    measured on the residual beside the line. The residual's average, taken as white, is not what the
    6th has: with the orders' leak gone it read the 6th's noise ~20 % high in variance, so the noise's
    interval (the wider of the two on 192 of 200 motors) covered k6 98 % alone (bench/bench_coverage.py).
    A fit without its :class:`CovarianceParts` (not converged) is returned as it is, and so is one
    of fewer than :data:`MIN_SEGMENTS_SCATTER` segments: there the lack of fit pooled over every
    harmonic's rows (Birge ratio) widens the noise's interval, and a bin beside one harmonic can hold
    another line (the 16th of a 64-PPR encoder's quantised angle on 4 pole pairs beside the 18th):
    counted as that harmonic's noise it diluted the 6th's lack of fit in the pool (one load point,
    two segments, cogging leaking into k6: Birge 2.16 -> 1.07, k6's interval 6.4 -> 4.0 % of k6 against
    an error of 5.1 %; tests/test_fit_cli.py).
    """
    if fit.parts is None or not takes_line_noise(fit) or row_var.shape != fit.parts.res.shape:
        return fit
    harmonics, cov6, delay_ci, birge, cov = _intervals(fit.parts, spec, row_var)
    if not np.all(np.isfinite(np.diag(cov))):
        return fit
    return dataclasses.replace(fit, harmonics=harmonics, cov6=cov6, delay_ci95=float(delay_ci), birge=birge)


def takes_line_noise(fit: MotorFit) -> bool:
    """Whether :func:`at_line_noise` makes ``fit``'s intervals again (else it returns the fit as it
    is): a converged fit of at least :data:`MIN_SEGMENTS_SCATTER` segments. A caller measures the
    noise at every harmonic only then (:func:`~eol_cal.analysis.fit.segment_noise.segment_noise`:
    a refit's fits of six segments read the 6th's alone, in the model check)."""
    return fit.parts is not None and fit.converged and fit.parts.scatter is not None
