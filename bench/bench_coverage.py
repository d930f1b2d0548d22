"""Do the fit's 95 % intervals cover the truth 95 % of the time? A Monte Carlo over plant motors.

Each motor is drawn from a production spread (default ``mech23``: the default spread with the
mechanical orders 2 and 3 of 2-4 mN*m, issue 34), run through the ``eol-default`` profile on the
plant under the ``best`` estimator (as the station's "prepare ECU" step flashes it), fitted as
``eol-cal fit`` fits (``fit_motors``' path: firmware frame, fingerprint, corrected angle,
mechanical orders), and every reported interval is judged against the plant's truth:

- ``k6``, ``c6`` (amplitudes) and ``phase_k6``, ``phase_c6`` in the firmware estimator's frame: the
  truth moved by the plant's own estimator's frame on the same run (``theta_hat - theta_r``),
  against the plant's parameter (what the fit reports since it takes the ECU's own current ripple
  out with the ``iq`` channel, docs/fit.md);
- ``delay_s``: the lag of the sampled torque behind the capture's angle, as the first-order
  low-pass the fit models it (:func:`chain_delay_s`): the transducer's time constant
  ``1 / (2 pi tq_bw_hz)`` as the plant samples it, with the shaft line's semi-implicit Euler step
  and the transducer's reading half a tick on (within 0.2 us of the time constant since issue 34's
  fix of the plant's reading; 25 us short before);
- ``mech{h}`` and ``phase_mech{h}`` (h = 1..3): each order in the block's frame (the truth's
  phase moved by the frame's mechanical angle against the plant's, measured per sample);
- ``fingerprint``: every edge error against the plant's pulse placement in the block's
  numbering, orders 0..2 taken out as the fit takes them out.

Printed per quantity: n, the share covered with its binomial standard error, and the median of
``|error| / ci95`` (1.0 at the interval's edge). A quantity covered in 95 +- 3 % passes.

    python bench/bench_coverage.py [--motors 400] [--batch 20] [--first-seed 1001] [--spread mech23] [--json cov.json]
        [--cache out/cov_cache]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import MotorResult, ValueCi

#: quantities whose value and truth are angles (rad): errors wrapped to (-pi, pi]
PHASES = ("phase_k6", "phase_c6", "phase_k6_eff", "phase_c6_eff", "phase_mech1", "phase_mech2", "phase_mech3")


def current_ripple(run, spec) -> dict[str, complex]:
    """The 6th harmonic of ``kt * i_q`` of a noise-free run (plant's true angle frame): ``{"k": N*m/A
    phasor, "c": N*m phasor}``, fitted with the fit's own model (no transducer, no bench)."""
    import dataclasses

    from eol_cal.analysis.fit import fit_many
    from eol_cal.analysis.fit.capture import motor_inputs

    (mi,) = motor_inputs([run.capture], frame="offline", hall_angle="nominal")
    kt = float(run.capture.metadata["kt"])
    iq = np.asarray(run.capture["iq"], dtype=float)
    seg = dataclasses.replace(mi.segments, torque=[kt * iq[s.start:s.stop] for s in mi.info], path_response=None,
                              kt_iq=None)
    (f,) = fit_many([seg], dataclasses.replace(spec, delay_s=1e-9), mode="loop")
    # the offline frame sits d_rec off the true angle: phase in the true frame = phase + 6 d_rec
    d_rec = float(np.angle(np.mean(np.exp(1j * (mi.angles[0].theta_r - run.theta_r)))))
    six = f.harmonics[6]
    return {part: six[part].value * np.exp(1j * (six[part].phase + 6 * d_rec)) for part in ("k", "c")}


