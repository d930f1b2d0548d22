"""A test profile as the dyno runs it: one :class:`DynoSetpoint` per profile segment, and how long
the shaft turns for them (:func:`physical_seconds`: ramps, captures, lead-in and stop, as
:func:`eol_cal.dyno.profile_run.run_profile` commands them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

from eol_cal.dyno import registers as rm
from eol_cal.dyno.registers import SPEED_TOL_REL, SPEED_TOL_RPM, DutCmdKind
from eol_cal.plant.profile import Profile

#: capture rate (Hz) when the profile gives none
DEFAULT_RATE_HZ = 10000


@dataclass(frozen=True)
class DynoSetpoint:
    """One steady operating point of a test profile (one profile segment), as the dyno runs it.

    Attributes
    ----------
    speed_rpm : float
        Shaft speed (rpm), signed: negative runs in reverse.
    seconds : float
        Capture duration at this point (s).
    torque_nm : float or None
        Load as shaft torque command (N*m) ...
    iq : float or None
        ... or as nominal q current i_qo (A); exactly one of the two is given.
    ramp_rpm_s : float
        Speed ramp rate to reach this point (rpm/s).
    """

    speed_rpm: float
    seconds: float
    torque_nm: float | None = None
    iq: float | None = None
    ramp_rpm_s: float = 1000.0

    def command(self) -> tuple[DutCmdKind, float]:
        """(kind, value) of the load command: torque (N*m) or i_qo (A)."""
        if self.iq is not None:
            return DutCmdKind.IQ, float(self.iq)
        return DutCmdKind.TORQUE, float(self.torque_nm or 0.0)


#: ramp rate (rpm/s) for a segment that gives no ramp time (a step on the plant)
DEFAULT_RAMP_RPM_S = 1000.0


def setpoints_from_profile(profile: Profile) -> list[DynoSetpoint]:
    """A test profile (:class:`eol_cal.plant.profile.Profile`) as the dyno's set points, one per
    profile segment.

    The dyno captures only the steady part of a segment: ``seconds - ramp_s``; the ramp rate is
    the speed change over ``ramp_s`` (or :data:`DEFAULT_RAMP_RPM_S` without a ramp time).
    """
    out: list[DynoSetpoint] = []
    prev = 0.0
    for seg in profile.segments:
        delta = abs(seg.speed_rpm - prev)
        ramp = delta / seg.ramp_s if seg.ramp_s > 0.0 and delta > 0.0 else DEFAULT_RAMP_RPM_S
        out.append(DynoSetpoint(seg.speed_rpm, seg.seconds - seg.ramp_s, seg.torque_nm, seg.iq, ramp))
        prev = seg.speed_rpm
    return out


def physical_seconds(segments: Sequence[DynoSetpoint], rate_hz: int = DEFAULT_RATE_HZ, lead_in_s: float = 0.0,
                     lead_in_point: DynoSetpoint | None = None) -> float:
    """How long the shaft must turn for ``segments`` (s), from standstill back to standstill: what
    no tool can take off a station's cycle.

    Each segment's ramp at its rate until the dyno reports at speed (within its tolerance), a
    reversal's stop at the previous ramp rate first, the capture's ``round(seconds * rate_hz)``
    samples (the first segment's ``lead_in_samples(lead_in_s, rate_hz)`` more; a
    ``lead_in_point`` first, with its :func:`lead_point_samples`), and the stop at the end, as
    :func:`~eol_cal.dyno.profile_run.run_profile` commands them.
    """
    points = [(lead_in_point, lead_point_samples(lead_in_point, rate_hz))] if lead_in_point and segments else []
    points += [(seg, int(round(seg.seconds * rate_hz))) for seg in segments]
    total, speed, ramp = 0.0, 0.0, DEFAULT_RAMP_RPM_S
    for seg, n in points:
        if abs(speed) > rm.STANDSTILL_RPM and (seg.speed_rpm < 0) != (speed < 0):
            total += (abs(speed) - rm.STANDSTILL_RPM) / ramp
            speed = math.copysign(rm.STANDSTILL_RPM, speed)
        ramp = seg.ramp_rpm_s
        tol = max(SPEED_TOL_RPM, SPEED_TOL_REL * abs(seg.speed_rpm))
        total += max(0.0, abs(seg.speed_rpm - speed) - tol) / ramp
        total += n / rate_hz
        speed = seg.speed_rpm
    total += lead_in_samples(lead_in_s, rate_hz) / rate_hz if segments else 0.0
    return total + max(0.0, abs(speed) - rm.STANDSTILL_RPM) / ramp


def lead_in_samples(lead_in_s: float, rate_hz: float) -> int:
    """Samples of a lead-in of ``lead_in_s`` (s) at ``rate_hz`` (Hz): captured and never read."""
    return int(math.ceil(max(0.0, lead_in_s) * rate_hz - 1e-9))


def lead_point_samples(point: DynoSetpoint, rate_hz: float) -> int:
    """Samples the dyno captures at a lead-in point (:func:`~eol_cal.dyno.profile_run.run_profile`): its ``seconds`` and the one
    sample read to close the capture (a capture reads at least one)."""
    return lead_in_samples(point.seconds, rate_hz) + 1
