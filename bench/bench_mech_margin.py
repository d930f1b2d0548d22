"""Calibrate the identification switch (issue 34, item 6): end of line writes ``MECH_COMP_ENABLE``
when the predicted cosine and margin (``eol_cal.analysis.fingerprint.predicted_margin``) reach their
thresholds; this bench checks them against the firmware twin's own identification.

Encoders drawn with production pitch errors scaled 0.1-1x of nominal (``draw_sensor_errors``,
``edge_sigma_mech_deg`` = 0.1 x scale), their true fingerprint in the block; per encoder, power-ups
at 300 rpm (the speed with the fewest ticks per pitch: the hardest) in either direction from a
random angle with 0.002 mechanical degrees of timing noise a tick, 1.2 s each (six revolutions; the
identification needs three); ``eol_cal.firmware.mech_sim`` (estimator and identifier in JAX, one
background slice a tick). An encoder is *right* when every power-up identified the true frame and
none applied a wrong one. The threshold is the least predicted margin above which every encoder
was right and the pooled power-ups reach 99.9 % right.

``--end-to-end``: the switch as end of line decides it, on the fingerprint it fits. Plant motors
(the ``mech23`` production spread, the paper's bench) with their encoders' pitch errors scaled
0.1-1x of nominal run ``eol-default`` under the prepared block; ``eol-cal fit``'s library call
(``fit_motors``) fits them and ``block_from_result`` writes each one's layout-2 block (its fitted
fingerprint and grid phase, ``MECH_COMP_ENABLE`` as the fit decided). The same twin power-ups then
run on each motor's TRUE encoder with its block's FITTED fingerprint (the block's frame is the
capture's count frame: the truth the identifier must find is moved by the model pulse the capture
started on). Per motor: the switch, power-ups right, wrong frames applied.

    python bench/bench_mech_margin.py [--encoders 32] [--per-encoder 128]
    python bench/bench_mech_margin.py --end-to-end [--encoders 16] [--per-encoder 128] [--seed0 S]
        [--scales 0.2,0.3] [--json F] [--plot F] [--dump F]
    python bench/bench_mech_margin.py --end-to-end --rescore F.json F.pkl [--plot F]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from eol_cal.firmware.kinematics import SensorErrors
    from eol_cal.firmware.mech_params import MechParams

SCALES = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.7, 1.0)
#: the end-to-end run's pitch-error scales (x nominal)
E2E_SCALES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)
N_ENC, POLES = 64, 6


def run(encoders: int, per_encoder: int) -> list[tuple[float, float, float, int, int, int]]:
    """(scale, predicted margin, predicted cosine, right, of, wrong frames) per encoder."""
    from eol_cal.analysis.fingerprint import predicted_margin
    from eol_cal.firmware.kinematics import draw_sensor_errors, fingerprint_of
    from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, unused_mech
    from eol_cal.firmware.mech_sim import simulate_powerups
    from eol_cal.sim.mech_motors import SWITCH_SECONDS, switch_powerups

    N, P = N_ENC, POLES
    rows = []
    for s in SCALES:
        t0 = time.perf_counter()
        pus, preds = [], []
        for e in range(encoders):
            err = draw_sensor_errors(np.random.default_rng(90_000 + e), N, edge_sigma_mech_deg=0.1 * s)
            fp, gp = fingerprint_of(err, P)
            mech = unused_mech(N).replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=gp, fingerprint=fp)
            preds.append(predicted_margin(np.asarray(fp), np.zeros(2 * N), FP_FORWARD | FP_REVERSE, P, N, 20000.0))
            pus += switch_powerups(err, mech, per_encoder, np.random.default_rng(1000 * e + int(100 * s)))
        res = simulate_powerups(pus, SWITCH_SECONDS, seed=int(100 * s))
        ok = res.right.reshape(encoders, -1)
        wrong = (res.wrong_ticks > 0).reshape(encoders, -1)
        for e in range(encoders):
            rows.append((s, preds[e][1], preds[e][0], int(ok[e].sum()), per_encoder, int(wrong[e].sum())))
        print(f"scale {s:4.2f}: predicted margin min {min(p[1] for p in preds):6.3f} median "
              f"{np.median([p[1] for p in preds]):6.3f}; right {int(ok.sum())}/{ok.size}, encoders all right "
              f"{int(ok.all(axis=1).sum())}/{encoders}, wrong frames applied {int(wrong.sum())} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return rows


def fingerprint_check(errors: SensorErrors, mech: MechParams, frame_pulse: int) -> tuple[float, float]:
    """How the block's fitted fingerprint matches the encoder's true one in the block's frame:
    (the least correlation of the two pitch-error sequences over the directions measured, the
    grid phase's difference in electrical degrees, ~0 when the frame is right)."""
    from eol_cal.analysis.fingerprint import pitch_errors
    from eol_cal.firmware.kinematics import fingerprint_of

    fp_true, gp_true = fingerprint_of(errors, POLES)
    ref = np.roll(fp_true, -2 * frame_pulse)
    dF, dT = pitch_errors(np.asarray(mech.fingerprint, float), N_ENC), pitch_errors(ref, N_ENC)
    corr = min(float(dF[d::2] @ dT[d::2] / math.sqrt(dF[d::2] @ dF[d::2] * (dT[d::2] @ dT[d::2])))
               for d in (0, 1) if mech.fp_dirs & (1 << d))
    delta = POLES * math.pi / N_ENC
    dg = math.remainder(float(mech.grid_phase) - gp_true - frame_pulse * delta, 2 * math.pi)
    return corr, math.degrees(dg)


def run_end_to_end(encoders: int, per_encoder: int, spread: str = "mech23", dump: str | None = None,
                   seed0: int = 70_000, scales: tuple[float, ...] = E2E_SCALES) -> list[dict[str, Any]]:
    """Per motor (``encoders`` a scale of :data:`E2E_SCALES`): the switch end of line wrote, the
    predicted margin, the fitted fingerprint against the truth, and ``per_encoder`` twin power-ups
    of the true encoder on the block's fitted fingerprint (right, wrong frames applied). ``dump``: a
    pickle of every motor's window edges and fingerprint (to study other rules on the same motors);
    ``seed0``: the first motor's seed (the same seeds at every scale: the same motors, their pitch
    errors scaled); ``scales``: the pitch-error scales run (x nominal)."""
    from eol_cal.firmware.contract import FLAG_MECH_COMP_ENABLE
    from eol_cal.firmware.mech_sim import simulate_powerups
    from eol_cal.sim.mech_motors import SWITCH_SECONDS, pitch_error_spread, switch_powerups, through_end_of_line

    rows: list[dict[str, Any]] = []
    kept = []
    for s in scales:
        t0 = time.perf_counter()
        seeds = [seed0 + e for e in range(encoders)]
        sp = pitch_error_spread(s, spread)
        motors = through_end_of_line([sp.draw(seed) for seed in seeds], seeds[0])
        t_fit = time.perf_counter() - t0
        pus, idx = [], []
        for e, m in enumerate(motors):
            if m.block is None or m.block.mech is None:
                continue
            pus += switch_powerups(m.errors, m.block.mech, per_encoder, np.random.default_rng(1000 * e + int(100 * s)),
                                   m.frame_pulse)
            idx.append(e)
        res = simulate_powerups(pus, SWITCH_SECONDS, seed=int(100 * s)) if pus else None
        for e, m in enumerate(motors):
            mech = m.result.mech
            row: dict[str, Any] = dict(scale=s, seed=seeds[e], fit=m.result.status, on=False, margin=math.nan, score=math.nan,
                       corr=math.nan, dgrid_deg=math.nan, right=0, of=0, wrong=0, field_margin_min=math.nan,
                       fp=None, sigma=None, dirs=0)
            if e in idx:
                assert res is not None and mech is not None and m.block is not None and m.block.mech is not None
                k = idx.index(e)
                sl = slice(k * per_encoder, (k + 1) * per_encoder)
                ok = res.right[sl]
                corr, dg = fingerprint_check(m.errors, m.block.mech, m.frame_pulse)
                done = res.margin[sl][np.asarray(res.active_end[sl]) != 0]
                row.update(on=bool(m.block.flags & FLAG_MECH_COMP_ENABLE), margin=mech.margin, score=mech.score,
                           corr=corr, dgrid_deg=dg, right=int(ok.sum()), of=per_encoder,
                           wrong=int((res.wrong_ticks[sl] > 0).sum()),
                           field_margin_min=float(done.min()) if done.size else math.nan,
                           fp=list(mech.fingerprint), sigma=[None if x is None else float(x) for x in mech.sigma],
                           dirs=mech.dirs)
            rows.append(row)
            kept.append((s, seeds[e], m.frame_pulse, m.prints, m.fingerprint))
        if dump:
            import pickle

            Path(dump).write_bytes(pickle.dumps(kept))
        sel = [r for r in rows if r["scale"] == s]
        ident = [r for r in sel if r["of"] and r["right"] == r["of"]]
        print(f"scale {s:4.2f}: on {sum(r['on'] for r in sel)}/{len(sel)}, predicted margin min "
              f"{np.nanmin([r['margin'] for r in sel]):6.3f} median {np.nanmedian([r['margin'] for r in sel]):6.3f}; "
              f"power-ups right {sum(r['right'] for r in sel)}/{sum(r['of'] for r in sel)}, motors right on every "
              f"power-up {len(ident)}/{len(sel)}, wrong frames applied {sum(r['wrong'] for r in sel)}; fitted vs true "
              f"pitch errors corr min {np.nanmin([r['corr'] for r in sel]):.3f}, grid phase off by at most "
              f"{np.nanmax(np.abs([r['dgrid_deg'] for r in sel])):.2f} deg "
              f"(fit {t_fit:.0f} s, twin {time.perf_counter() - t0 - t_fit:.0f} s)", flush=True)
    return rows


def rescore(rows: list[dict[str, Any]], dump: str) -> list[dict[str, Any]]:
    """The end-to-end rows (``--json``) with each motor's predicted cosine and margin recomputed by
    the current library from the run's ``--dump`` (its window edges and fingerprint) and the switch
    decided by the current thresholds; the twin's power-ups (run on every motor, on or off) stay."""
    import pickle

    from eol_cal.analysis.fingerprint import predicted_margin, split_noise
    from eol_cal.firmware.mech_params import SWITCH_MARGIN, SWITCH_MIN_SCORE

    kept = pickle.loads(Path(dump).read_bytes())
    out = []
    for r, (s, seed, _, prints, fp) in zip(rows, kept, strict=True):
        if (r["scale"], r["seed"]) != (s, seed):
            raise ValueError(f"{dump}: motor {seed} at {s:g}x where the rows have {r['seed']} at {r['scale']:g}x")
        r = dict(r)
        if fp is not None and r["of"]:
            r["score"], r["margin"] = predicted_margin(fp.fp, fp.sigma, fp.dirs, POLES, N_ENC, 20000.0,
                                                       noise=split_noise(prints, fp, POLES, N_ENC))
            r["on"] = bool(r["margin"] >= SWITCH_MARGIN and r["score"] >= SWITCH_MIN_SCORE)
        out.append(r)
    return out


def report_end_to_end(rows: list[dict[str, Any]]) -> None:
    """The switch against the twin: per scale, on where the twin failed (must be none), off where it
    identified on every power-up."""
    print("\n| pitch errors (x nominal) | predicted cosine min / median | predicted margin min / median | on | "
          "power-ups right | motors right on "
          "every power-up | on, twin not right on every power-up | off, twin right on every power-up |")
    print("|---|---|---|---|---|---|---|---|")
    for s in sorted({r["scale"] for r in rows}):
        sel = [r for r in rows if r["scale"] == s]
        allright = [r["of"] > 0 and r["right"] == r["of"] for r in sel]
        bad_on = sum(r["on"] and not a for r, a in zip(sel, allright, strict=True))
        bad_off = sum(a and not r["on"] for r, a in zip(sel, allright, strict=True))
        print(f"| {s:.2f} | {np.nanmin([r['score'] for r in sel]):.3f} / {np.nanmedian([r['score'] for r in sel]):.3f} "
              f"| {np.nanmin([r['margin'] for r in sel]):.3f} / {np.nanmedian([r['margin'] for r in sel]):.3f} "
              f"| {sum(r['on'] for r in sel)} / {len(sel)} | {sum(r['right'] for r in sel)} / {sum(r['of'] for r in sel)} "
              f"| {sum(allright)} / {len(sel)} | {bad_on} | {bad_off} |")
    on = [r for r in rows if r["on"]]
    n_ok, n = sum(r["right"] for r in on), sum(r["of"] for r in on)
    print(f"\nswitched on: {len(on)} motors, {n_ok}/{n} power-ups right, wrong frames applied "
          f"{sum(r['wrong'] for r in rows)} over all {sum(r['of'] for r in rows)} power-ups"
          + (f"; with none wrong the rate is at least {1 - 3.0 / n:.5f} with 95 % confidence" if n and n_ok == n else ""))


def plot_end_to_end(rows: list[dict[str, Any]], path: str, threshold: float) -> None:
    """Predicted cosine (x: the switch's ``threshold`` on it) against the twin's power-ups right (y)
    per motor, by scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for s in E2E_SCALES:
        sel = [r for r in rows if r["scale"] == s and r["of"]]
        if not sel:  # a run of some scales only
            continue
        ax.scatter([r["score"] for r in sel], [r["right"] / r["of"] for r in sel], s=14, label=f"{s:g}x")
    ax.axvline(threshold, color="k", ls="--", lw=1, label=f"switch {threshold:g}")
    ax.set_xlabel("predicted cosine (end of line, fitted fingerprint)")
    ax.set_ylabel("twin power-ups identified right (fraction)")
    ax.set_title("End to end: the switch against the firmware twin (300 rpm)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


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
    ap.add_argument("--end-to-end", action="store_true",
                    help="plant motors through the fit and the block it writes, the twin on the fitted fingerprint")
    ap.add_argument("--spread", default="mech23", help="production spread of the end-to-end motors")
    ap.add_argument("--seed0", type=int, default=70_000, help="end to end: the first motor's seed")
    ap.add_argument("--scales", default=",".join(f"{s:g}" for s in E2E_SCALES),
                    help="end to end: the pitch-error scales (x nominal), comma-separated")
    ap.add_argument("--dump", help="end to end: pickle of the motors' window edges and fingerprints")
    ap.add_argument("--plot", help="end to end: PNG of the predicted cosine against the twin's power-ups right")
    ap.add_argument("--rescore", nargs=2, metavar=("JSON", "DUMP"),
                    help="end to end: no run; an earlier run's rows and dump, the switch recomputed by the current code")
    args = ap.parse_args()
    if args.end_to_end:
        from eol_cal.firmware.mech_params import SWITCH_MIN_SCORE

        print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}", flush=True)
        if args.rescore:
            rows_e = rescore(json.loads(Path(args.rescore[0]).read_text()), args.rescore[1])
        else:
            rows_e = run_end_to_end(args.encoders, args.per_encoder, args.spread, args.dump, args.seed0,
                                    tuple(float(x) for x in args.scales.split(",")))
        report_end_to_end(rows_e)
        if args.json:
            Path(args.json).write_text(json.dumps(rows_e))
        if args.plot:
            plot_end_to_end(rows_e, args.plot, SWITCH_MIN_SCORE)
        print(f"load {os.getloadavg()[0]:.2f}")
        return
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