def chain_delay_s(p, freqs_hz: np.ndarray) -> float:
    """The plant's sampled torque chain as the fit sees it: the time constant (s) of the first-order
    low-pass that, behind the continuous shaft line the fit divides out, has the chain's phase,
    averaged over ``freqs_hz`` (Hz, the 6th harmonic at the profile's speeds).

    The chain is the plant's own tick (:func:`eol_cal.domain.bench_mechanics.mech_step`, then the
    transducer's ``y += tq_gain (T_shaft - y)`` of :func:`eol_cal.plant.sensors.transducer_step`,
    whose reading is the mean of its states at the tick's start and end), linear in its state
    (twist, speeds, the dyno's integrator, the transducer's state) about standstill, so its
    response is ``C (zI - A)^-1 b + d`` at ``z = e^{i w dt}``.
    """
    from types import SimpleNamespace

    from eol_cal.domain.bench_mechanics import mech_step, torsion_response
    from eol_cal.plant.params import to_params

    q = to_params(p, np.zeros(16), np.zeros(16), 0.0, 0.0)
    line = SimpleNamespace(**{k: float(getattr(q, k)) for k in ("J", "B", "J_dyno", "K_shaft", "D_shaft", "Kp_dyno",
                                                                 "Ki_dyno")})
    g, dt = float(q.tq_gain), 1.0 / p.motor.f_pwm

    def tick(x: np.ndarray, u: float) -> tuple[np.ndarray, float]:
        _, tw, om, od, xd, T_shaft = mech_step(0.0, x[0], x[1], x[2], x[3], u, 0.0, line, dt, np)
        y = x[4] + g * (T_shaft - x[4])
        return np.array([tw, om, od, xd, y]), 0.5 * (x[4] + y)

    cols = [tick(e, 0.0) for e in np.eye(5)]
    A = np.column_stack([c[0] for c in cols])
    C = np.array([c[1] for c in cols])
    b, d = tick(np.zeros(5), 1.0)
    tau = 1.0 / (2 * math.pi * p.tq_bw_hz)
    out = []
    for f in np.atleast_1d(freqs_hz):
        w = 2 * math.pi * float(f)
        z = np.exp(1j * w * dt)
        h = C @ np.linalg.solve(z * np.eye(5) - A, b) + d
        cont = torsion_response(np.array([w]), float(q.J), float(q.B), p.mechanics)[0] / (1 + 1j * w * tau)
        out.append(math.tan(math.atan(w * tau) - float(np.angle(h / cont))) / w)
    return float(np.mean(out))


def prepared_runs(plants, profile, options: int, seed: int, effective: bool = False) -> tuple[list, list, list]:
    """The lot's calibration runs as the station makes them: each motor under its uncompensated
    block carrying ``options`` (the "prepare ECU" step), and, with ``effective``, the same motors
    again without sensor noise (same start angles) for :func:`current_ripple` (bench_fit_lot.py's).

    Returns ``(prepared blocks, runs, clean runs or None per motor)``."""
    from eol_cal.analysis.fit.table import uncompensated_block
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.plant.simulate import simulate

    motor = load_motor("paper")
    prepared = [uncompensated_block(p.serial[:16], motor, calibrated_at=0, options=options) for p in plants]
    runs = simulate(plants, profile, mode="estimated", blocks=prepared, seed=seed)
    clean = simulate([p.replace(tq_noise_nm=0.0, i_noise_a=0.0) for p in plants], profile, mode="estimated",
                     blocks=prepared, seed=seed) if effective else [None] * len(plants)
    return prepared, runs, clean


def cache_path(cache: Path, spread, seed: int, first: int, size: int) -> Path:
    """Where motor ``seed``'s run lies in ``cache``: one folder per spread (its name and a digest of
    its distributions, so an edited spread file misses), one file per motor and noise draw (the
    plant draws a batch's noise from the batch's seed ``first`` split over its ``size`` motors, so a
    motor's run depends on both)."""
    import hashlib

    digest = hashlib.sha256(repr((spread.params, spread.sensors, spread.bench)).encode()).hexdigest()[:12]
    name = "".join(c if c.isalnum() or c in "-_" else "_" for c in spread.name)
    return cache / f"{name}-{digest}" / f"m{seed}_n{first}x{size}.npz"


def save_run(path: Path, run) -> None:
    """One simulated run (its capture and the angles only the plant knows) as a plain ``.npz``, written atomically."""
    import json

    from eol_cal.infra.atomic import atomic_path

    cap = run.capture
    arrays = {f"ch_{k}": v for k, v in cap.channels.items()}
    arrays.update({k: getattr(run, k) for k in ("theta_r", "theta_hat", "theta_enc", "mech_active", "theta_m")})
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, t=cap.t, meta=np.array(json.dumps({"metadata": cap.metadata, "truth": cap.truth})), **arrays)


