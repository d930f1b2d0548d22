"""A faster lead-in: does the firmware learn as well when the shaft turns its settling faster?

After each flash the ECU resets, and the shaft turns before a capture counts (the lead-in,
:mod:`eol_cal.firmware.settling`): with the ``best`` estimator 1.5 revolutions of pitch-error
learning, with a mechanical-order block four revolutions of identification. The station turns
them at the capture's own speed (60 rpm on eol-default: 1.5 s and 4 s). Turning them at a higher
speed and ramping down would save shaft time, but the estimator measures pulse periods in PWM
ticks (312 a pulse at 60 rpm, 62 at 300, 31 at 600), so what it learns may be coarser.

This bench asks the built-in plant (the firmware twin's estimator and identifier, production
motors drawn with their encoder pitch errors and unbalance), for each lead-in speed: the motor
compensated with its true layout-2 block (every order; ``--case calibration``: the cycle's
uncompensated prepare block), the lead-in at that speed from power-up,
a ramp to 60 rpm at 1000 rpm/s and 0.3 s there (``--settle-s``; the station's
:func:`eol_cal.firmware.settling.lead_in_plan`), then a 1.2 s capture at 60 rpm, 65 A.
Against the lead-in all at 60 rpm (`dyno.lead_in = "at-point"`) it prints over the capture: the
estimated angle's error (rms and worst, electrical degrees), the share of samples with the
mechanical compensation identified and running, the compensated filtered p-p (% of the mean
torque, docs/metrics.md), and the lead-in's shaft time.

    python bench/bench_lead_in.py [--motors 8] [--speeds 60,150,300,600] [--case verification|calibration]
        [--settle-s 0.3]
"""

from __future__ import annotations

import argparse
import math
import statistics

import numpy as np

from eol_cal.analysis.metrics import ripple_pp
from eol_cal.firmware.block import ParamBlock
from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE
from eol_cal.firmware.options import parse_options
from eol_cal.firmware.settling import FIRST_EDGES_S, block_settle_s
from eol_cal.plant import variation
from eol_cal.plant.ecu_model import true_block
from eol_cal.plant.presets import preset_spec
from eol_cal.plant.profile import Profile, ProfileSegment
from eol_cal.plant.simulate import simulate
from eol_cal.plant.params import PlantSpec
from eol_cal.numerics.wrap import wrap_pi

CAPTURE_RPM = 60.0
CAPTURE_S = 1.2
I_QO_A = 65.0
RAMP_RPM_S = 1000.0


def one(spec: PlantSpec, block: ParamBlock, lead_rpm: float, mode: str, settle_at_point_s: float) -> dict[str, float]:
    """The capture at 60 rpm after a lead-in at ``lead_rpm``: its figures and the lead-in's time."""
    settle = block_settle_s(block, lead_rpm)
    if lead_rpm == CAPTURE_RPM:  # the station today: the lead-in is the pre-roll at the capture's point
        profile = Profile("lead-in", (ProfileSegment(CAPTURE_RPM, CAPTURE_S, iq=I_QO_A),))
        lead_s = settle
    else:
        ramp = abs(lead_rpm - CAPTURE_RPM) / RAMP_RPM_S
        skip_s = ramp + settle_at_point_s
        lead_s = settle + skip_s
        profile = Profile("lead-in", (ProfileSegment(lead_rpm, 1e-3, iq=I_QO_A),
                                      ProfileSegment(CAPTURE_RPM, skip_s + CAPTURE_S, iq=I_QO_A, ramp_s=ramp)))
    result = simulate(spec, profile, mode=mode, blocks=block, pre_roll_s=settle, seed=1)[0]
    cap = result.capture
    keep = cap.t >= cap.t[-1] - CAPTURE_S + 0.5 / spec.motor.f_pwm
    err = np.degrees(wrap_pi(np.asarray(result.theta_hat)[keep] - np.asarray(result.theta_r)[keep]))
    theta = np.unwrap(np.asarray(result.theta_r)[keep])
    pp = ripple_pp(cap.t[keep] - cap.t[keep][0], cap.channels["torque"][keep], theta, poles=spec.motor.poles,
                   i_qo=cap.channels["iq_ref"][keep] if "iq_ref" in cap.channels else None)
    mech = np.asarray(result.mech_active)[keep] if result.mech_active is not None else np.zeros(1)
    return {"lead_s": lead_s, "err_rms": float(np.sqrt(np.mean(err ** 2))), "err_max": float(np.max(np.abs(err))),
            "mech": float(np.mean(mech)), "pp": float(pp.filtered_pct)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motors", type=int, default=8)
    parser.add_argument("--speeds", default="60,150,300,600")
    parser.add_argument("--settle-s", type=float, default=FIRST_EDGES_S,
                        help="s turned at 60 rpm after the ramp before the capture counts (the station's: "
                             "eol_cal.firmware.settling.FIRST_EDGES_S)")
    parser.add_argument("--case", choices=("verification", "calibration"), default="verification",
                        help="verification: the true layout-2 block, compensated (four revolutions);"
                             " calibration: the cycle's prepare block (no compensation, 1.5 revolutions)")
    opts = parser.parse_args()
    speeds = [float(s) for s in opts.speeds.split(",")]
    flags = FLAG_INTERP_ENABLE | parse_options("best")
    if opts.case == "verification":
        flags |= FLAG_COMP_ENABLE | FLAG_MECH_COMP_ENABLE
    mode = "compensated" if opts.case == "verification" else "estimated"
    rows: dict[float, list[dict[str, float]]] = {v: [] for v in speeds}
    for k in range(opts.motors):
        spec = variation.vary(preset_spec("paper", serial=f"L-{k}"), 100 + k)
        block = true_block(spec, flags=flags, mech=opts.case == "verification")
        for v in speeds:
            rows[v].append(one(spec, block, v, mode, opts.settle_s))
    what = ("true layout-2 block, compensated" if opts.case == "verification"
            else "the prepare block: not compensated, so its p-p is the motor's own")
    print(f"{opts.case}: {opts.motors} motors (production draws, 'best' estimator, {what}), capture 60 rpm 65 A;"
          " median (worst) over the motors")
    print(f"{'lead-in at':>10s} {'shaft time s':>13s} {'angle err rms deg':>18s} {'worst deg':>10s}"
          f" {'mech running':>13s} {'p-p %':>12s}")
    for v, rs in rows.items():
        med = {key: statistics.median(r[key] for r in rs) for key in ("lead_s", "err_rms", "pp")}
        worst_pp = max(r["pp"] for r in rs)
        print(f"{v:7.0f} rpm {med['lead_s']:13.2f} {med['err_rms']:18.3f} {max(r['err_max'] for r in rs):10.2f}"
              f" {min(r['mech'] for r in rs):13.2f} {med['pp']:7.2f} ({worst_pp:.2f})")
    print("lead-in at 60 rpm: all of it at the capture's point (at-point); the others add the"
          f" ramp to 60 rpm at {RAMP_RPM_S:g} rpm/s and {opts.settle_s:g} s at 60 rpm to their shaft time")
    assert math.isfinite(sum(r["pp"] for rs in rows.values() for r in rs))


if __name__ == "__main__":
    main()
