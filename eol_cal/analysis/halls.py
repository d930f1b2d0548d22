"""Where each hall boundary sits: the block's ``hall_angle`` table measured per motor.

The firmware anchors its angle at every hall transition on ``hall_angle[s-1]`` (contract
section 2: where state s begins in forward rotation). With the nominal table each boundary's
mounting error (about 2/3 electrical degree, sigma, on the plant) makes the ECU's angle jump at
the transition and tilts the speed it extrapolates with: a 6th-periodic error pattern that the
compensation table, evaluated at that angle, turns into residual ripple. The offline angle
(encoder edges between the transitions, :mod:`eol_cal.analysis.angle`) shows where each
boundary actually is; its circular mean over all transitions of the motor is the calibrated
table, in the offline (hall-mean) frame. A boundary is one hall sensor's switching point, the
same in both directions (the plant's sensor model has no hysteresis; a real sensor's would show
as a larger ``scatter``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE
from eol_cal.numerics.wrap import wrap_2pi, wrap_pi

@dataclass(frozen=True)
class HallAngles:
    """A motor's hall table and how it was found.

    Attributes
    ----------
    hall_angle : tuple of 6 float
        Angle where state s begins in forward rotation, entry s-1 (rad, electrical, [0, 2*pi)).
    source : str
        ``measured``, or ``nominal`` with the reason the measurement was not used.
    n_transitions : tuple of 6 int
        Transitions of each boundary averaged.
    deviation_rad : tuple of 6 float
        Measured minus nominal (rad, wrapped to (-pi, pi]); 0 for ``nominal``.
    scatter_rad : tuple of 6 float
        RMS of the single transitions about their boundary's mean (rad): encoder placement
        errors under the interpolated angle, sampling, hysteresis.
    """

    hall_angle: tuple[float, ...]
    source: str
    n_transitions: tuple[int, ...]
    deviation_rad: tuple[float, ...]
    scatter_rad: tuple[float, ...]

    def to_dict(self) -> dict:
        """The result record's ``hall_angle`` entry (``docs/json.md``)."""
        return {
            "value": list(self.hall_angle),
            "source": self.source,
            "n_transitions": list(self.n_transitions),
            "deviation_deg": [math.degrees(d) for d in self.deviation_rad],
            "scatter_deg": [math.degrees(d) for d in self.scatter_rad],
        }


def nominal_hall_angles(reason: str, n_transitions: Sequence[int] = (0,) * 6) -> HallAngles:
    """The contract's nominal table, with the reason it is used."""
    return HallAngles(tuple(float(a) for a in NOMINAL_HALL_ANGLE), f"nominal ({reason})",
                      tuple(int(n) for n in n_transitions), (0.0,) * 6, (0.0,) * 6)


def measure_hall_angles(
    begins: Sequence[np.ndarray],
    theta: Sequence[np.ndarray],
    min_transitions: int = 3,
    max_deviation_rad: float = math.radians(15.0),
) -> HallAngles:
    """The hall table from a motor's transitions.

    Parameters
    ----------
    begins : sequence of int arrays
        Per capture window, the boundary of each transition (state that begins there in forward
        rotation, 1..6; :attr:`eol_cal.analysis.angle.AngleResult.hall_begins`).
    theta : sequence of arrays
        The reconstructed angle at those transitions (rad; ``AngleResult.hall_theta``). All
        windows must be in one frame (every window's frame is the mean of its hall transitions,
        so they are, up to the hall errors' weighting).
    min_transitions : int
        Fewest transitions per boundary for a measured entry.
    max_deviation_rad : float
        A boundary further than this from nominal is taken as a wiring or mounting fault, not a
        tolerance (rad).

    Returns
    -------
    HallAngles
        ``measured``, or ``nominal`` with the reason (too few transitions, a boundary too far).
    """
    b = np.concatenate([np.asarray(x, dtype=np.int64) for x in begins]) if len(begins) else np.zeros(0, np.int64)
    th = np.concatenate([np.asarray(x, dtype=float) for x in theta]) if len(theta) else np.zeros(0)
    counts, table, dev, scatter = [], [], [], []
    for s in range(1, 7):
        d = th[b == s] - NOMINAL_HALL_ANGLE[s - 1]
        counts.append(int(d.size))
        if d.size == 0:
            table.append(float("nan"))
            dev.append(float("nan"))
            scatter.append(float("nan"))
            continue
        mean = float(np.angle(np.mean(np.exp(1j * d))))
        resid = wrap_pi(d - mean)
        dev.append(mean)
        scatter.append(float(np.sqrt(np.mean(resid**2))))
        table.append(float(wrap_2pi(NOMINAL_HALL_ANGLE[s - 1] + mean)))
    if min(counts) < min_transitions:
        return nominal_hall_angles(f"boundary of state {counts.index(min(counts)) + 1} crossed {min(counts)} "
                                   f"times, fewer than {min_transitions}", counts)
    worst = int(np.argmax(np.abs(dev)))
    if abs(dev[worst]) > max_deviation_rad:
        return nominal_hall_angles(f"boundary of state {worst + 1} measured {math.degrees(dev[worst]):+.1f} deg "
                                   f"from nominal, more than {math.degrees(max_deviation_rad):.0f} deg", counts)
    return HallAngles(tuple(table), "measured", tuple(counts), tuple(dev), tuple(scatter))