def load_run(path: Path):
    """The run :func:`save_run` wrote (no pickles: arrays and a JSON string)."""
    import json

    from eol_cal.capture.data import Capture
    from eol_cal.plant.simulate import SimResult

    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        channels = {k[3:]: z[k] for k in z.files if k.startswith("ch_")}
        cap = Capture(t=z["t"], channels=channels, metadata=meta["metadata"], truth=meta["truth"], source="<plant>")
        return SimResult(cap, *(z[k] for k in ("theta_r", "theta_hat", "theta_enc", "mech_active", "theta_m")))


def cached_runs(plants, seeds: list[int], profile, options: int, first: int, spread, cache: Path | None) -> tuple[list, bool]:
    """The batch's runs from ``cache`` when every motor is there, else simulated (and stored when
    ``cache`` is given). Returns ``(runs, simulated)``."""
    paths = [cache_path(cache, spread, s, first, len(seeds)) for s in seeds] if cache is not None else []
    if paths and all(p.is_file() for p in paths):
        return [load_run(p) for p in paths], False
    _, runs, _ = prepared_runs(plants, profile, options, first)
    for path, run in zip(paths, runs, strict=False):
        save_run(path, run)
    return runs, True


def _circmean(x: np.ndarray) -> float:
    return float(np.angle(np.mean(np.exp(1j * x))))


