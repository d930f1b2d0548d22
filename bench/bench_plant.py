"""Speed of the built-in plant, and its p-p figures, against an older checkout of the code and
against motulator, side by side in one run.

Prints simulated seconds per second (x real time) for:

- eol-cal's plant (JAX ``lax.scan`` at the 20 kHz PWM tick, float32, compensated mode of the
  paper preset: estimator + compensator + PI current control + SPMSM + shaft/dyno + transducer),
  one motor and a vmapped batch (default 64 motors drawn from the production spread), cold (first
  call: trace + compile + run, no persistent cache) and warm (the next calls), with the ideal
  blocks of both layouts side by side: layout 1 (the paper's estimator, 6th-harmonic tables) and
  layout 2 (contract revision 1.2: every estimator option and ``MECH_COMP_ENABLE``, the ECU's
  identifier running every tick and the mechanical orders compensated once it has identified);
- the same with ``--baseline DIR`` (a checkout of older code, e.g. ``git worktree add DIR
  COMMIT``): its ``eol_cal`` imported instead of this one, in a process of its own;
- motulator (the package index's PMSM drive simulator, when installed: ``pip install -e .[bench]``)
  simulating the same motor under current-vector control at the same 20 kHz sampling, an
  externally driven rotor at 60 rpm, 3.2 N*m reference.

Each simulator runs in a fresh process pinned to one CPU core (``os.sched_setaffinity``): the
figures are one-core figures, ``warm/cpu`` per CPU second of that process (which other jobs on the
machine move less than the wall time). The rounds alternate the code versions.

``--pp-seeds N`` also measures the paper preset's p-p ripple (docs/metrics.md: raw and filtered,
60 rpm, 65 A, 1.5 s) in the three modes over N noise seeds with each code version: the means the
speed-ups must keep (issue 25: within 2 %).

    python bench/bench_plant.py [--seconds 2.0] [--batch 64] [--rounds 2] [--baseline DIR ...] [--pp-seeds 10]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()
MODES = ("raw", "estimated", "compensated")
LAYOUTS = (1, 2)


def _pin_one_core() -> int:
    cpus = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpus[0]})
    return cpus[0]


def _loop_kernel() -> None:
    try:
        from eol_cal.numerics.xla import configure_xla
    except ImportError:  # older checkouts kept it with the plant
        from eol_cal.plant.simulate import configure_xla
    configure_xla()


def layout_blocks(layout: int, specs: list[Any]) -> list[Any] | None:
    """The ideal blocks of ``specs`` in a layout: None for layout 1 (the plant makes them from its
    truth), layout-2 blocks that identify (every estimator option, ``MECH_COMP_ENABLE``) for 2."""
    if layout == 1:
        return None
    from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
    from eol_cal.plant.ecu_model import true_block

    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE
    return [true_block(s, flags=flags, mech=True) for s in specs]


def bench_plant(seconds: float, batch: int, warm_runs: int) -> dict[str, float]:
    """Cold and best warm wall and CPU times (s) of one motor and of ``batch`` motors, per layout
    (keys ``L<layout>/<motors>/<cold|warm>[/cpu]``)."""
    from eol_cal.plant.presets import paper
    from eol_cal.plant.profile import constant
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.variation import draw_motor

    prof = constant(60.0, seconds, iq=65.0)
    out: dict[str, float] = {}
    for layout in LAYOUTS:
        for label, specs in (("1", [paper()]), (str(batch), [draw_motor(s) for s in range(batch)])):
            blocks = layout_blocks(layout, specs)
            for k in range(1 + warm_runs):
                t0, c0 = time.perf_counter(), time.process_time()
                simulate(specs, prof, mode="compensated", blocks=blocks, pre_roll_s=0.0)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                key = f"L{layout}/{label}/{'cold' if k == 0 else 'warm'}"
                out[key] = min(out.get(key, math.inf), wall)
                out[f"{key}/cpu"] = min(out.get(f"{key}/cpu", math.inf), cpu)
    return out


def paper_pp(seeds: int) -> dict[str, list[list[float]]]:
    """Per mode, (raw %, filtered %) of the paper preset for noise seeds 1..``seeds``."""
    from eol_cal.analysis.metrics import capture_ripple_pp
    from eol_cal.plant.presets import paper
    from eol_cal.plant.profile import constant
    from eol_cal.plant.simulate import simulate

    prof = constant(60.0, 1.5, iq=65.0)
    out: dict[str, list[list[float]]] = {}
    for mode in MODES:
        out[mode] = []
        for seed in range(1, seeds + 1):
            pp = capture_ripple_pp(simulate(paper(), prof, mode=mode, seed=seed)[0].capture)
            out[mode].append([pp.raw_pct, pp.filtered_pct])
    return out


def bench_motulator(seconds: float) -> dict[str, float]:
    """Cold/warm wall and CPU times (s) of motulator's PMSM current-vector-controlled drive."""
    import motulator.drive.control.sm as control
    from motulator.drive import model
    from motulator.drive.utils import SynchronousMachinePars

    from eol_cal.domain.motor_params import load_motor

    m = load_motor("paper")
    out: dict[str, float] = {}
    for phase in ("cold", "warm"):
        par = SynchronousMachinePars(n_p=m.pole_pairs, R_s=m.R_s, L_d=m.L_d, L_q=m.L_q, psi_f=m.psi_f)
        machine = model.SynchronousMachine(par)
        mechanics = model.ExternalRotorSpeed(w_M=lambda t: 2.0 * math.pi + 0.0 * t)  # the dyno holds 60 rpm
        converter = model.VoltageSourceConverter(u_dc=m.u_dc)
        mdl = model.Drive(converter, machine, mechanics)
        cfg = control.CurrentReferenceCfg(par, max_i_s=100.0, nom_w_m=2.0 * math.pi * 50.0)
        ctrl = control.CurrentVectorControl(par, cfg, T_s=1.0 / m.f_pwm, alpha_c=2.0 * math.pi * m.current_bw_hz,
                                            sensorless=False)
        ctrl.ref.tau_M = lambda t: 3.2
        sim = model.Simulation(mdl, ctrl)
        t0, c0 = time.perf_counter(), time.process_time()
        sim.simulate(t_stop=seconds)
        out[phase] = time.perf_counter() - t0
        out[f"{phase}/cpu"] = time.process_time() - c0
    return out


