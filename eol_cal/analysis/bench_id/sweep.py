"""A master motor's speed sweep as points of the torque path's response: one complex phasor of the
shaft torque and one of the ECU's q current per steady segment and harmonic.

At each steady speed the 6th, 12th and 18th electrical harmonics of the motor's ripple reach the
transducer at ``h * omega_e``. Their phasors, fitted per segment by linear least squares (with an
offset, a drift and the mechanical orders 1..3 as nuisance columns), move through frequency as the
speed changes: the torque path's response sampled at each point. The ECU's measured q current is
fitted with the same columns, because the current ripple it carries (its angle estimate's errors,
the back-EMF's reaction to the speed ripple) is air-gap torque too, ``kt * i_q``, and grows with
speed: the path's input at a point is ``Z_h + kt * I`` with ``Z_h`` the motor's own ripple
(:mod:`eol_cal.analysis.bench_id.identify`).

Segments come from the fit's own segmentation (:func:`eol_cal.analysis.fit.capture.segment_motors`,
offline hall frame): one frame for the whole sweep, since the phases of all points are compared.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.fit.capture import segment_motors
from eol_cal.capture.data import Capture
from eol_cal.errors import InputError
from eol_cal.domain.motor_params import MotorParams

#: the electrical harmonics whose phasors sample the path
HARMONICS = (6, 12, 18)
#: mechanical orders fitted as nuisance (unbalance, eccentricity) so that they do not leak
MECH_ORDERS = (1, 2, 3)


@dataclass(frozen=True)
class SweepPoints:
    """The path's samples: one row per (steady segment, harmonic).

    Attributes
    ----------
    serial : str
        The master motor's serial.
    sources : list of str
        The capture files.
    kt : float
        Torque constant (N*m/A) the current's ripple is turned into torque with.
    omega : ndarray
        Angular frequency of the point (rad/s, signed: negative in reverse rotation).
    harmonic : ndarray of int
        Electrical harmonic order h.
    segment : ndarray of int
        Index of the steady segment.
    speed_rpm : ndarray
        The segment's mechanical speed (rpm, signed).
    i_qo : ndarray
        The segment's nominal q current (A).
    M, se_M : ndarray
        Shaft torque phasor (N*m, complex; ``T = Re(M exp(i h theta))``) and its standard error
        (N*m, per real component).
    Iq, se_Iq : ndarray
        q-current phasor (A, complex) and its standard error (A).
    skipped : tuple of str
        The capture windows that gave no steady segment (named, with the reason), none silently.
    """

    serial: str
    sources: list[str]
    kt: float
    omega: np.ndarray
    harmonic: np.ndarray
    segment: np.ndarray
    speed_rpm: np.ndarray
    i_qo: np.ndarray
    M: np.ndarray
    se_M: np.ndarray
    Iq: np.ndarray
    se_Iq: np.ndarray
    skipped: tuple[str, ...] = ()

    @property
    def freq_hz(self) -> np.ndarray:
        """|frequency| of each point (Hz)."""
        return np.abs(self.omega) / (2.0 * math.pi)

    def take(self, keep: np.ndarray) -> SweepPoints:
        """The points where ``keep`` (bool) is true."""
        arrays = {name: getattr(self, name)[keep] for name in ("omega", "harmonic", "segment", "speed_rpm", "i_qo",
                                                               "M", "se_M", "Iq", "se_Iq")}
        return SweepPoints(self.serial, self.sources, self.kt, **arrays, skipped=self.skipped)


def segment_phasors(theta: np.ndarray, pole_pairs: int, signals: np.ndarray,
                    harmonics: tuple[int, ...] = HARMONICS) -> tuple[np.ndarray, np.ndarray]:
    """Phasors of ``harmonics`` of each signal over one segment, with their standard errors.

    Parameters
    ----------
    theta : ndarray
        Unwrapped electrical angle (rad), one steady segment.
    pole_pairs : int
        Pole pairs (the mechanical orders are at ``theta / pole_pairs``).
    signals : ndarray
        Shape (samples, k): the signals (any unit).

    Returns
    -------
    phasors, se : ndarray
        Shape (len(harmonics), k): ``a - i b`` of ``a cos(h theta) + b sin(h theta)`` (the signal's
        unit) and the standard error of each component from the residual's variance.
    """
    span = float(np.ptp(theta)) or 1.0
    cols = [np.ones_like(theta), (theta - theta.mean()) / span]
    for h in harmonics:
        cols += [np.cos(h * theta), np.sin(h * theta)]
    theta_m = theta / pole_pairs
    for o in MECH_ORDERS:
        cols += [np.cos(o * theta_m), np.sin(o * theta_m)]
    A = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(A, signals, rcond=None)
    res = signals - A @ coef
    dof = max(len(theta) - A.shape[1], 1)
    var = np.sum(res * res, axis=0) / dof
    # columns of whole revolutions are near orthogonal: the diagonal of inv(A'A) per column pair
    diag = np.diag(np.linalg.inv(A.T @ A))
    idx = 2 + 2 * np.arange(len(harmonics))
    ph = coef[idx] - 1j * coef[idx + 1]
    se = np.sqrt(0.5 * (diag[idx] + diag[idx + 1]))[:, None] * np.sqrt(var)[None, :]
    return ph, se


def sweep_points(captures: list[Capture], motor: MotorParams, settle_s: float = 0.2) -> SweepPoints:
    """The path's samples of one master motor's sweep captures (any number of files).

    Refused (InputError naming the files and the field): captures of more than one motor, no
    ``iq`` channel (the current's ripple is part of the path's input), no steady segment.
    """
    for c in captures:
        if not c.has("iq"):
            raise InputError(c.source, "iq", "missing channel: the identification needs the ECU's measured q current "
                                             "(its ripple drives the torque path too): acquire with --all-channels")
    inputs = segment_motors(captures, motor, settle_s=settle_s, min_revs=1, hall_angle="nominal", mechanics=None)
    if len(inputs) != 1:
        raise InputError(", ".join(c.source for c in captures), "serial",
                         f"the sweep must come from one master motor, got {len(inputs)}: "
                         + ", ".join(mi.serial for mi in inputs))
    (mi,) = inputs
    seg = mi.segments
    kt = float(mi.kt)
    rows: dict[str, list] = {k: [] for k in ("omega", "harmonic", "segment", "speed_rpm", "i_qo", "M", "se_M", "Iq",
                                            "se_Iq")}
    for s, (theta, y, info) in enumerate(zip(seg.theta, seg.torque, mi.info, strict=True)):
        cap = mi.captures[mi.capture_of_segment[s]]
        iq = np.asarray(cap["iq"][info.start:info.stop], dtype=float)
        ph, se = segment_phasors(np.asarray(theta, dtype=float), seg.pole_pairs, np.stack([y, iq], axis=1))
        for j, h in enumerate(HARMONICS):
            rows["omega"].append(h * float(seg.omega_e[s]))
            rows["harmonic"].append(h)
            rows["segment"].append(s)
            rows["speed_rpm"].append(info.speed_rpm)
            rows["i_qo"].append(float(seg.i_qo[s]))
            rows["M"].append(ph[j, 0])
            rows["se_M"].append(se[j, 0])
            rows["Iq"].append(ph[j, 1])
            rows["se_Iq"].append(se[j, 1])
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    used = set(mi.capture_of_segment)
    skipped = tuple(f"{c.source}: no steady segment of a whole electrical revolution after {settle_s:g} s settling"
                    for i, c in enumerate(mi.captures) if i not in used)
    # the files as given (their windows are named file#k)
    return SweepPoints(mi.serial, list(dict.fromkeys(c.source for c in captures)), kt, **arrays, skipped=skipped)
