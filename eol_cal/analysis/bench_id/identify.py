"""The torque path identified from a master motor's sweep: the bench's shaft and transducer.

Model of a point (:class:`eol_cal.analysis.bench_id.sweep.SweepPoints`) at frequency ``omega``::

    M = H(omega) * (Z_h + kt * I),   H = G(omega; J_dyno, K_shaft, shaft_zeta, dyno loop) * T(omega)

``G`` is the shaft line (:func:`eol_cal.domain.bench_mechanics.torsion_response`, with the master motor's rotor
inertia from its data sheet), ``T`` the transducer (:func:`eol_cal.domain.bench_mechanics.transducer_response`:
a first-order low-pass and a pure delay), ``Z_h`` the motor's own ripple at harmonic ``h`` (one
complex value per harmonic, or ``c_h + k_h i_qo`` when the sweep holds several loads), ``I`` the
measured q-current phasor. The ripple is not known in advance: it enters linearly and is
projected out for every trial of the nonlinear parameters (variable projection), so the sweep
fixes the path's shape over frequency; the current's ripple, known in absolute terms, ties its
level.

Nonlinear parameters: the torsion mode's undamped frequency ``f_n`` (Hz; ``K_shaft = (2 pi f_n)^2
J J_dyno / (J + J_dyno)``) and damping ratio, the transducer's time constant (s; its bandwidth is
``1 / (2 pi tau)``) and delay (s), and ``J_dyno`` when the sweep resolves it. The dyno's speed
loop acts at a few hertz, where the rotor's share of the torque is negligible: it is held at the
base bench's values, and the result says by how much halving or doubling them would move the
response at the sweep's points. Every estimate comes with a 95 % interval from the Jacobian,
widened by the Birge ratio when the scatter exceeds the points' own errors.

A sweep that cannot identify the path is refused (InputError naming the files and the field):
too few speeds, the torsion mode outside the measured band or without points on both flanks, an
undetermined mode, or a model the points contradict.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.analysis.bench_id.sweep import SweepPoints
from eol_cal.errors import InputError
from eol_cal.domain.bench_mechanics import BenchMechanics, torsion_response, transducer_response
from eol_cal.domain.motor_params import MotorParams

if TYPE_CHECKING:
    from scipy.optimize import OptimizeResult

TWO_PI = 2.0 * math.pi
#: fewest distinct speeds a sweep must hold
MIN_SPEEDS = 5
#: largest Birge ratio sqrt(chi2 / dof) accepted: beyond, the model does not describe the points
MAX_BIRGE = 3.0
#: a point whose normalised residual exceeds this is dropped once (an alias of the ECU's
#: sampling landing on a harmonic), and named in the result
OUTLIER_SIGMA = 6.0
#: largest relative 95 % half-width of the torsion frequency accepted
MAX_FN_CI_REL = 0.10
#: a free J_dyno whose relative 95 % half-width exceeds this is not resolved: held at the base value
MAX_JDYNO_CI_REL = 0.25
#: points a flank of the mode needs (signal above 3 standard errors)
MIN_FLANK_POINTS = 2
_Z95 = 1.959964


@dataclass(frozen=True)
class Estimate:
    """One identified (or held) quantity: value, 95 % half-width (None: held or unresolved), unit, how."""

    value: float
    ci95: float | None
    unit: str
    status: str  # "identified", "held", "unresolved"
    note: str = ""


@dataclass(frozen=True)
class BenchIdentification:
    """The identified torque path.

    Attributes
    ----------
    mechanics : BenchMechanics
        The bench file's values (held ones from ``base``).
    estimates : dict[str, Estimate]
        ``f_n_hz``, ``K_shaft``, ``shaft_zeta``, ``J_dyno``, ``dyno_bw_hz``, ``dyno_zeta``,
        ``transducer_bw_hz``, ``transducer_delay_s``.
    base : BenchMechanics
        The bench the held values come from.
    points : SweepPoints
        The points used.
    dropped : list of str
        Points dropped as outliers, with their residual.
    birge : float
        sqrt(chi2 / dof) of the final fit.
    dof : int
        Degrees of freedom.
    ripple : dict[int, ndarray]
        Per harmonic the fitted ripple coefficients (N*m; ``[Z]`` or ``[c, k]``, complex).
    motor : MotorParams
        The master motor's data (rotor inertia, friction).
    """

    mechanics: BenchMechanics
    estimates: dict[str, Estimate]
    base: BenchMechanics
    points: SweepPoints
    dropped: list[str]
    birge: float
    dof: int
    ripple: dict[int, np.ndarray]
    motor: MotorParams
    notes: list[str] = field(default_factory=list)

    def response(self, omega: np.ndarray) -> np.ndarray:
        """The identified path ``H`` (shaft line times transducer) at ``omega`` (rad/s)."""
        return path_response(omega, self.motor, self.mechanics)

    def inputs(self) -> np.ndarray:
        """The air-gap torque phasor ``Z_h + kt I`` at each point (N*m, complex)."""
        return _inputs(self.points, self.ripple)


def path_response(omega: np.ndarray, motor: MotorParams, mechanics: BenchMechanics) -> np.ndarray:
    """Shaft line times transducer at ``omega`` (rad/s) for a bench (transducer as it gives it)."""
    return (torsion_response(omega, motor.J, motor.B, mechanics)
            * transducer_response(omega, mechanics.transducer_bw_hz, mechanics.transducer_delay_s))


def _bench(u: np.ndarray, free: tuple[str, ...], base: BenchMechanics, J: float) -> BenchMechanics:
    """The bench of parameter vector ``u`` (``free`` names its entries)."""
    v = dict(zip(free, u, strict=True))
    J_dyno = math.exp(v["ln_J_dyno"]) if "ln_J_dyno" in v else base.J_dyno
    f_n = math.exp(v["ln_f_n"])
    J_eff = J * J_dyno / (J + J_dyno)
    tau = v["tau_lp_ms"] * 1e-3
    return dataclasses.replace(base, J_dyno=J_dyno, K_shaft=(TWO_PI * f_n) ** 2 * J_eff,
                               shaft_zeta=math.exp(v["ln_zeta"]),
                               transducer_bw_hz=math.inf if tau <= 0 else 1.0 / (TWO_PI * tau),
                               transducer_delay_s=v["delay_ms"] * 1e-3, source="", sha256="")


def _bases(points: SweepPoints) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per harmonic: its point indices and the columns of its ripple (1, or 1 and i_qo)."""
    out = {}
    for h in np.unique(points.harmonic):
        idx = np.flatnonzero(points.harmonic == h)
        loads = np.unique(np.round(points.i_qo[idx] * 2) / 2)
        cols = [np.ones(len(idx))] + ([points.i_qo[idx]] if len(loads) >= 2 else [])
        out[int(h)] = (idx, np.stack(cols, axis=1))
    return out


