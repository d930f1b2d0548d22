"""Firmware frame offset over captures of different lengths: one compiled scan vs one per length.

``eol-cal fit`` runs the firmware estimator over every capture window to place the phases in the
firmware's angle frame (:func:`eol_cal.analysis.firmware_angle.firmware_frame_offset`). Here: the
windows of the ``eol-default`` profile (seven lengths, 10 kHz), run cold in a fresh process,
then again warm; side by side with what a user would write, ``estimator.run_jax`` per window.

    python bench/bench_frame_offset.py            # both, each in its own process
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np

#: eol-default window lengths at 10 kHz (s), ramps of 0.1 s cut: 1.2, 1.1, 1.1, 0.7 ...
SECONDS = (1.2, 1.1, 1.1, 0.7, 0.7, 0.7, 1.2, 1.1, 1.1, 0.7)


def windows():
    from eol_cal.capture.synthetic import synthetic_capture

    return [synthetic_capture(rpm=60.0 if s > 1 else 120.0, i_qo=40.0, seconds=s, fs=10000.0, seed=k)
            for k, s in enumerate(SECONDS)]


def run(which: str) -> None:
    from eol_cal.analysis.firmware_angle import firmware_frame_offset
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.firmware import estimator as est

    caps = windows()
    angles = [capture_angle(c) for c in caps]

    def per_window_run_jax(c, th):
        cfg = est.EstimatorConfig.paper(poles=c.poles, N_enc=c.encoder_ppr, tick_hz=c.sample_rate)
        out = est.run_jax(cfg, c["enc_a"], c["enc_b"], c["hall"])
        np.asarray(out.theta_hat)

    def chunked(c, th):
        firmware_frame_offset(c, th, [(0, len(c.t))])

    f = per_window_run_jax if which == "run_jax" else chunked
    for label in ("cold", "warm"):
        t0 = time.perf_counter()
        for c, a in zip(caps, angles, strict=True):
            f(c, a.theta_r)
        dt = time.perf_counter() - t0
        print(f"{which:>12} {label}: {dt:6.2f} s for {len(caps)} windows ({len(set(len(c.t) for c in caps))} lengths, "
              f"{sum(len(c.t) for c in caps)} samples)")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        run(sys.argv[1])
    else:
        for which in ("run_jax", "chunked"):
            subprocess.run([sys.executable, __file__, which], check=True)
