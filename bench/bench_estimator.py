"""Accuracy of the firmware's angle estimator on a kinematic motion model (issue 3 item 7).

A 6-pole motor with a 64 PPR encoder (edge placement error sigma 0.1 mechanical degree) and halls
within 2 electrical degrees (each switching point normal, sigma 2/3 deg, truncated at +-2 deg),
sampled at 20 kHz. For a batch of motors (one sensor-error draw each) it prints the RMS and the
maximum electrical-angle error of

  (a) the raw encoder angle (the last A edge's angle, what a user gets without the estimator),
  (b) the paper's estimator (eqs. 13-16),
  (c) each improvement alone and the combinations,

at constant 60 rpm and over a 30 -> 85 rpm ramp in 2 s. Both runs start with the estimator
running on the same motion (60 rpm for 4 s; 30 rpm for 4 s) and are scored after it: the
learned improvements need a few revolutions, the paper's method does not care.

    python bench/bench_estimator.py [--motors 16] [--hall-uniform]
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from eol_cal.firmware import estimator as est
from eol_cal.firmware.kinematics import (draw_sensor_errors, electrical_angle, encoder_hall_signals,
                                         speed_profile_angle)
from eol_cal.numerics.wrap import wrap_pi

TICK_HZ = 20000.0

CONFIGS = {
    "(b) paper": {},
    "(c1) clamp_to_next_edge": {"clamp_to_next_edge": True},
    "(c2) learn_grid_offset": {"learn_grid_offset": True},
    "(c3) accel_prediction": {"accel_prediction": True},
    "(c4) learn_pitch_errors": {"learn_pitch_errors": True},
    "(c2+c4) grid + pitch": {"learn_grid_offset": True, "learn_pitch_errors": True},
    "(c1+c2+c4) best": {"clamp_to_next_edge": True, "learn_grid_offset": True, "learn_pitch_errors": True},
    "(c1..c4) all": {"clamp_to_next_edge": True, "learn_grid_offset": True, "accel_prediction": True,
                     "learn_pitch_errors": True},
}

MOTIONS = {
    "60 rpm": (((4.0, 60.0, 60.0), (2.0, 60.0, 60.0)), 4.0),
    "30->85 rpm ramp in 2 s": (((4.0, 30.0, 30.0), (2.0, 30.0, 85.0)), 4.0),
}


def _errors(n: int, hall_uniform: bool) -> list:
    out = []
    for seed in range(n):
        rng = np.random.default_rng(seed)
        err = draw_sensor_errors(rng, 64)
        if hall_uniform:
            err = err._replace(hall_offset=np.radians(rng.uniform(-2.0, 2.0, (3, 2))))
        out.append(err)
    return out


def _err_deg(x: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.degrees(wrap_pi(np.asarray(x, np.float64) - truth))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motors", type=int, default=16, help="sensor-error draws (seeds 0..n-1)")
    ap.add_argument("--hall-uniform", action="store_true",
                    help="hall errors uniform in +-2 deg (worst case) instead of 3 sigma = 2 deg")
    args = ap.parse_args()
    errors = _errors(args.motors, args.hall_uniform)
    print(f"{args.motors} motors, 6 poles, 64 PPR, edge sigma 0.1 deg mech, halls "
          f"{'uniform +-2' if args.hall_uniform else 'sigma 0.67, max 2'} deg elec, 20 kHz")
    for motion, (segments, t_score) in MOTIONS.items():
        theta_m = speed_profile_angle(segments, TICK_HZ, 0.3)
        truth = electrical_angle(theta_m, 6)
        sig = [encoder_hall_signals(theta_m, 6, 64, e) for e in errors]
        a, b, h = (np.stack([s[i] for s in sig]) for i in range(3))
        score = slice(int(t_score * TICK_HZ), None)
        print(f"\n### {motion} (scored over {len(truth) - score.start} ticks after {t_score:g} s)\n")
        print("| angle | RMS deg (mean of motors) | RMS deg (worst motor) | max deg | mean deg |")
        print("|---|---:|---:|---:|---:|")
        raw_done = False
        for name, flags in CONFIGS.items():
            cfg = est.EstimatorConfig.paper(tick_hz=TICK_HZ, **flags)
            out = est.run_jax(cfg, a, b, h)
            rows = []
            if not raw_done:
                rows.append(("(a) raw encoder angle", np.asarray(out.theta_enc)))
                raw_done = True
            rows.append((name, np.asarray(out.theta_hat)))
            for label, x in rows:
                e = _err_deg(x, truth)[:, score]
                rms = np.sqrt(np.mean(e**2, axis=1))
                print(f"| {label} | {rms.mean():.3f} | {rms.max():.3f} | {np.abs(e).max():.2f} | "
                      f"{e.mean():+.3f} |")
        raw = _err_deg(np.asarray(est.run_jax(est.EstimatorConfig.paper(), a, b, h).theta_enc), truth)[:, score]
        print(f"\nraw encoder angle: standard deviation {raw.std(axis=1).mean():.2f} deg "
              f"(one pitch 16.875 deg / sqrt(12) = {16.875 / math.sqrt(12):.2f}), "
              f"mean {raw.mean():+.2f} deg (the staircase lags by half a pitch)")


if __name__ == "__main__":
    main()