def _inputs(points: SweepPoints, ripple: dict[int, np.ndarray]) -> np.ndarray:
    Z = np.zeros(len(points.M), dtype=complex)
    for h, (idx, cols) in _bases(points).items():
        Z[idx] = cols @ ripple[h]
    return Z + points.kt * points.Iq


def _residual(H: np.ndarray, points: SweepPoints) -> tuple[np.ndarray, dict[int, np.ndarray], np.ndarray]:
    """Normalised complex residuals at a path ``H``, the ripple solved for, the points' sigmas."""
    sigma = np.sqrt(points.se_M ** 2 + (np.abs(H) * points.kt * points.se_Iq) ** 2)
    r = np.empty(len(H), dtype=complex)
    ripple = {}
    for h, (idx, cols) in _bases(points).items():
        y = (points.M[idx] - H[idx] * points.kt * points.Iq[idx]) / sigma[idx]
        A = H[idx, None] * cols / sigma[idx, None]
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        ripple[h] = coef
        r[idx] = y - A @ coef
    return r, ripple, sigma


def _fit(points: SweepPoints, motor: MotorParams, base: BenchMechanics, free: tuple[str, ...],
         starts: list[np.ndarray]) -> OptimizeResult:
    from scipy.optimize import least_squares

    def fun(u):
        H = path_response(points.omega, motor, _bench(u, free, base, motor.J))
        r, _, _ = _residual(H, points)
        return np.concatenate([r.real, r.imag])

    f_lo, f_hi = float(points.freq_hz.min()), float(points.freq_hz.max())
    lo = {"ln_f_n": math.log(f_lo / 4), "ln_zeta": math.log(0.005), "tau_lp_ms": 0.0, "delay_ms": -5.0,
          "ln_J_dyno": math.log(motor.J)}
    hi = {"ln_f_n": math.log(f_hi * 4), "ln_zeta": math.log(2.0), "tau_lp_ms": 50.0, "delay_ms": 5.0,
          "ln_J_dyno": math.log(1000 * base.J_dyno)}
    bounds = (np.array([lo[n] for n in free]), np.array([hi[n] for n in free]))
    best = None
    for u0 in starts:
        u0 = np.clip(u0, bounds[0] + 1e-9, bounds[1] - 1e-9)
        sol = least_squares(fun, u0, bounds=bounds, x_scale="jac", method="trf")
        if best is None or sol.cost < best.cost:
            best = sol
    return best