def motor_rows(p, run, mi, res: MotorResult, cur: dict[str, complex] | None = None) -> list[dict]:
    """Per reported interval of one motor's result: quantity, estimate, ci95, truth, error (rad wrapped for phases);
    with ``cur`` (:func:`current_ripple`, bench_fit_lot.py's) also k6 and c6 against the parameter plus the
    ECU's current ripple (``_eff``), which this bench no longer judges: the fit takes that ripple out."""
    from eol_cal.analysis import fingerprint as fpr
    from eol_cal.analysis.fingerprint_fit import low_order_complement
    from eol_cal.firmware.kinematics import fingerprint_of
    from eol_cal.plant.params import sensor_errors, to_params
    from eol_cal.numerics.wrap import wrap_pi

    out: list[dict] = []
    e = res.estimates
    if not res.usable or e is None:
        return [{"quantity": "status", "value": str(res.status), "reasons": list(res.reasons)}]
    seg = mi.segments
    idx = np.concatenate([np.arange(o.start, o.stop) for o in mi.info])
    # the firmware estimator's frame on this run, against the plant's true angle (rad electrical)
    d_fw = _circmean(np.asarray(run.theta_hat)[idx] - np.asarray(run.theta_r)[idx])

    def add(q: str, est: ValueCi, truth: float) -> None:
        if est.value is None:
            return
        err = est.value - truth
        if q in PHASES:
            err = float(wrap_pi(err))
        out.append({"quantity": q, "value": est.value, "ci95": est.ci95, "truth": float(truth), "err": float(err)})

    # the fit's frame offset (firmware frame minus its own, fingerprint-corrected, angle) against
    # the truth; no interval of its own: its error moves harmonic h's phases by -h times it
    d_fit = _circmean(np.concatenate([np.asarray(seg.theta[s]) for s in range(seg.n_segments)])
                      - np.asarray(run.theta_r)[idx])
    out.append({"quantity": "frame_offset", "value": mi.frame_offset_rad, "ci95": None, "truth": d_fw - d_fit,
                "err": float(wrap_pi(mi.frame_offset_rad - (d_fw - d_fit)))})
    plant_ph = {"k": p.k6 * np.exp(1j * p.phase_k6), "c": p.c6 * np.exp(1j * p.phase_c6)}
    for part in ("k", "c"):
        z = plant_ph[part]
        add(f"{part}6", getattr(e, f"{part}6"), abs(z))
        add(f"phase_{part}6", getattr(e, f"phase_{part}6"), np.angle(z) - 6 * d_fw)
        if cur is not None:
            z = z + cur[part]
            add(f"{part}6_eff", getattr(e, f"{part}6"), abs(z))
            add(f"phase_{part}6_eff", getattr(e, f"phase_{part}6"), np.angle(z) - 6 * d_fw)
    f6 = sorted({round(6 * abs(float(o.speed_rpm)) * mi.poles / 2 / 60.0, 3) for o in mi.info})
    add("delay_s", e.delay_s, chain_delay_s(p, np.array(f6)))
    mech = res.mech
    fp = mi.fingerprint
    if not mech or fp is None or mi.prints is None:
        return out
    # the block's mechanical angle against the plant's, over the segments of placed windows
    diffs = []
    for s, info in enumerate(mi.info):
        ci = mi.capture_of_segment[s]
        edges, offset = mi.prints[ci], fp.offsets[ci]
        if edges is None or offset is None:
            continue
        th_b = fpr.block_frame_mech_angle(edges.q[info.start:info.stop], offset, fp.grid_phase,
                                          np.asarray(seg.theta[s]) + mi.frame_offset_rad, mi.poles, mi.encoder_ppr)
        diffs.append(th_b - np.asarray(run.theta_m)[info.start:info.stop])
    delta = _circmean(np.concatenate(diffs))
    for o in mech.orders:
        h = o.order
        add(f"mech{h}", o.c, getattr(p, f"unb{h}"))
        if getattr(p, f"unb{h}") > 0:
            add(f"phase_mech{h}", o.phase_c, getattr(p, f"phase_unb{h}") - h * delta)
    # the fingerprint: the plant's edge errors in the block's numbering, orders 0..2 out per half
    N = mi.encoder_ppr
    true_fp, _ = fingerprint_of(sensor_errors(to_params(p, np.zeros(16), np.zeros(16), 0.0, 0.0)), mi.poles)
    P = low_order_complement(N)
    got = np.asarray(mech.fingerprint, float)
    sig = np.array([np.inf if s is None else s for s in mech.sigma], float)
    best = None
    for r in range(N):
        cand = np.roll(true_fp, -2 * r).copy()
        for d in (0, 1):
            cand[d::2] = P @ (P.T @ cand[d::2])
        score = float(got @ cand)
        if best is None or score > best[0]:
            best = (score, cand)
    assert best is not None
    for j in np.flatnonzero(np.isfinite(sig) & (sig > 0)):
        out.append({"quantity": "fingerprint", "value": float(got[j]), "ci95": float(1.959963984540054 * sig[j]),
                    "truth": float(best[1][j]), "err": float(got[j] - best[1][j])})
    return out


def write_rows(path: Path, rows: list[dict]) -> None:
    """Every judged interval as JSON, written atomically (a reader never sees half a file)."""
    import json

    from eol_cal.infra.atomic import atomic_write

    atomic_write(path, json.dumps(rows, indent=1))


