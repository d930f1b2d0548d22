"""Calibrate the identification margin's switch (issue 34, item 6): end of line writes
``MECH_COMP_ENABLE`` when the predicted margin (``eol_cal.analysis.fingerprint.predicted_margin``)
reaches a threshold; this bench finds the threshold from the firmware twin's own identification.

Encoders drawn with production pitch errors scaled 0.1-1x of nominal (``draw_sensor_errors``,
``edge_sigma_mech_deg`` = 0.1 x scale), their true fingerprint in the block; per encoder, power-ups
at 300 rpm (the speed with the fewest ticks per pitch: the hardest) in either direction from a
random angle with 0.002 mechanical degrees of timing noise a tick, 1.2 s each (six revolutions; the
identification needs three); ``eol_cal.firmware.mech_sim`` (estimator and identifier in JAX, one
background slice a tick). An encoder is *right* when every power-up identified the true frame and
none applied a wrong one. The threshold is the least predicted margin above which every encoder
was right and the pooled power-ups reach 99.9 % right.

    python bench/bench_mech_margin.py [--encoders 32] [--per-encoder 128]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

SCALES = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.7, 1.0)


def run(encoders: int, per_encoder: int) -> list[tuple[float, float, float, int, int, int]]:
    """(scale, predicted margin, predicted cosine, right, of, wrong frames) per encoder."""
    from eol_cal.analysis.fingerprint import predicted_margin
    from eol_cal.firmware.kinematics import draw_sensor_errors, fingerprint_of
    from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, unused_mech
    from eol_cal.firmware.mech_sim import PowerUp, simulate_powerups

    N, P = 64, 6
    rows = []
    for s in SCALES:
        t0 = time.perf_counter()
        pus, preds = [], []
        for e in range(encoders):
            err = draw_sensor_errors(np.random.default_rng(90_000 + e), N, edge_sigma_mech_deg=0.1 * s)
            fp, gp = fingerprint_of(err, P)
            mech = unused_mech(N).replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=gp, fingerprint=fp)
            preds.append(predicted_margin(np.asarray(fp), np.zeros(2 * N), FP_FORWARD | FP_REVERSE, P, N, 20000.0))
            rng = np.random.default_rng(1000 * e + int(100 * s))
            pus += [PowerUp(err, mech, float(rng.uniform(0, 2 * math.pi)), float(rng.choice([-1.0, 1.0]) * 300.0),
                            jitter_deg=0.002) for _ in range(per_encoder)]
        res = simulate_powerups(pus, 1.2, seed=int(100 * s))
        ok = (np.isfinite(res.first_id_s) & (res.r_first == res.truth) & (res.wrong_ticks == 0)).reshape(encoders, -1)
        wrong = (res.wrong_ticks > 0).reshape(encoders, -1)
        for e in range(encoders):
            rows.append((s, preds[e][1], preds[e][0], int(ok[e].sum()), per_encoder, int(wrong[e].sum())))
        print(f"scale {s:4.2f}: predicted margin min {min(p[1] for p in preds):6.3f} median "
              f"{np.median([p[1] for p in preds]):6.3f}; right {int(ok.sum())}/{ok.size}, encoders all right "
              f"{int(ok.all(axis=1).sum())}/{encoders}, wrong frames applied {int(wrong.sum())} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return rows


def threshold(rows: list[tuple[float, float, float, int, int, int]], target: float = 0.999
              ) -> tuple[float, int, int, int]:
    """The least predicted margin T such that every encoder at or above it was right on every
    power-up and the pooled rate is at least ``target``: (T, encoders, power-ups right, power-ups)."""
    cands = sorted({r[1] for r in rows})
    best = (math.inf, 0, 0, 0)
    for t in reversed(cands):
        above = [r for r in rows if r[1] >= t]
        n_ok, n = sum(r[3] for r in above), sum(r[4] for r in above)
        if all(r[3] == r[4] for r in above) and n_ok >= target * n:
            best = (t, len(above), n_ok, n)
        else:
            break
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--encoders", type=int, default=32, help="encoders per pitch-error scale")
    ap.add_argument("--per-encoder", type=int, default=128, help="power-ups per encoder")
    ap.add_argument("--json", help="write the per-encoder rows here")
    args = ap.parse_args()
    rows = run(args.encoders, args.per_encoder)
    t, n_enc, n_ok, n = threshold(rows)
    below = [r for r in rows if r[1] < t]
    print(f"\nthreshold on the predicted margin: {t:.3f} ({n_enc} encoders at or above it, {n_ok}/{n} power-ups "
          f"right); below it {len(below)} encoders, {sum(r[3] for r in below)}/{sum(r[4] for r in below)} right")
    print(f"  predicted cosine of the encoders at or above it: min {min(r[2] for r in rows if r[1] >= t):.3f}; "
          f"the largest predicted margin of an encoder not right on every power-up: "
          f"{max((r[1] for r in rows if r[3] < r[4]), default=math.nan):.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows))
    for s in SCALES:
        sel = [r for r in rows if r[0] == s]
        on = sum(r[1] >= t for r in sel)
        print(f"  scale {s:4.2f}: compensation on for {on}/{len(sel)} encoders")


if __name__ == "__main__":
    main()
