"""Offline angle reconstruction against the angles a user would otherwise take.

Side by side on the same sampled encoder/hall signals (6 poles, 64 PPR, 20 kHz):

- raw encoder angle (the firmware's ``theta_enc``: angle of the last A edge, seed eq. 8),
- the firmware's causal estimator (seed eqs. 13-16, ``EstimatorConfig.paper``) and with its
  four options (``EstimatorConfig.best``, block flags bits 2-5 all set; three before contract revision 1.1),
- offline linear interpolation between the same edges (``np.interp``),
- offline PCHIP (``eol_cal.analysis.angle``, this product).

Figures: electrical angle error RMS / max (deg) after 0.3 s, and the 6th harmonic of a unit
test torque ``cos(6*theta_true)`` measured through each angle (phase error, deg; amplitude
ratio), which is what the ripple fit inherits; and the run time per second of capture.

    python bench/bench_angle.py
"""

from __future__ import annotations

import time

import numpy as np

from eol_cal.analysis.angle import reconstruct_angle
from eol_cal.numerics.wrap import wrap_pi
from eol_cal.analysis.spectrum import order_spectrum
from eol_cal.firmware import estimator as est
from eol_cal.firmware.kinematics import draw_sensor_errors, encoder_hall_signals, ideal_sensor_errors

P, N_ENC, FS, SECONDS = 6, 64, 20000.0, 1.5
T = np.arange(0.0, SECONDS, 1.0 / FS)


def motions() -> dict[str, np.ndarray]:
    """Mechanical angle (rad) per sample of each test motion."""
    w60 = 2 * np.pi * 1.0
    theta_e60 = P / 2 * w60 * T
    return {
        "60 rpm": w60 * T + 0.4,
        "ramp 30->85 rpm": 2 * np.pi * (0.5 * T + 0.5 * (55 / 60 / SECONDS) * T**2) + 0.4,
        # 5 % speed ripple at the 6th electrical harmonic (what torque ripple does to a soft shaft)
        "60 rpm +-5% @6th": w60 * T + 0.05 * w60 / (6 * P / 2 * w60) * np.sin(6 * theta_e60) + 0.4,
    }


def sixth(theta: np.ndarray, theta_true: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Phase error (deg) and amplitude ratio of cos(6*theta_true) analysed against ``theta``."""
    # unwrap on the true angle's turns so that the analysis sees a continuous angle
    th = theta_true[mask] + wrap_pi(theta[mask] - theta_true[mask])
    # the firmware's binary32 angles step back by rounding; the order analysis needs one way
    th = np.maximum.accumulate(th)
    s = order_spectrum(th, np.cos(6 * theta_true[mask]), P)
    return float(np.rad2deg(wrap_pi(s.phase(6)))), s.amplitude(6)


def main() -> None:
    rng = np.random.default_rng(1)
    sensors = {"ideal sensors": ideal_sensor_errors(N_ENC, 0.013),
               "drawn errors": draw_sensor_errors(rng, N_ENC, grid_offset=0.013)}
    # warm up (scipy imports) so the first timing is not the import
    a0, _, h0 = encoder_hall_signals(motions()["60 rpm"][:8000], P, N_ENC)
    reconstruct_angle(T[:8000], a0, h0, P, N_ENC)
    print(f"{'motion':18s} {'sensors':14s} {'angle':22s} {'rms deg':>8s} {'max deg':>8s} "
          f"{'6th ph deg':>10s} {'6th amp':>8s} {'ms per s':>9s}")
    for mname, theta_m in motions().items():
        theta_true = P / 2 * theta_m
        for sname, errs in sensors.items():
            a, b, h = encoder_hall_signals(theta_m, P, N_ENC, errs)
            rows = {}
            # the firmware runs in the ECU: its (JAX) run time is not comparable, not shown
            fw = est.run_jax(est.EstimatorConfig.paper(), a, b, h)
            rows["raw encoder (fw)"] = (np.asarray(fw.theta_enc, float), None)
            rows["estimator paper (fw)"] = (np.asarray(fw.theta_hat, float), None)
            fwb = est.run_jax(est.EstimatorConfig.best(), a, b, h)
            rows["estimator best (fw)"] = (np.asarray(fwb.theta_hat, float), None)
            t0 = time.perf_counter()
            res = reconstruct_angle(T, a, h, P, N_ENC, enc_b=b)
            t_pchip = time.perf_counter() - t0
            t_u, idx = np.unique(res.t_edges, return_index=True)
            # judged after the firmware's start-up and inside the edge span (np.interp holds
            # the last value beyond it)
            mask = (T >= 0.3) & (T <= res.t_span[1])
            t0 = time.perf_counter()
            lin = np.interp(T, t_u, res.theta_edges[idx])
            rows["offline linear"] = (lin, t_pchip + time.perf_counter() - t0)
            rows["offline PCHIP (ours)"] = (res.theta_r, t_pchip)
            for aname, (theta, secs) in rows.items():
                err = np.rad2deg(wrap_pi(theta - theta_true))[mask]
                ph, amp = sixth(theta, theta_true, mask)
                ms = "-" if secs is None else f"{1e3 * secs / SECONDS:.1f}"
                print(f"{mname:18s} {sname:14s} {aname:22s} {np.sqrt(np.mean(err**2)):8.3f} "
                      f"{np.max(np.abs(err)):8.3f} {ph:10.3f} {amp:8.4f} {ms:>9s}")


if __name__ == "__main__":
    main()