def child(kind: str, a: argparse.Namespace, out: Path) -> None:
    _pin_one_core()
    if not a.no_loop_kernel:
        _loop_kernel()
    if kind == "plant":
        res: Any = bench_plant(a.seconds, a.batch, a.warm_runs)
    elif kind == "pp":
        res = paper_pp(a.pp_seeds)
    else:
        res = bench_motulator(a.motulator_seconds)
    out.write_text(json.dumps(res))


def run_child(kind: str, a: argparse.Namespace, baseline: Path | None) -> Any:
    env = dict(os.environ)
    if baseline is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(baseline), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        env["PYTHONDONTWRITEBYTECODE"] = "1"  # another checkout is read, not written
    args = [sys.executable, str(HERE), "--child", kind, "--seconds", str(a.seconds), "--batch", str(a.batch),
            "--warm-runs", str(a.warm_runs), "--pp-seeds", str(a.pp_seeds), "--motulator-seconds",
            str(a.motulator_seconds)] + (["--no-loop-kernel"] if a.no_loop_kernel else [])
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        subprocess.run(args + ["--out", f.name], check=True, env=env, cwd=baseline or HERE.parent.parent)
        return json.loads(Path(f.name).read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="simulated seconds of the plant runs")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--warm-runs", type=int, default=2, help="warm calls per process (the best one counts)")
    ap.add_argument("--rounds", type=int, default=2, help="the code versions run in turn, this many times")
    ap.add_argument("--baseline", type=Path, action="append", default=[],
                    help="a checkout of older code to run side by side (repeat for several)")
    ap.add_argument("--pp-seeds", type=int, default=0, help="noise seeds of the p-p comparison (0: none)")
    ap.add_argument("--motulator-seconds", type=float, default=1.0, help="simulated seconds of motulator")
    ap.add_argument("--no-loop-kernel", action="store_true",
                    help="leave XLA's small-while-loop threshold at its default (each kernel dispatched)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child, a, a.out)
        return

    versions: list[tuple[str, Path | None]] = [(f"baseline {b}", b.resolve()) for b in a.baseline]
    versions.append(("this checkout", None))
    load0 = os.getloadavg()
    runs: dict[str, list[dict[str, float]]] = {name: [] for name, _ in versions}
    for r in range(a.rounds):
        for name, path in versions:
            res = run_child("plant", a, path)
            runs[name].append(res)
            b = a.batch
            for lay in LAYOUTS:
                print(f"round {r + 1}: {name:<40} layout {lay}: 1 motor {a.seconds / res[f'L{lay}/1/warm/cpu']:6.1f}x "
                      f"per CPU s ({a.seconds / res[f'L{lay}/1/warm']:6.1f}x wall), "
                      f"batch {b} {b * a.seconds / res[f'L{lay}/{b}/warm']:6.1f}x (wall), "
                      f"{b * a.seconds / res[f'L{lay}/{b}/warm/cpu']:6.1f}x per CPU s; load {os.getloadavg()[0]:.2f}",
                      flush=True)
    try:
        import motulator  # noqa: F401

        mot = run_child("motulator", a, None)
    except ImportError:
        mot = None

    b = a.batch
    print(f"\none CPU core per process; simulated {a.seconds:g} s (plant); batch of {b} from the production spread; "
          f"load average {load0[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end; "
          f"x real time = simulated s per s, best of {a.rounds} rounds x {a.warm_runs} warm runs")
    print(f"{'simulator':46s} {'cold':>7s} {'warm':>7s} {'warm/cpu':>9s}")
    best: dict[str, dict[str, float]] = {}
    for name, _ in versions:
        best[name] = {k: min(r[k] for r in runs[name]) for k in runs[name][0]}
        x = best[name]
        for lay in LAYOUTS:
            for label, n in (("1", 1), (str(b), b)):
                title = f"{name}: L{lay} {'1 motor' if n == 1 else f'batch {b} (aggregate)'}"
                k = f"L{lay}/{label}"
                print(f"{title:46s} {n * a.seconds / x[f'{k}/cold']:7.1f} {n * a.seconds / x[f'{k}/warm']:7.1f} "
                      f"{n * a.seconds / x[f'{k}/warm/cpu']:9.1f}")
    if mot is not None:
        print(f"{'motulator PMSM current-vector control':46s} {a.motulator_seconds / mot['cold']:7.2f} "
              f"{a.motulator_seconds / mot['warm']:7.2f} {a.motulator_seconds / mot['warm/cpu']:9.2f}")
    else:
        print("motulator: not installed (pip install -e .[bench]); not compared")
    for name, _ in versions[:-1]:
        new, old = best["this checkout"], best[name]
        for lay in LAYOUTS:
            for key, what in ((f"{b}/warm/cpu", f"batch {b} per CPU s"), (f"{b}/warm", f"batch {b} wall"),
                              ("1/warm/cpu", "1 motor per CPU s"), ("1/warm", "1 motor wall")):
                print(f"speed-up against {name}, layout {lay}, {what}: "
                      f"{old[f'L{lay}/{key}'] / new[f'L{lay}/{key}']:.2f}x")
    for lay in LAYOUTS:
        x = best["this checkout"]
        print(f"layout {lay}: batch {b} {b * a.seconds / x[f'L{lay}/{b}/warm/cpu']:.0f}x real time per CPU s "
              f"(target >= 300x on one core), 1 motor {a.seconds / x[f'L{lay}/1/warm/cpu']:.0f}x (target >= 120x)")

    if a.pp_seeds:
        import numpy as np

        pps = {name: run_child("pp", a, path) for name, path in versions}
        print(f"\npaper preset p-p (%), 60 rpm / 65 A / 1.5 s, mean over noise seeds 1..{a.pp_seeds}:")
        for mode in MODES:
            line = f"{mode:<12}"
            means = {name: np.mean(np.array(pps[name][mode]), axis=0) for name, _ in versions}
            for name, _ in versions:
                sd = np.std(np.array(pps[name][mode]), axis=0, ddof=1)
                line += f"  {name}: raw {means[name][0]:.3f} (sd {sd[0]:.3f}), filtered {means[name][1]:.3f} (sd {sd[1]:.3f})"
            for name, _ in versions[:-1]:
                new, old = means["this checkout"], means[name]
                line += f"  -> against {name}: {100 * (new[0] / old[0] - 1):+.2f} %, {100 * (new[1] / old[1] - 1):+.2f} %"
            print(line)


if __name__ == "__main__":
    main()