def _grid_starts(points: SweepPoints, motor: MotorParams, base: BenchMechanics, n_best: int = 3) -> list[np.ndarray]:
    """The best few points of a coarse grid over mode frequency, damping and transducer lag."""
    f_lo, f_hi = float(points.freq_hz.min()), float(points.freq_hz.max())
    free = ("ln_f_n", "ln_zeta", "tau_lp_ms", "delay_ms")
    scored = []
    for f_n in np.geomspace(f_lo / 2, f_hi * 2, 60):
        for zeta in (0.03, 0.06, 0.1, 0.18, 0.3, 0.5):
            for tau_ms in (0.0, 0.05, 0.15, 0.5, 1.5, 3.0, 6.0):
                u = np.array([math.log(f_n), math.log(zeta), tau_ms, 0.0])
                r, _, _ = _residual(path_response(points.omega, motor, _bench(u, free, base, motor.J)), points)
                scored.append((float(np.sum(np.abs(r) ** 2)), u))
    scored.sort(key=lambda x: x[0])
    return [u for _, u in scored[:n_best]]


def _refuse(points: SweepPoints, field_: str, reason: str) -> InputError:
    return InputError(", ".join(points.sources), field_, reason)


def _check_sweep(points: SweepPoints) -> None:
    speeds = np.unique(np.round(np.abs(points.speed_rpm) / 5) * 5)
    if len(speeds) < MIN_SPEEDS:
        raise _refuse(points, "speed_rpm", f"too few speeds to identify the torque path: {len(speeds)} steady "
                                           f"speed(s) ({', '.join(f'{s:g}' for s in speeds)} rpm), need at least "
                                           f"{MIN_SPEEDS} (ship profile bench-sweep: 60 .. 1500 rpm)")


def _check_mode(points: SweepPoints, f_n: float, f_n_ci: float) -> None:
    strong = np.abs(points.M) > 3 * points.se_M
    f = points.freq_hz
    below = int(np.sum(strong & (f < 0.8 * f_n)))
    above = int(np.sum(strong & (f > 1.2 * f_n)))
    top = float(f[strong].max()) if strong.any() else 0.0
    if above < MIN_FLANK_POINTS:
        per_rpm = float(np.median(f / (points.harmonic * np.maximum(np.abs(points.speed_rpm), 1e-9))))
        rpm = 1.3 * f_n / (6 * per_rpm)  # where the 6th passes the mode's upper flank
        raise _refuse(points, "speed_rpm", f"the torsion mode (about {f_n:.0f} Hz) lies outside the sweep: "
                                           f"{above} measured point(s) above {1.2 * f_n:.0f} Hz (highest with signal: "
                                           f"{top:.0f} Hz), need {MIN_FLANK_POINTS}; extend the sweep to about "
                                           f"{rpm:.0f} rpm, or measure with a transducer of more bandwidth")
    if below < MIN_FLANK_POINTS:
        raise _refuse(points, "speed_rpm", f"the torsion mode (about {f_n:.0f} Hz) lies below the sweep: {below} "
                                           f"point(s) under {0.8 * f_n:.0f} Hz, need {MIN_FLANK_POINTS}; start the "
                                           "sweep at a lower speed")
    if not f_n_ci <= MAX_FN_CI_REL * f_n:
        raise _refuse(points, "K_shaft", f"the sweep does not determine the torsion mode: {f_n:.0f} ± {f_n_ci:.0f} Hz "
                                         f"(95 %), more than ±{100 * MAX_FN_CI_REL:.0f} %; measure longer or at more "
                                         "speeds near it")


