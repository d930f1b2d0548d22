"""Analytic motion for the analysis tests: encoder and hall levels from a known angle."""

from __future__ import annotations

import numpy as np

from eol_cal.capture.data import Capture

TWO_PI = 2.0 * np.pi


def levels_from_angle(theta_m, poles=6, N_enc=64, phi_enc=0.0, hall_err_deg=None):
    """Encoder A/B and hall levels for a mechanical angle theta_m (rad).

    A is high for the first half of each pitch starting at phi_enc (mech rad); B lags A by a
    quarter pitch (A leads in forward rotation). hall_err_deg: optional 6 per-boundary
    placement errors (electrical deg) of the hall transitions at 0, 60, ... 300 deg.
    """
    pitch = TWO_PI / N_enc
    frac_a = np.mod((theta_m - phi_enc) / pitch, 1.0)
    a = (frac_a < 0.5).astype(np.int8)
    frac_b = np.mod((theta_m - phi_enc - pitch / 4) / pitch, 1.0)
    b = (frac_b < 0.5).astype(np.int8)
    theta_e = np.mod(poles / 2 * theta_m, TWO_PI)
    bounds = np.deg2rad(np.arange(6) * 60.0)
    if hall_err_deg is not None:
        bounds = bounds + np.deg2rad(np.asarray(hall_err_deg))
    # sector k spans [bounds[k], bounds[k+1]); states in forward order 5 1 3 2 6 4
    seq = np.array([5, 1, 3, 2, 6, 4])
    sector = np.searchsorted(np.mod(bounds, TWO_PI), theta_e, side="right") - 1
    order = np.argsort(np.mod(bounds, TWO_PI))
    hall = seq[order][np.mod(sector, 6)]
    return a, b, hall.astype(np.int8)


def motion_capture(t, theta_m, torque=None, poles=6, N_enc=64, phi_enc=0.0, iq_ref=65.0, with_b=True,
                   hall_err_deg=None):
    a, b, hall = levels_from_angle(theta_m, poles, N_enc, phi_enc, hall_err_deg)
    ch = {"enc_a": a, "hall": hall}
    if with_b:
        ch["enc_b"] = b
    if torque is not None:
        ch["torque"] = np.asarray(torque, dtype=float)
    return Capture(t=np.asarray(t, dtype=float), channels=ch,
                   metadata={"serial": "T-1", "poles": poles, "encoder_ppr": N_enc, "iq_ref": iq_ref})
