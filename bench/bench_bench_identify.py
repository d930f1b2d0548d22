"""The bench identified at commissioning (issue 34): a master motor's sweep on a bench with a
torsion mode, identified by ``eol-cal bench identify``, against the plant's truth.

For each master (seed ``--master-seed`` + k, noise seed k) the plant runs the ``bench-sweep``
profile on the bench (``--plant-bench NAME|FILE``, default ``resonant-250``: 250 Hz, damping 0.1;
or ``--station-seed N``: the default spread's ``[bench]`` draw for station N), the capture is
written as MDF4 and ``eol-cal bench identify`` runs on it as a station engineer would run it
(subprocess; exit code, bench file, plot). Printed: each identified quantity against the truth
and whether the 95 % interval holds it, over ``--repeat`` masters; the first master's bench file
and plot stay in ``--out`` (default ``out/bench_identify``), the file to hand to
``bench/bench_fit_lot.py --bench``.

    python bench/bench_bench_identify.py [--repeat 5] [--plant-bench resonant-250 | --station-seed 3]
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def discrete_mode(spec) -> tuple[float, float]:
    """The torsion mode (Hz, damping ratio) of the plant's shaft line as it integrates it.

    :func:`eol_cal.domain.bench_mechanics.mech_step` linearised (one tick per column of its state), its
    eigenvalues taken to continuous time: the pair of the largest frequency is the torsion mode.
    """
    from types import SimpleNamespace

    from eol_cal.domain.bench_mechanics import mech_step, shaft_damping, speed_gains

    m, b = spec.motor, spec.mechanics
    Kp, Ki = speed_gains(m.J + b.J_dyno, b.dyno_bw_hz, b.dyno_zeta)
    p = SimpleNamespace(J=m.J, B=m.B, J_dyno=b.J_dyno, K_shaft=b.K_shaft,
                        D_shaft=shaft_damping(b.K_shaft, m.J, b.J_dyno, b.shaft_zeta), Kp_dyno=Kp, Ki_dyno=Ki)
    dt = 1.0 / m.f_pwm
    A = np.zeros((4, 4))
    for i in range(4):
        x = np.zeros(4)
        x[i] = 1.0
        # state (twist, omega_m, omega_d, x_dyno); the angle is not part of the dynamics
        _, tw, wm, wd, xd, _ = mech_step(0.0, x[0], x[1], x[2], x[3], 0.0, 0.0, p, dt, np)
        A[:, i] = (tw, wm, wd, xd)
    s = np.log(np.linalg.eigvals(A).astype(complex)) / dt
    top = s[np.argmax(np.abs(s.imag))]
    return float(abs(top) / (2 * math.pi)), float(-top.real / abs(top))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plant-bench", default="resonant-250", metavar="NAME|FILE.toml")
    ap.add_argument("--station-seed", type=int, help="draw the bench from the default spread's [bench] instead")
    ap.add_argument("--master-seed", type=int, default=1001, help="the first master motor's plant seed")
    ap.add_argument("--repeat", type=int, default=1, help="masters (motor and noise seeds) identified one after another")
    ap.add_argument("--out", default="out/bench_identify", help="directory for the captures, bench files and plots")
    args = ap.parse_args()

    from eol_cal.capture.io import write_capture
    from eol_cal.domain.bench_mechanics import load_mechanics, torsion_response
    from eol_cal.plant.presets import paper
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.spread import load_spread

    print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    spread = load_spread("default")
    base = paper()
    base = (spread.draw_bench(args.station_seed, base) if args.station_seed is not None
            else base.replace(mechanics=load_mechanics(args.plant_bench)))
    truth = base.mechanics
    J, J_d = base.motor.J, truth.J_dyno
    f_true = math.sqrt(truth.K_shaft * (J + J_d) / (J * J_d)) / (2 * math.pi)
    print(f"plant bench {truth.name}: torsion mode {f_true:.1f} Hz, damping {truth.shaft_zeta:.3f}, "
          f"K_shaft {truth.K_shaft:.2f} N*m/rad; transducer low-pass {base.tq_bw_hz:g} Hz")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sweep = load_profile("bench-sweep")
    f_eff, z_eff = discrete_mode(base)
    print(f"the plant's integrator (semi-implicit Euler at {base.motor.f_pwm:g} Hz) puts the mode at {f_eff:.2f} Hz, "
          f"damping {z_eff:.4f}: the truth the identification is judged against")
    f_true = f_eff
    truths = {"f_n_hz": f_true, "shaft_zeta": z_eff, "K_shaft": (2 * math.pi * f_eff) ** 2 * J * J_d / (J + J_d),
              "transducer_bw_hz": base.tq_bw_hz,
              # the plant's transducer reads the mean of its states at the tick's start and end, in
              # step with the tick's angle (plant/sensors.py): its continuous model's delay is 0
              # (-0.1 us left to O(dt^2)); the -0.5 / f_pwm that stood here was the chain before that fix
              "transducer_delay_s": 0.0}
    rows = []
    for k in range(args.repeat):
        master = spread.draw(args.master_seed + k, base=base, serial=f"MASTER-{args.master_seed + k}")
        t0 = time.perf_counter()
        (run,) = simulate([master], sweep, mode="estimated", seed=k)
        t_sim = time.perf_counter() - t0
        # as eol-cal acquire joins a profile's windows: one window per segment (segment_starts)
        starts = np.cumsum([0.0] + [seg.seconds for seg in sweep.segments[:-1]])
        run.capture.metadata["segment_starts"] = ",".join(f"{s:.6f}" for s in starts)
        cap_path = out / f"sweep_{k}.mf4"
        write_capture(run.capture, cap_path)
        bench_file, plot = out / f"identified_{k}.toml", out / f"identified_{k}.png"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "cli.main", "bench", "identify", str(cap_path), "-o", str(bench_file),
                               "--plot", str(plot)], capture_output=True, text=True)
        t_id = time.perf_counter() - t0
        if proc.returncode != 0:
            print(f"master {k}: eol-cal bench identify exit {proc.returncode}: {proc.stderr.strip()}")
            rows.append(None)
            continue
        import tomllib

        ident = tomllib.loads(bench_file.read_text())["identification"]
        row = {}
        for key, value in truths.items():
            e = ident[key]
            ci = e.get("ci95")
            row[key] = (e["value"], ci, value, ci is not None and abs(e["value"] - value) <= ci)
        rows.append(row)
        print(f"master {k} ({master.serial}): simulated {t_sim:.1f} s, identified {t_id:.1f} s, "
              f"Birge {ident['birge']:.2f}, {ident['points']} points, dropped {len(ident['dropped'])}")
        for key, (v, ci, tv, held) in row.items():
            cis = "none" if ci is None else f"{ci:.4g}"
            print(f"  {key:<18} {v:.6g} ± {cis}   truth {tv:.6g}   error {100 * (v - tv) / tv if tv else v:+.3g}"
                  f"{' %' if tv else ''}   {'' if held is None else ('in interval' if held else 'OUTSIDE')}")
        # the response error at the calibration profile's harmonics (6, 12, 18 at 60 and 120 rpm)
        ident_bench = load_mechanics(bench_file)
        f_cal = np.array([6, 12, 18, 6, 12, 18]) * np.array([1, 1, 1, 2, 2, 2]) * 3.0
        w = 2 * math.pi * f_cal
        g_id = torsion_response(w, J, base.motor.B, ident_bench)
        g_tr = torsion_response(w, J, base.motor.B, truth)
        g_pa = torsion_response(w, J, base.motor.B, load_mechanics("paper"))
        print("  shaft response error at the calibration's harmonics "
              + ", ".join(f"{f:.0f} Hz" for f in f_cal) + ":")
        print("    identified: " + ", ".join(f"{100 * (abs(a / b) - 1):+.3f} %/{math.degrees(np.angle(a / b)):+.2f} deg"
                                          for a, b in zip(g_id, g_tr, strict=True)))
        print("    paper bench: " + ", ".join(f"{100 * (abs(a / b) - 1):+.3f} %/{math.degrees(np.angle(a / b)):+.2f} deg"
                                           for a, b in zip(g_pa, g_tr, strict=True)))
    ok = [r for r in rows if r is not None]
    print(f"\n{len(ok)}/{len(rows)} sweeps identified")
    for key in truths:
        n_in = sum(1 for r in ok if r[key][3])
        tv = truths[key]
        # a zero truth (the delay) is judged in its own unit, not in percent of nothing
        errs = (np.array([(r[key][0] - tv) * (100 / tv if tv else 1.0) for r in ok]) if ok else np.array([np.nan]))
        print(f"{key:<18} 95 % interval holds the truth {n_in}/{len(ok)}; error ({'%' if tv else 'abs'}): "
              f"max |.| {np.max(np.abs(errs)):.3g}, mean {np.mean(errs):+.3g}")
    print(f"bench file: {out / 'identified_0.toml'}, plot: {out / 'identified_0.png'}")


if __name__ == "__main__":
    main()