def identify_bench(points: SweepPoints, motor: MotorParams, base: BenchMechanics, name: str = "identified"
                   ) -> BenchIdentification:
    """Identify the torque path from a sweep's points (see the module doc).

    Parameters
    ----------
    points : SweepPoints
        The master motor's sweep (:func:`eol_cal.analysis.bench_id.sweep.sweep_points`).
    motor : MotorParams
        The master motor's data sheet (rotor inertia ``J`` kg*m^2, friction ``B`` N*m*s/rad).
    base : BenchMechanics
        Where the held values (the dyno's speed loop; ``J_dyno`` unless resolved) and the start
        come from.
    name : str
        The identified bench's name.
    """
    _check_sweep(points)
    starts = _grid_starts(points, motor, base)
    free4 = ("ln_f_n", "ln_zeta", "tau_lp_ms", "delay_ms")
    dropped: list[str] = []
    sol = _fit(points, motor, base, free4, starts)
    r = sol.fun[: len(points.M)] + 1j * sol.fun[len(points.M):]
    bad = np.abs(r) / math.sqrt(2) > OUTLIER_SIGMA * max(1.0, _birge(sol.fun, len(points.M), free4, points))
    if bad.any() and (~bad).sum() >= 0.8 * len(bad):
        dropped = [f"{points.speed_rpm[i]:.0f} rpm, harmonic {points.harmonic[i]} ({points.freq_hz[i]:.0f} Hz): "
                   f"residual {abs(r[i]) / math.sqrt(2):.1f} sigma" for i in np.flatnonzero(bad)]
        points = points.take(~bad)
        sol = _fit(points, motor, base, free4, [sol.x])
    # J_dyno: free when the sweep resolves it
    free: tuple[str, ...] = free4 + ("ln_J_dyno",)
    sol5 = _fit(points, motor, base, free, [np.append(sol.x, math.log(base.J_dyno))])
    cov5 = _covariance(sol5, len(points.M), free, points)
    jd_rel = _Z95 * math.sqrt(max(cov5[-1, -1], 0.0))
    notes = [f"left out: {line}" for line in points.skipped]
    if math.isfinite(jd_rel) and jd_rel <= MAX_JDYNO_CI_REL:
        sol = sol5
        cov = cov5
    else:
        free = free4
        cov = _covariance(sol, len(points.M), free, points)
        notes.append(f"J_dyno held at the base bench's {base.J_dyno:g} kg*m^2: the sweep resolves it only to "
                     f"±{100 * jd_rel:.0f} % (95 %)")
    birge = _birge(sol.fun, len(points.M), free, points)
    dof = _dof(len(points.M), free, points)
    if birge > MAX_BIRGE:
        res = sol.fun[: len(points.M)] + 1j * sol.fun[len(points.M):]
        worst = np.argsort(-np.abs(res))[:3]
        where = "; ".join(f"{points.speed_rpm[i]:.0f} rpm h{points.harmonic[i]} ({points.freq_hz[i]:.0f} Hz) "
                          f"{abs(res[i]) / math.sqrt(2):.1f} sigma" for i in worst)
        raise _refuse(points, "model", f"the two-inertia shaft and first-order transducer do not describe the sweep: "
                                       f"Birge ratio {birge:.2f} > {MAX_BIRGE:g} (worst points: {where})")
    bench = _bench(sol.x, free, base, motor.J)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    ix = {n: i for i, n in enumerate(free)}
    f_n = math.exp(sol.x[ix["ln_f_n"]])
    f_n_ci = _Z95 * f_n * sd[ix["ln_f_n"]]
    _check_mode(points, f_n, f_n_ci)
    est = _estimates(bench, base, sol.x, cov, free, f_n, f_n_ci, points, motor)
    final = dataclasses.replace(bench, name=name)
    if est["transducer_bw_hz"].status != "identified":
        final = dataclasses.replace(final, transducer_bw_hz=None)
    _, ripple, _ = _residual(path_response(points.omega, motor, bench), points)
    return BenchIdentification(final, est, base, points, dropped, birge, dof, ripple, motor, notes)


