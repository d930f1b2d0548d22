"""Peak-to-peak ripple %: our steady-window definition against what a user would compute.

Signal: 3.2 N*m at 60 rpm (the paper's operating point), 6th harmonic 0.05 N*m and 12th
0.01 N*m (true p-p of the noise-free torque known on a fine grid), white transducer noise of
standard deviation sigma, and 5 single-sample spikes of +-0.3 N*m per second; 3 s at 20 kHz,
20 noise seeds per row. Angle: reconstructed from the encoder and halls of the analytic capture.

Compared, each over the same record:
- naive: (max - min) / mean of the whole record,
- percentile: (P99.9 - P0.1) / mean of the whole record,
- ours raw and ours filtered (``eol_cal.analysis.metrics.ripple_pp``, docs/metrics.md).

Printed: mean error against the true p-p (percentage points) and its spread over seeds, and the
time per capture.

    python bench/bench_ripple_pp.py
"""

from __future__ import annotations

import time

import numpy as np

from eol_cal.analysis.angle import capture_angle
from eol_cal.analysis.metrics import ripple_pp
from eol_cal.capture.synthetic import synthetic_capture

SECONDS, FS, T_AVG = 3.0, 20000.0, 3.2


def main() -> None:
    cap = synthetic_capture(rpm=60.0, seconds=SECONDS, fs=FS, noise=0.0, torque_lsb=0.0, theta_r0=0.3)
    angle = capture_angle(cap)
    theta, t = angle.theta_r, cap.t
    clean = T_AVG + 0.05 * np.sin(6 * theta + 0.4) + 0.01 * np.sin(12 * theta - 1.0)
    fine = np.linspace(0, 2 * np.pi, 200001)
    ref = 0.05 * np.sin(6 * fine + 0.4) + 0.01 * np.sin(12 * fine - 1.0)
    true_pct = 100 * (ref.max() - ref.min()) / T_AVG
    print(f"true p-p {true_pct:.3f} %  (3 s, 60 rpm, 20 kHz; error = estimate - true, percentage points)")
    print(f"{'noise sigma N*m':>15s} {'method':14s} {'mean err':>9s} {'std':>7s} {'ms/capture':>11s}")
    rng = np.random.default_rng(0)
    for sigma in (0.0, 0.002, 0.005, 0.01):
        results: dict[str, list[float]] = {"naive": [], "percentile": [], "ours raw": [], "ours filtered": []}
        times: dict[str, float] = {k: 0.0 for k in results}
        for _ in range(20):
            x = clean + sigma * rng.standard_normal(len(t))
            idx = rng.choice(len(t), int(5 * SECONDS), replace=False)
            x[idx] += rng.choice([-0.3, 0.3], len(idx))
            t0 = time.perf_counter()
            results["naive"].append(100 * (x.max() - x.min()) / x.mean())
            times["naive"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            lo, hi = np.percentile(x, [0.1, 99.9])
            results["percentile"].append(100 * (hi - lo) / x.mean())
            times["percentile"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            r = ripple_pp(t, x, theta, poles=6, i_qo=cap.iq_ref())
            dt = time.perf_counter() - t0
            times["ours raw"] += dt
            times["ours filtered"] += dt
            results["ours raw"].append(r.raw_pct)
            results["ours filtered"].append(r.filtered_pct)
        for name, vals in results.items():
            err = np.asarray(vals) - true_pct
            print(f"{sigma:15.3f} {name:14s} {err.mean():9.3f} {err.std():7.3f} {1e3 * times[name] / 20:11.2f}")


if __name__ == "__main__":
    main()