def summary(rows: list[dict]) -> list[tuple[str, int, float, float, float]]:
    """Per quantity: (name, n, covered share, its standard error, median |err| / ci95)."""
    names = list(dict.fromkeys(r["quantity"] for r in rows if r["quantity"] != "status" and r["ci95"] is not None))
    out = []
    for q in names:
        sub = [r for r in rows if r["quantity"] == q and r["ci95"] is not None]  # no interval: nothing to cover
        ratio = np.array([abs(r["err"]) / r["ci95"] if r["ci95"] else np.inf for r in sub])
        cov = float(np.mean(ratio <= 1.0))
        out.append((q, len(sub), cov, math.sqrt(cov * (1 - cov) / len(sub)), float(np.median(ratio))))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motors", type=int, default=400)
    ap.add_argument("--batch", type=int, default=20, help="motors simulated together (memory)")
    ap.add_argument("--first-seed", type=int, default=1001)
    ap.add_argument("--spread", default="mech23", help="production spread (built-in name or .toml file)")
    ap.add_argument("--cache", type=Path, help="keep the simulated runs here (e.g. out/cov_cache) and read them "
                    "back: a refit of the same motors costs only the fit")
    ap.add_argument("--json", help="write every judged interval here")
    ap.add_argument("--simulate-only", action="store_true", help="fill --cache, fit nothing")
    ap.add_argument("--fit-chunk", type=int, default=8, help="motors fitted together (the rows are written after each)")
    args = ap.parse_args()

    from rich.progress import Progress

    from eol_cal.analysis.fit import FitSpec
    from eol_cal.analysis.fit.motors import FitOptions, fit_inputs
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.firmware.options import parse_options
    from eol_cal.domain.bench_mechanics import load_mechanics
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.spread import load_spread
    from eol_cal.plant.variation import draw_motor

    print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; spread {args.spread}, seeds "
          f"{args.first_seed}..{args.first_seed + args.motors - 1}")
    spread = load_spread(args.spread)
    cal = load_profile("eol-default")
    best = parse_options("best")
    spec = FitSpec()
    options = FitOptions(spec=spec, capture_metrics=False, estimator_options=best)
    bench = load_mechanics("paper")
    rows: list[dict] = []
    t_start = time.perf_counter()
    t_sim, t_load = [0.0], [0.0]
    t_fit = 0.0
    with Progress(transient=True) as progress:
        task = progress.add_task("motors", total=args.motors)
        for first in range(args.first_seed, args.first_seed + args.motors, args.batch):
            seeds = list(range(first, min(first + args.batch, args.first_seed + args.motors)))
            plants = [draw_motor(s, spread=spread) for s in seeds]
            t0 = time.perf_counter()
            runs, simulated = cached_runs(plants, seeds, cal, best, first, spread, args.cache)
            (t_sim if simulated else t_load)[0] += time.perf_counter() - t0
            if args.simulate_only:
                progress.update(task, completed=len(seeds) + first - args.first_seed)
                continue
            # fitted a few at a time, the rows written after each: a run stopped early keeps what it fitted
            for c in range(0, len(runs), args.fit_chunk):
                chunk = slice(c, c + args.fit_chunk)
                t0 = time.perf_counter()
                inputs = [motor_inputs([r.capture], mechanics=bench, estimator_options=best)[0] for r in runs[chunk]]
                results = fit_inputs(inputs, options).results
                t_fit += time.perf_counter() - t0
                for p, run, mi, res in zip(plants[chunk], runs[chunk], inputs, results, strict=True):
                    for row in motor_rows(p, run, mi, res):
                        rows.append({"seed": p.serial, **row})
                if args.json:
                    write_rows(Path(args.json), rows)
                done = first - args.first_seed + min(c + args.fit_chunk, len(runs))
                progress.update(task, completed=done)
                print(f"{done} motors fitted, {time.perf_counter() - t_start:.0f} s, load {os.getloadavg()[0]:.1f}",
                      flush=True)
    wall = time.perf_counter() - t_start
    bad = [r for r in rows if r["quantity"] == "status"]
    print(f"{args.motors} motors, {len(bad)} fits not usable; wall {wall:.0f} s (simulation {t_sim[0]:.0f} s, "
          f"cache reads {t_load[0]:.0f} s, fits {t_fit:.0f} s; {wall / args.motors:.2f} s a motor), "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'quantity':<16} {'n':>6} {'covered':>9} {'± se':>7}  {'median |err|/ci95':>18}  verdict (95 ± 3 %)")
    for q, n, cov, se, med in summary(rows):
        verdict = "ok" if abs(cov - 0.95) <= 0.03 else ("too narrow" if cov < 0.95 else "too wide")
        print(f"{q:<16} {n:>6} {100 * cov:>8.1f}% {100 * se:>6.1f}%  {med:>18.2f}  {verdict}")
    frame = np.degrees([r["err"] for r in rows if r["quantity"] == "frame_offset"])
    if len(frame):
        print(f"frame offset error (firmware frame, electrical deg; the phases' share is h times it): mean "
              f"{frame.mean():+.3f}, sd {frame.std(ddof=1) if len(frame) > 1 else 0.0:.3f}, max |.| {np.abs(frame).max():.3f}")


if __name__ == "__main__":
    main()
