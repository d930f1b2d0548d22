"""The fit checks its own model: k6 and c6 estimated per speed band must agree within their intervals.

The motor's ripple does not depend on speed; what does is what stands between it and the
transducer (the bench's response, the transducer's lag), and the fit divides that out with the
bench file it is given. When the torque path has a resonance the bench file does not describe,
or the bench file is not the bench's, what is left differs from one speed to the next: the same
motor fitted on each speed band alone gives different k6 and c6. So after the fit the segments
are grouped into speed bands (|speed| within 10 % of each other), each band with at least two
load points is fitted alone (delay fixed at the joint fit's: one band cannot tell it), and the
bands' 6th-harmonic ``(c6, k6)`` phasor pairs are compared with their weighted mean:
``chi2 = sum_b (z_b - zbar)^T C_b^-1 (z_b - zbar)`` on ``4 (B - 1)`` degrees of freedom, ``C_b`` the
band's full 4 x 4 covariance (c6 and k6 of one band are an intercept and a slope over the load
points, strongly correlated: summed as two independent tests, the statistic's tail was too heavy).

The noise a band's covariance is scaled by is the noise at the 6th harmonic's own frequency, not
the residual's average (:mod:`~eol_cal.analysis.fit.segment_noise`): the torque's noise is far from white there (the
current loop's answer to the ECU's current noise reaches the shaft below the transducer's
bandwidth; what the ECU's ``iq`` channel does not cancel of it stayed 4-11 times the white
level at 18-36 Hz on the plant), so it is measured per segment on the residual's neighbouring
frequencies ``6 f_e + k / T`` (``2 <= |k| <= 9``: no ripple there, whatever the path does),
with the ECU's current taken out through the same path and transducer as the fit takes it. The
joint fit's lack of fit (Birge ratio) widened the bands before: the 6th's own is what a wrong bench
file inflates, so it blinded the check, and the pooled one left 3-10 % of right-model plant motors
below p = 0.001. The p-value is Snedecor's F (the noise level is itself estimated, 32 degrees of
freedom a segment). A p-value below the
limit (:class:`eol_cal.analysis.result.CiLimits` ``model_p``) makes the motor's status
``model_mismatch`` with the bands' figures as the reason.

At low speed the check is nearly blind: below a torsion mode the path's gain rises only as
``(f / f0)^2``, so the calibration profile's 60 and 120 rpm (the 6th at 18 and 36 Hz with 3 pole
pairs) see a 250 Hz mode as a 1.5 % change of k6 between the bands, inside their +-1-2 %
intervals. So the check also says how far it sees (:func:`sees_up_to_hz`: the highest mode it
would find at least half the time), and where that is below the modes real torque paths have
(:data:`RESONANCE_TOP_HZ`) and the bench file was not identified on the bench (``eol-cal bench
identify``), its status is ``insensitive``: bands that agree then vouch for nothing.

Where the bench file came from (:func:`bench_provenance`, the check's ``bench``): ``identified``
(``eol-cal bench identify`` measured it on the bench), ``simulated`` (every capture comes from the
plant and says it simulated exactly the torque path the file gives: the demo, CI, the station's
simulated rig; a capture's own claim, which the result keeps visible) or ``assumed`` (the built-in
``paper`` or a hand-written file on a dyno nobody measured; a real dyno's captures make no claim).
On an assumed file a check that is ``insensitive`` or ``not checked`` leaves the file unverified,
which the station's limits judge by default (the limit on ``bench_assumed``, :mod:`eol_cal.records.limits`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from eol_cal.analysis.fit.batch import fit_many
from eol_cal.capture.data import Capture
from eol_cal.domain.bench_mechanics import RIGID, SIMULATED_BENCH_KEY, BenchMechanics, model_digest
from eol_cal.analysis.fit.model import FitSpec, SteadySegments
from eol_cal.analysis.fit.motor_fit import Estimate, MotorFit
from eol_cal.analysis.fit.segment_noise import SegmentNoise, segment_noise

#: segments whose |speed| is within this fraction of each other share a band
BAND_TOL = 0.1
#: the highest torsion mode (Hz) of the torque paths real benches have (shaft, couplings and
#: transducer: 150-400 Hz, issue 34; the plant's spread draws them there): a check that cannot see
#: a mode this high cannot vouch for a bench file nobody identified
RESONANCE_TOP_HZ = 400.0
#: damping ratio of the mode the sensitivity assumes (below the mode the gain hardly depends on it)
SENSITIVITY_ZETA = 0.1
#: where the bench file the fit divided out came from (:func:`bench_provenance`)
BENCH_SOURCES = ("identified", "simulated", "assumed")
#: the candidate modes :func:`sees_up_to_hz` tries (Hz), made once (np.geomspace per motor was a third
#: of its time)
_MODES_HZ = np.geomspace(20.0, 5000.0, 241)
_MODES_HZ.flags.writeable = False


@dataclass(frozen=True)
class ModelCheck:
    """The speed-band check of one motor's fit.

    status : ``ok``, ``mismatch``, ``insensitive`` (the bands agree but could not have seen a
    resonance of the range real torque paths have, on a bench file not identified) or ``not
    checked``; note : why not checked, or the mismatch in words; p_value, chi2, dof : the test
    (NaN, 0 when not checked); bands : per band its speed (rpm, mean |speed|), segments and
    ``k6``, ``phase_k6``, ``c6``, ``phase_c6`` (value, ci95; offline frame: only their
    differences matter); sees_up_to_hz : the highest torsion mode the test would find half the
    time (Hz, :func:`sees_up_to_hz`; NaN when not checked); bench : where the bench file came
    from (:data:`BENCH_SOURCES`, :func:`bench_provenance`).
    """

    status: str
    note: str
    p_value: float = math.nan
    chi2: float = math.nan
    dof: int = 0
    bands: tuple[dict[str, Any], ...] = ()
    sees_up_to_hz: float = math.nan
    bench: str = "assumed"

    def to_json(self) -> dict[str, Any]:
        p = self.p_value if math.isfinite(self.p_value) else None
        chi2 = self.chi2 if math.isfinite(self.chi2) else None
        out = {"status": self.status, "note": self.note, "p_value": p, "chi2": chi2, "dof": self.dof,
               "bands": [dict(b) for b in self.bands], "bench": self.bench}
        if math.isfinite(self.sees_up_to_hz):
            out["sees_up_to_hz"] = self.sees_up_to_hz
        return out


def bench_provenance(mechanics: BenchMechanics | None, captures: list[Capture]) -> str:
    """Where the bench file the fit divides out came from (:data:`BENCH_SOURCES`).

    ``identified`` when ``eol-cal bench identify`` wrote it (its ``[identification]`` table);
    ``simulated`` when every capture says it came from the plant (directly, or through the dyno
    simulator's ``sim_bench`` register) simulating exactly the torque path the file gives
    (metadata :data:`~eol_cal.domain.bench_mechanics.SIMULATED_BENCH_KEY`: its
    :func:`~eol_cal.domain.bench_mechanics.model_digest`; ``none`` for no file, a rigid coupling);
    else ``assumed``. The claim is the capture's own (untrusted): the result keeps it visible.
    """
    if mechanics is not None and mechanics.identified:
        return "identified"
    digest = RIGID if mechanics is None else model_digest(mechanics)
    if captures and all(c.metadata.get(SIMULATED_BENCH_KEY) == digest for c in captures):
        return "simulated"
    return "assumed"


def speed_bands(omega: np.ndarray, tol: float = BAND_TOL) -> list[np.ndarray]:
    """Segment indices grouped by |speed| (rad/s): sorted, a new band where the next speed is more
    than ``tol`` above the band's first."""
    w = np.abs(np.asarray(omega, dtype=float))
    order = np.argsort(w, kind="stable")
    bands: list[list[int]] = []
    for i in order:
        if bands and w[i] <= w[bands[-1][0]] * (1 + tol):
            bands[-1].append(int(i))
        else:
            bands.append([int(i)])
    return [np.array(sorted(b)) for b in bands]


def _subset(seg: SteadySegments, idx: np.ndarray) -> SteadySegments:
    return dataclasses.replace(seg, theta=[seg.theta[i] for i in idx], t=[seg.t[i] for i in idx],
                               torque=[seg.torque[i] for i in idx], i_qo=seg.i_qo[idx], omega_e=seg.omega_e[idx],
                               labels=[seg.labels[i] for i in idx] if seg.labels else [],
                               kt_iq=None if seg.kt_iq is None else [seg.kt_iq[i] for i in idx])


def _pair(e: Estimate) -> np.ndarray:
    """The (cos, sin) pair of an amplitude/phase estimate: the solver's parameters."""
    return e.value * np.array([math.cos(e.phase), math.sin(e.phase)])


def mode_gain(f_hz: np.ndarray, f0_hz: float | np.ndarray, zeta: float = SENSITIVITY_ZETA) -> np.ndarray:
    """|T_shaft / T_airgap| of a torsion mode at ``f0_hz`` (Hz) with damping ``zeta``, at ``f_hz`` (Hz)
    (the two broadcast against each other)."""
    r = np.abs(np.asarray(f_hz, dtype=float)) / np.asarray(f0_hz, dtype=float)
    return np.abs(1.0 / (1.0 - r * r + 2j * zeta * r))


def sees_up_to_hz(f6_hz: np.ndarray, info: np.ndarray, dof: int, p_min: float) -> float:
    """The highest torsion mode (Hz, damping :data:`SENSITIVITY_ZETA`) an unmodelled one of which
    the check would report as a mismatch at least half the time; 0 when none from 20 Hz up.

    Parameters
    ----------
    f6_hz : ndarray
        Each band's 6th-harmonic frequency (Hz).
    info : ndarray
        Each band's information on a common scaling of its phasors: ``sum_parts zbar^T C_b^-1 zbar``
        (1; ``zbar`` the weighted mean phasor, ``C_b`` the band's covariance).
    dof, p_min
        The test's degrees of freedom and the p-value below which it reports a mismatch.

    Notes
    -----
    The mode scales band b's phasors by its gain ``g_b``; what is left after the weighted mean
    gain ``gbar`` gives the chi-square's noncentrality ``sum_b info_b (g_b / gbar - 1)^2``. The
    mode's phase, nearly linear in frequency below it, is taken up by the fitted delay and
    ignored here, and so is the delay's share of the gain: the figure errs towards blindness.
    """
    # scipy.special, not scipy.stats: the same functions (chi2.isf is chdtri) without the 0.5-1 s
    # scipy.stats costs to import in a one-capture `eol-cal fit`
    from scipy.special import chdtri, chndtr

    crit = float(chdtri(dof, p_min))
    # every candidate mode at once (one column each): a refit calls this per motor
    f0 = _MODES_HZ
    info_b = np.asarray(info, dtype=float)[:, None]
    g = mode_gain(np.asarray(f6_hz, dtype=float)[:, None], f0[None, :])
    gbar = (info_b * g).sum(axis=0) / info_b.sum()
    lam = (info_b * (g / gbar - 1.0) ** 2).sum(axis=0)
    seen = f0[chndtr(crit, dof, lam) <= 0.5]  # detected at least half the time: sf >= 0.5
    return float(seen[-1]) if len(seen) else 0.0


def _widened(f: MotorFit, factor: float) -> MotorFit:
    """The same fit with the 6th's intervals (the check reads no other) times ``factor``."""
    harmonics = {**f.harmonics, 6: {part: dataclasses.replace(e, ci95=e.ci95 * factor, phase_ci95=e.phase_ci95 * factor)
                                    for part, e in f.harmonics[6].items()}}
    return dataclasses.replace(f, harmonics=harmonics, cov6=None if f.cov6 is None else f.cov6 * factor * factor)


def check_model(seg: SteadySegments, fit: MotorFit, spec: FitSpec, p_min: float,
                bench: str = "assumed", noise: SegmentNoise | None = None,
                cache_dir: str | os.PathLike[str] | None = None) -> ModelCheck:
    """Fit each speed band alone and test that k6 and c6 agree between bands (module docstring).

    Parameters
    ----------
    seg, fit, spec
        The motor's segments, its joint fit and the model.
    p_min : float
        The least p-value of an agreement (below: ``mismatch``).
    bench : str
        Where the bench file came from (:func:`bench_provenance`): only on an ``assumed`` one do
        bands that agree but could not see a mode up to :data:`RESONANCE_TOP_HZ` give ``insensitive``.
    noise : SegmentNoise, optional
        The segments' noise at the 6th (:func:`~eol_cal.analysis.fit.segment_noise.segment_noise`
        at the fit's delay), when the caller measured it already for the joint fit's intervals; else
        the 6th's alone is measured here, once the bands' fits converged.
    cache_dir : path, optional
        The fit's directory of serialized solvers (:func:`~eol_cal.analysis.fit.batch.fit_many`):
        the bands' solver is read from there instead of traced in every process (~0.6 CPU s).
    """
    from scipy.special import fdtrc  # scipy.stats' f.sf (above)

    if not fit.converged:
        return ModelCheck("not checked", "the fit did not converge", bench=bench)
    parts = [p for p, on in (("k", spec.fit_k), ("c", spec.fit_c)) if on]
    bands, skipped = [], []
    for idx in speed_bands(seg.omega_e):
        rpm = float(np.mean(np.abs(seg.omega_e[idx]))) / seg.pole_pairs * 60.0 / (2 * math.pi)
        scale = max(float(np.abs(seg.i_qo[idx]).max()), 1e-9)
        loads = len(np.unique(np.round(seg.i_qo[idx] / (0.05 * scale))))
        if len(parts) == 2 and loads < 2:
            skipped.append(f"{rpm:.4g} rpm (one load point)")
            continue
        bands.append((idx, rpm))
    if len(bands) < 2:
        why = "fewer than two speed bands with two load points each"
        return ModelCheck("not checked", why + (f": {', '.join(skipped)} left out" if skipped else ""), bench=bench)
    band_spec = dataclasses.replace(spec, delay_s=fit.delay_s, lack_of_fit=False)
    fits = fit_many([_subset(seg, idx) for idx, _ in bands], band_spec, mode="loop", cache_dir=cache_dir)
    if not all(f.converged and f.cov6 is not None for f in fits):
        return ModelCheck("not checked", "a speed band's fit did not converge", bench=bench)
    # each band's covariance at the noise its 6th actually has (module docstring)
    if noise is None:
        noise = segment_noise(seg, spec, fit.delay_s, harmonics=(6,))
    ratios = [noise.ratio(idx) for idx, _ in bands]
    fits = [_widened(f, math.sqrt(max(r, 1e-12))) for f, r in zip(fits, ratios, strict=True)]
    dof_noise = int(sum(noise.dof[idx, noise.harmonics.index(6)].sum() for idx, _ in bands))
    n = 2 * len(parts)  # each band's phasors: the fitted parts' (cos, sin) pairs, c's then k's
    # the 6th only: the 12th and 18th would see the path nearer a resonance, but on the plant their
    # speed bands differed beyond their intervals on 4 of 40 motors of the paper bench (the ECU's
    # own current ripple at those orders changes with speed), a false alarm of the bench file
    zs = [np.concatenate([_pair(f.harmonics[6][part]) for part in ("c", "k") if part in parts]) for f in fits]
    Ws = [np.linalg.pinv(np.asarray(f.cov6)) for f in fits]  # cov6 holds the fitted parts' pairs, in zs' order
    zbar = np.linalg.solve(sum(Ws), sum(W @ z for W, z in zip(Ws, zs, strict=True)))
    chi2 = float(sum((z - zbar) @ W @ (z - zbar) for W, z in zip(Ws, zs, strict=True)))
    dof = n * (len(fits) - 1)
    # the sensitivity on one common scaling of the bands' phasors, per part (each part's own share)
    rows: list[dict[str, Any]] = []
    info = np.zeros(len(fits))
    for j in range(0, n, 2):
        info += np.array([float(zbar[j:j + 2] @ W[j:j + 2, j:j + 2] @ zbar[j:j + 2]) for W in Ws])
    for (idx, rpm), f in zip(bands, fits, strict=True):
        row: dict[str, Any] = {"speed_rpm": rpm, "segments": len(idx)}
        for part in parts:
            e = f.harmonics[6][part]
            row[f"{part}6"] = {"value": e.value, "ci95": e.ci95}
            row[f"phase_{part}6"] = {"value": e.phase, "ci95": e.phase_ci95}
        rows.append(row)
    # the noise level is itself estimated (dof_noise): Snedecor's F, not the chi-square
    p = float(fdtrc(dof, dof_noise, chi2 / dof))
    words = "; ".join(
        f"{r['speed_rpm']:.4g} rpm: " + ", ".join(
            f"{part}6 {r[f'{part}6']['value'] * 1e3:.4g}±{r[f'{part}6']['ci95'] * 1e3:.2g} "
            f"at {math.degrees(r[f'phase_{part}6']['value']):.1f}±{math.degrees(r[f'phase_{part}6']['ci95']):.1f} deg"
            for part in parts) for r in rows)
    agree = f"the speed bands agree (chi2 {chi2:.3g} on {dof} dof, p = {p:.3g})"
    f6 = np.array([6.0 * rpm * seg.pole_pairs / 60.0 for _, rpm in bands])
    seen = sees_up_to_hz(f6, info, dof, p_min)
    if p >= p_min and bench == "assumed" and seen < RESONANCE_TOP_HZ:
        note = (f"{agree}, but at these speeds (the 6th at {f6.min():.3g}-{f6.max():.3g} Hz) they would show a "
                f"torque-path resonance only below {seen:.0f} Hz (real torque paths have them at up to "
                f"{RESONANCE_TOP_HZ:.0f} Hz), and the bench file was not identified on this bench: a resonance it "
                "does not describe would bias k6 unseen. Identify the bench (eol-cal bench identify, "
                "docs/bench-identify.md)")
        return ModelCheck("insensitive", note, p, chi2, dof, tuple(rows), seen, bench)
    if p >= p_min:
        return ModelCheck("ok", agree, p, chi2, dof, tuple(rows), seen, bench)
    note = (f"the ripple differs between speed bands beyond its intervals (chi2 {chi2:.3g} on {dof} dof, p = {p:.2g} < "
            f"{p_min:g}; {words}; mN*m/A and mN*m): the torque path is not what the bench file says (an unmodelled "
            f"resonance, a wrong bench file?)")
    return ModelCheck("mismatch", note, p, chi2, dof, tuple(rows), seen, bench)
