"""The plant motors of tests/test_fit_mech.py, shared with bench/check_mech_fit.py: two motors
calibrated as the station does, one of them with an encoder too good to identify, and a
continuous capture cut into the windows a dyno records."""

from __future__ import annotations

import numpy as np

from eol_cal.analysis.fit.table import uncompensated_block
from eol_cal.capture.data import Capture
from eol_cal.firmware.options import parse_options
from eol_cal.domain.motor_params import load_motor
from eol_cal.plant.profile import Profile, load_profile
from eol_cal.plant.simulate import simulate
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
