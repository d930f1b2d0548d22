"""The plant motors of tests/test_fit_mech.py, shared with bench/check_mech_fit.py: two motors
calibrated as the station does, one of them with an encoder too good to identify, and a
continuous capture cut into the windows a dyno records; plant motors through end of line and the
firmware twin's power-ups the identification switch is calibrated on."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.fingerprint import Fingerprint, WindowEdges
from eol_cal.analysis.fit import FitSpec
from eol_cal.analysis.fit.motors import FitOptions, fit_motors
from eol_cal.analysis.fit.table import block_from_result, uncompensated_block
from eol_cal.analysis.motor_result import MotorResult
from eol_cal.capture.data import Capture
from eol_cal.domain.motor_params import load_motor
from eol_cal.firmware.block import ParamBlock
from eol_cal.firmware.kinematics import SensorErrors, pulse_at
from eol_cal.firmware.mech_params import MechParams
from eol_cal.firmware.mech_sim import PowerUp
from eol_cal.firmware.options import parse_options
from eol_cal.plant.params import PlantSpec, sensor_errors, to_params
from eol_cal.plant.profile import Profile, load_profile
from eol_cal.plant.simulate import simulate
from eol_cal.plant.spread import Spread, load_spread
from eol_cal.plant.variation import draw_motor

BEST = parse_options("best")
MOTOR = load_motor("paper")


def weak(spec):
    """The same motor with an encoder 30 times better: its fingerprint is too weak to identify."""
    return spec.replace(serial=spec.serial + "W", enc_edge_err_deg=tuple(v / 30.0 for v in spec.enc_edge_err_deg))


def station_runs():
    """Two plant motors (seed 14, and seed 13 made weak) run through eol-default under their
    prepared blocks: ``(plants, runs)``."""
    plants = [draw_motor(14), weak(draw_motor(13))]
    prep = [uncompensated_block(p.serial[:16], MOTOR, calibrated_at=0, options=BEST) for p in plants]
    return plants, simulate(plants, load_profile("eol-default"), mode="estimated", blocks=prep, seed=14)


def station_windows(cap: Capture, prof: Profile) -> Capture:
    """The capture as a dyno records it: one window per profile segment after its ramp and 50 ms
    (the count lost between windows), joined with their ``segment_starts``."""
    keep = np.zeros(len(cap.t), bool)
    starts, t0 = [], 0.0
    for seg in prof.segments:
        a, b = t0 + seg.ramp_s + 0.05, t0 + seg.seconds
        keep |= (cap.t >= a) & (cap.t < b)
        starts.append(float(cap.t[np.searchsorted(cap.t, a)]))
        t0 += seg.seconds
    md = dict(cap.metadata, segment_starts=",".join(f"{s:.6f}" for s in starts))
    return Capture(t=cap.t[keep], channels={k: v[keep] for k, v in cap.channels.items()}, metadata=md,
                   truth=cap.truth, source="<windows>")


#: the power-ups the identification switch is calibrated on (firmware_params/MECH.md, "The switch,
#: calibrated"): 300 rpm (the fewest ticks per pitch: the hardest speed) either way from a random
#: angle, 0.002 mechanical degrees of timing noise a tick, 1.2 s (six revolutions; identifying takes three)
SWITCH_RPM = 300.0
SWITCH_JITTER_DEG = 0.002
SWITCH_SECONDS = 1.2


def switch_powerups(errors: SensorErrors, mech: MechParams, n: int, rng: np.random.Generator,
                    frame_pulse: int = 0) -> list[PowerUp]:
    """``n`` twin power-ups of the encoder ``errors`` under the block's mechanical part ``mech`` at
    :data:`SWITCH_RPM`, random start angle and direction; ``frame_pulse`` the model pulse that is
    the block's pulse 0 (:class:`~eol_cal.firmware.mech_sim.PowerUp`)."""
    out = []
    for _ in range(n):
        theta0 = float(rng.uniform(0, 2 * np.pi))
        rpm = float(rng.choice([-1.0, 1.0]) * SWITCH_RPM)
        out.append(PowerUp(errors, mech, theta0, rpm, jitter_deg=SWITCH_JITTER_DEG, frame_pulse=frame_pulse))
    return out


def pitch_error_spread(scale: float, name: str = "mech23") -> Spread:
    """The production spread ``name`` with the encoders' pitch errors ``scale`` x its own."""
    sp = load_spread(name)
    return dataclasses.replace(sp, sensors={**sp.sensors, "edge_sigma_mech_deg": sp.sensors["edge_sigma_mech_deg"] * scale})


@dataclass(frozen=True)
class EolMotor:
    """One plant motor through end of line (:func:`through_end_of_line`).

    plant : the motor; errors : its true sensor errors (the twin's); result : its fit result;
    block : the layout-2 block ``eol-cal table`` writes from it (None when the fit is not usable);
    frame_pulse : the model pulse that is the block's pulse 0 (the capture's count started there);
    prints, fingerprint : the fit's window edges and fingerprint.
    """

    plant: PlantSpec
    errors: SensorErrors
    result: MotorResult
    block: ParamBlock | None
    frame_pulse: int
    prints: list[WindowEdges | None] | None
    fingerprint: Fingerprint | None


def through_end_of_line(plants: list[PlantSpec], seed: int) -> list[EolMotor]:
    """The motors through end of line as the station does it: eol-default under the prepared
    block, ``fit_motors`` as ``eol-cal fit`` calls it, ``block_from_result`` (layout 2: the fitted
    fingerprint, ``MECH_COMP_ENABLE`` as the fit decided)."""
    prep = [uncompensated_block(p.serial[:16], MOTOR, calibrated_at=0, options=BEST) for p in plants]
    runs = simulate(plants, load_profile("eol-default"), mode="estimated", blocks=prep, seed=seed)
    fitted = fit_motors([r.capture for r in runs], FitOptions(spec=FitSpec(), capture_metrics=False,
                                                              estimator_options=BEST))
    out = []
    for p, run, res, mi in zip(plants, runs, fitted.results, fitted.inputs, strict=True):
        err = sensor_errors(to_params(p, np.zeros(16), np.zeros(16), 0.0, 0.0))
        err = err._replace(edge_error=np.asarray(err.edge_error, float), grid_offset=float(err.grid_offset))
        cap = run.capture
        usable = res.status == "ok" and res.mech is not None and res.mech.dirs != 0
        # one continuous capture: its only window is the block's frame, its count from sample 0
        if usable and res.mech is not None and res.mech.windows != (0,):
            raise ValueError(f"{p.serial}: windows {res.mech.windows}, one continuous capture expected")
        assert run.theta_m is not None
        pw = pulse_at(float(run.theta_m[0]), err, int(cap["enc_a"][0]), int(cap["enc_b"][0]))
        out.append(EolMotor(p, err, res, block_from_result(res, MOTOR, options=BEST) if usable else None, pw,
                            mi.prints, mi.fingerprint))
    return out
