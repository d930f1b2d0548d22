"""The firmware's identification of the rotor's mechanical angle (contract revision 1.2) over the
plant's production spread: how separable the hypotheses are, how fast and how reliably the
identifier finds the frame after power-up, and what simulating it costs.

1. Separability, noise-free, per motor (true fingerprint, drawn as the plant draws it): the
   cosine margin of the true offset over the best wrong one when the fingerprint alone must pick
   among all N rotations (no halls: the alternative), and among the P/2 hypotheses the halls allow
   (what the firmware does); the hall fraction of the wrong pole pairs; the margin end of line
   predicts after one revolution at 300 rpm.
2. Power-ups (``eol_cal.firmware.mech_sim``: the kinematic sensors, the estimator and the
   identifier in JAX, vmapped) per speed band from 30 to 300 rpm, both directions, random start:
   identified, revolutions to identification, wrong frames applied, the firmware's own margin.
3. Cost: power-ups per second batched in JAX against the numpy reference (``mech_run.run_mech``,
   the golden vectors' tick-by-tick code) on the same power-up.

    python bench/bench_mech_id.py [--motors 1000] [--per-band 200]
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motors", type=int, default=1000, help="motors for the separability figures")
    ap.add_argument("--per-band", type=int, default=200, help="power-ups per speed band")
    args = ap.parse_args()

    from eol_cal.analysis.fingerprint import pitch_errors, predicted_margin
    from eol_cal.firmware.kinematics import draw_sensor_errors, fingerprint_of
    from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, unused_mech
    from eol_cal.firmware.mech_sim import PowerUp, simulate_powerups

    print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    P, N = 6, 64
    delta = P * math.pi / N
    lags_pp = [L for L in range(1, N) if abs(math.remainder(L * delta, 2 * math.pi)) < delta]
    m_all, m_pp, m_pred, frac = [], [], [], []
    for s in range(args.motors):
        err = draw_sensor_errors(np.random.default_rng(10_000 + s), N)
        fp, _ = fingerprint_of(err, P)
        x = pitch_errors(fp, N)[0::2]
        auto = np.array([x @ np.roll(x, -L) for L in range(N)]) / (x @ x)
        m_all.append(1.0 - auto[1:].max())
        m_pp.append(1.0 - max(0.0, max(auto[L] for L in lags_pp)))
        m_pred.append(predicted_margin(fp, np.zeros(2 * N), 3, P, N, 20000.0)[1])
        frac += [abs(math.degrees(math.remainder(L * delta, 2 * math.pi))) for L in lags_pp]
    q = lambda v: " / ".join(f"{x:.3f}" for x in np.percentile(v, [0, 1, 5, 50]))  # noqa: E731
    print(f"\n1. separability over {args.motors} motors of the plant's spread (min / p1 / p5 / median):")
    print(f"   fingerprint alone, all {N} rotations:      margin {q(m_all)}")
    print(f"   halls + fingerprint, {P // 2} hypotheses:         margin {q(m_pp)}")
    print(f"   predicted by end of line (1 rev at 300 rpm): margin {q(m_pred)}; "
          f"below 0.25: {int((np.array(m_pred) < 0.25).sum())}")
    print(f"   hall fraction of the wrong pole pairs' offsets: {min(frac):.2f} deg electrical at least "
          f"(identified frames agree within the 2 deg tolerance)")

    print(f"\n2. power-ups, {args.per_band} per band (half with 0.002 deg timing noise, both directions):")
    print(f"{'band rpm':>12} {'identified':>11} {'revs median':>12} {'max':>6} {'wrong':>6} {'margin min':>11} "
          f"{'median':>7} {'wall s':>7} {'power-ups/s':>12} {'ticks/s':>12}")
    rng = np.random.default_rng(22)
    bands = [(30, 50), (50, 100), (100, 200), (200, 300)]
    for lo, hi in bands:
        pus = []
        for i in range(args.per_band):
            err = draw_sensor_errors(np.random.default_rng(50_000 + 1000 * lo + i), N)
            fp, gp = fingerprint_of(err, P)
            mech = unused_mech(N).replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=gp, fingerprint=fp)
            rpm = rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi)
            pus.append(PowerUp(err, mech, float(rng.uniform(0, 2 * math.pi)), float(rpm),
                               jitter_deg=0.002 if i % 2 else 0.0))
        secs = 5.0 * 60.0 / lo
        t0 = time.perf_counter()
        res = simulate_powerups(pus, secs, seed=lo)
        wall = time.perf_counter() - t0
        revs = res.first_id_s * np.abs([p.rpm0 for p in pus]) / 60.0
        ok = np.isfinite(res.first_id_s) & (res.r_first == res.truth)
        print(f"{lo:>5}-{hi:<6} {int(ok.sum()):>5}/{len(pus):<5} {np.nanmedian(revs):>12.2f} {np.nanmax(revs):>6.2f} "
              f"{int((res.wrong_ticks > 0).sum()):>6} {res.margin.min():>11.3f} {np.median(res.margin):>7.3f} "
              f"{wall:>7.1f} {len(pus) / wall:>12.1f} {len(pus) * secs * 20000.0 / wall:>12,.0f}")

    print("\n3. one power-up at 300 rpm for 0.7 s (14 000 ticks): numpy reference against the JAX batch")
    from eol_cal.firmware import mech_golden as G
    from eol_cal.firmware.mech_run import run_mech

    sc = G.SCENARIOS["mech_pole_pair_0.csv"]
    a, b, h = sc.signals()
    t0 = time.perf_counter()
    run_mech(G.golden_block("mech_a"), a, b, h, G.I_QO)
    t_np = time.perf_counter() - t0
    print(f"   numpy reference: {t_np:.2f} s, {len(a) / t_np:,.0f} ticks/s (the batches above: their ticks/s column, "
          "compile included)")


if __name__ == "__main__":
    main()