def _dof(n: int, free: tuple[str, ...], points: SweepPoints) -> int:
    """Degrees of freedom: two per point, less the path's parameters and the ripple's real ones."""
    return 2 * n - len(free) - 2 * sum(cols.shape[1] for _, cols in _bases(points).values())


def _birge(f: np.ndarray, n: int, free: tuple[str, ...], points: SweepPoints) -> float:
    """sqrt(chi2 / dof) of the normalised residuals ``f``."""
    return math.sqrt(float(np.sum(f * f)) / max(_dof(n, free, points), 1))


def _covariance(sol: OptimizeResult, n: int, free: tuple[str, ...], points: SweepPoints) -> np.ndarray:
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J)
    return cov * max(1.0, _birge(sol.fun, n, free, points)) ** 2


def _estimates(bench: BenchMechanics, base: BenchMechanics, u: np.ndarray, cov: np.ndarray, free: tuple[str, ...],
               f_n: float, f_n_ci: float, points: SweepPoints, motor: MotorParams) -> dict[str, Estimate]:
    ix = {n: i for i, n in enumerate(free)}

    def sd(name: str) -> float:
        return math.sqrt(max(cov[ix[name], ix[name]], 0.0))

    out = {"f_n_hz": Estimate(f_n, f_n_ci, "Hz", "identified", "undamped torsion frequency")}
    # K = (2 pi f_n)^2 J J_d / (J + J_d): d ln K = 2 d ln f_n + J / (J + J_d) d ln J_d
    g = np.zeros(len(free))
    g[ix["ln_f_n"]] = 2.0
    if "ln_J_dyno" in ix:
        g[ix["ln_J_dyno"]] = motor.J / (motor.J + bench.J_dyno)
        out["J_dyno"] = Estimate(bench.J_dyno, _Z95 * bench.J_dyno * sd("ln_J_dyno"), "kg*m^2", "identified")
    else:
        out["J_dyno"] = Estimate(base.J_dyno, None, "kg*m^2", "held", "not resolved by the sweep")
    out["K_shaft"] = Estimate(bench.K_shaft, _Z95 * bench.K_shaft * math.sqrt(max(g @ cov @ g, 0.0)), "N*m/rad",
                              "identified")
    out["shaft_zeta"] = Estimate(bench.shaft_zeta, _Z95 * bench.shaft_zeta * sd("ln_zeta"), "1", "identified")
    tau, tau_ci = u[ix["tau_lp_ms"]] * 1e-3, _Z95 * sd("tau_lp_ms") * 1e-3
    if tau > tau_ci:
        bw = 1.0 / (TWO_PI * tau)
        out["transducer_bw_hz"] = Estimate(bw, bw * tau_ci / tau, "Hz", "identified")
    else:
        out["transducer_bw_hz"] = Estimate(1.0 / (TWO_PI * (tau + tau_ci)), None, "Hz", "unresolved",
                                           "no low-pass resolved: the bandwidth is above this value (95 %)")
    out["transducer_delay_s"] = Estimate(u[ix["delay_ms"]] * 1e-3, _Z95 * sd("delay_ms") * 1e-3, "s", "identified")
    for key in ("dyno_bw_hz", "dyno_zeta"):
        out[key] = Estimate(getattr(base, key), None, "Hz" if key == "dyno_bw_hz" else "1", "held",
                            f"held at the base bench's value; halving or doubling it moves the response at the "
                            f"sweep's points by at most {100 * _sensitivity(bench, key, points, motor):.2g} %")
    return out


def _sensitivity(bench: BenchMechanics, key: str, points: SweepPoints, motor: MotorParams) -> float:
    """Largest relative change of the shaft line's response at the points for half or twice ``key``."""
    G = torsion_response(points.omega, motor.J, motor.B, bench)
    worst = 0.0
    for factor in (0.5, 2.0):
        other = dataclasses.replace(bench, **{key: getattr(bench, key) * factor})
        worst = max(worst, float(np.max(np.abs(torsion_response(points.omega, motor.J, motor.B, other) / G - 1))))
    return worst
