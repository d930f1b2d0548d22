"""Ripple figures of one capture at the operating point, for the station's before/after verdict.

:func:`point_ripple` measures one steady window; :func:`nearest_segment` and
:func:`verify_segments` pick the window and the profile segments at the fit's operating point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.analysis.metrics import ripple_pp
from eol_cal.analysis.spectrum import order_spectrum
from eol_cal.infra.jsonsafe import json_safe

if TYPE_CHECKING:
    from eol_cal.analysis.angle import AngleResult
    from eol_cal.capture.data import Capture


@dataclass(frozen=True)
class PointRipple:
    """Ripple of one capture at the operating point.

    Attributes
    ----------
    pp_pct : float
        Filtered p-p ripple (%), median over the steady windows (``docs/metrics.md``).
    pp_raw_pct : float
        Despiked, unfiltered p-p ripple (%).
    pp_nm : float
        Filtered p-p (N*m).
    T_avg_nm : float
        Mean torque (N*m).
    amp6_nm : float
        6th-order amplitude of the order spectrum (N*m).
    span_s : (float, float)
        The capture's time span that was analysed (s).
    pp_no_mech1_pct : float
        ``pp_pct`` with the mechanical order 1 taken out (%): what the 6th-harmonic tables can act on.
    mech1_nm : float
        Amplitude of the mechanical order 1 (N*m; the order spectrum's): the rotor's unbalance,
        which only a layout-2 block's mechanical compensation (contract revision 1.2) cancels.
    """

    pp_pct: float
    pp_raw_pct: float
    pp_nm: float
    T_avg_nm: float
    amp6_nm: float
    span_s: tuple[float, float]
    ripple: Any = None
    spectrum: Any = None
    t: Any = None
    torque: Any = None
    poles: int = 0
    pp_no_mech1_pct: float = float("nan")
    mech1_nm: float = float("nan")
    theta_r: Any = None  # electrical angle per sample (rad), for the report's torque against angle

    def to_dict(self) -> dict[str, Any]:
        return json_safe({"pp_pct": self.pp_pct, "pp_raw_pct": self.pp_raw_pct, "pp_nm": self.pp_nm,
                           "pp_no_mech1_pct": self.pp_no_mech1_pct, "mech1_nm": self.mech1_nm,
                           "T_avg_nm": self.T_avg_nm, "amp6_nm": self.amp6_nm, "span_s": list(self.span_s)})


def nearest_segment(pieces: list[Capture], speed_rpm: float, i_qo_a: float) -> int:
    """Index of the piece whose mean speed (rpm) and i_qo (A) are nearest the operating point."""
    def distance(c: Capture) -> float:
        iq = float(np.mean(c.iq_ref()))
        rpm = float(np.mean(c["speed"])) if c.has("speed") else speed_rpm
        return abs(iq - i_qo_a) / max(abs(i_qo_a), 1.0) + abs(rpm - speed_rpm) / max(abs(speed_rpm), 1.0)

    return min(range(len(pieces)), key=lambda k: distance(pieces[k]))


def point_ripple(capture: Capture, angle: AngleResult) -> PointRipple:
    """p-p ripple and 6th-order amplitude of one steady capture (the operating point's window).

    Parameters
    ----------
    capture : Capture
        One window of a dyno capture (:func:`eol_cal.capture.windows.split_windows`).
    angle : AngleResult
        Its reconstructed angle.
    """
    t, torque, theta = capture.t, np.asarray(capture["torque"], float), angle.theta_r
    rp = ripple_pp(t, torque, theta, poles=capture.poles, i_qo=np.asarray(capture.iq_ref(), float),
                   source=capture.source)
    sp = order_spectrum(theta, torque, capture.poles, t=t, source=capture.source)
    return PointRipple(rp.filtered_pct, rp.raw_pct, rp.filtered_pp_nm, rp.T_avg_nm, float(sp.amplitude(6)),
                       (float(t[0]), float(t[-1])), rp, sp, t, torque, capture.poles,
                       pp_no_mech1_pct=rp.no_mech1_pct, mech1_nm=float(sp.mech1_amplitude_nm), theta_r=theta)


def verify_segments(segments: list, speed_rpm: float, i_qo_a: float, rel_tol: float = 0.02) -> list:
    """The profile segments at the operating point, in either direction.

    Parameters
    ----------
    segments : list of DynoSetpoint
        The test profile as the dyno runs it.
    speed_rpm, i_qo_a : float
        Operating point: speed (rpm) and nominal q current (A); matched by magnitude within
        ``rel_tol``, so the reverse point of the same magnitude is verified too.

    Returns
    -------
    list of DynoSetpoint
        In profile order; the whole profile when no segment gives the load as i_qo or none matches.
    """
    def near(a: float, b: float) -> bool:
        return abs(abs(a) - abs(b)) <= rel_tol * max(abs(b), 1e-9)

    out = [s for s in segments if s.iq is not None and near(s.speed_rpm, speed_rpm) and near(s.iq, i_qo_a)]
    return out or list(segments)
