"""Speed of the built-in plant against motulator, side by side in one run.

Prints simulated seconds per wall second (x real time) for:

- eol-cal's plant (JAX lax.scan at the 20 kHz PWM tick, float32, compensated mode of the paper
  preset: estimator + compensator + PI current control + SPMSM + shaft/dyno + transducer),
  one motor and a vmapped batch of 64, cold (first call: trace + compile + run, no persistent
  cache) and warm (second call);
- motulator (the package index's PMSM drive simulator: continuous-time model solved by scipy
  between control samples) simulating the same motor (seed Table I) under current-vector control
  at the same 20 kHz sampling, an externally driven rotor at 60 rpm, 3.2 N*m reference,
  for the same simulated time; cold = first run in the process (imports excluded), warm = second.

Everything is pinned to one CPU core (``os.sched_setaffinity``), so the figures are one-core figures.

    python bench/bench_plant.py [--seconds 1.0] [--batch 64] [--motulator-seconds 1.0]
"""

from __future__ import annotations

import argparse
import math
import os
import time


def _pin_one_core() -> int:
    cpus = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpus[0]})
    return cpus[0]


def bench_plant(seconds: float, batch: int) -> dict[str, float]:
    """Cold/warm wall times (s) of one motor and of ``batch`` motors."""
    from eol_cal.plant.presets import paper
    from eol_cal.plant.profile import constant
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.variation import draw_motor

    prof = constant(60.0, seconds, iq=65.0)
    out: dict[str, float] = {}
    for label, specs in (("1", paper()), (str(batch), [draw_motor(s) for s in range(batch)])):
        for phase in ("cold", "warm"):
            t0, c0 = time.perf_counter(), time.process_time()
            simulate(specs, prof, mode="compensated", pre_roll_s=0.0)
            out[f"{label}/{phase}"] = time.perf_counter() - t0
            out[f"{label}/{phase}/cpu"] = time.process_time() - c0
    return out


def bench_motulator(seconds: float) -> dict[str, float]:
    """Cold/warm wall times (s) of motulator's PMSM current-vector-controlled drive."""
    import motulator.drive.control.sm as control
    from motulator.drive import model
    from motulator.drive.utils import SynchronousMachinePars

    from eol_cal.motor import load_motor

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
        tau = mdl.machine.data.tau_M if hasattr(mdl.machine, "data") else None
        if tau is not None:
            out["torque_check"] = float(sum(tau[len(tau) // 2:]) / max(1, len(tau) - len(tau) // 2))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated seconds of the plant runs")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--motulator-seconds", type=float, default=1.0, help="simulated seconds of motulator")
    ap.add_argument("--no-loop-kernel", action="store_true",
                    help="leave XLA's small-while-loop threshold at its default (each kernel dispatched)")
    args = ap.parse_args()
    core = _pin_one_core()
    if not args.no_loop_kernel:
        from eol_cal.plant.simulate import configure_xla

        configure_xla()

    plant = bench_plant(args.seconds, args.batch)
    mot = bench_motulator(args.motulator_seconds)

    def rate(sim_s: float, wall: float) -> float:
        return sim_s / wall

    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"one CPU core (#{core}); simulated {args.seconds:g} s (plant), {args.motulator_seconds:g} s (motulator)")
    print(f"{'simulator':40s} {'cold x RT':>10s} {'warm x RT':>10s} {'warm/cpu':>10s}  (simulated s per wall s; "
          "last column per CPU s of the process, less sensitive to other load)")
    print(f"{'eol-cal plant, 1 motor':40s} {rate(args.seconds, plant['1/cold']):10.2f} "
          f"{rate(args.seconds, plant['1/warm']):10.2f} {rate(args.seconds, plant['1/warm/cpu']):10.2f}")
    b = args.batch
    print(f"{f'eol-cal plant, batch {b} (aggregate)':40s} {rate(b * args.seconds, plant[f'{b}/cold']):10.2f} "
          f"{rate(b * args.seconds, plant[f'{b}/warm']):10.2f} {rate(b * args.seconds, plant[f'{b}/warm/cpu']):10.2f}")
    print(f"{'motulator 0.5 PMSM current-vector ctrl':40s} {rate(args.motulator_seconds, mot['cold']):10.2f} "
          f"{rate(args.motulator_seconds, mot['warm']):10.2f} {rate(args.motulator_seconds, mot['warm/cpu']):10.2f}")
    mot_warm = rate(args.motulator_seconds, mot["warm"])
    if "torque_check" in mot:
        print(f"motulator mean torque over the second half: {mot['torque_check']:.3f} N*m (reference 3.2)")
    print(f"speed-up warm, 1 motor: {rate(args.seconds, plant['1/warm']) / mot_warm:.1f}x; "
          f"batch {b} aggregate: {rate(b * args.seconds, plant[f'{b}/warm']) / mot_warm:.1f}x")


if __name__ == "__main__":
    main()
