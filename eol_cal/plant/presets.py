"""Plant presets: complete :class:`PlantSpec` descriptions of a motor on the test bench.

``paper`` reproduces the seed paper's bench (section IV): Table I motor at 60 rpm and
i_qo = 65 A (3.2 N*m) with k6 = 0.00062 N*m/A (eq. 18). How its ripple sources were chosen is
written down in ``docs/plant.md``; in short the 6th harmonic is the paper's, and what remains after
compensation (12th harmonic, order-1 unbalance, transducer noise, estimator error) was sized so
that the three peak-to-peak figures of ``eol_cal.analysis.metrics`` land on the paper's 6.25 %,
3.1 % and 1.6 %.
"""

from __future__ import annotations

import numpy as np

from eol_cal.errors import InputError
from eol_cal.firmware.kinematics import draw_sensor_errors
from eol_cal.domain.motor_params import load_motor
from eol_cal.plant.params import PlantSpec


def _sensor_errors_deg(seed: int, N_enc: int) -> tuple[tuple[float, ...], tuple[float, ...], float]:
    err = draw_sensor_errors(np.random.default_rng(seed), N_enc)
    return (tuple(float(v) for v in np.degrees(err.edge_error)),
            tuple(float(v) for v in np.degrees(np.asarray(err.hall_offset).ravel())),
            float(np.degrees(err.grid_offset)))


def paper(serial: str = "PAPER-0001") -> PlantSpec:
    """The seed paper's bench (Figs. 10-12)."""
    motor = load_motor("paper")
    edge, hall, grid = _sensor_errors_deg(2010, motor.N_enc)
    return PlantSpec(
        motor=motor, serial=serial, temp_degC=70.0,
        k6=0.00062, phase_k6=0.0,            # seed eq. (17)-(18): -k6*i_qo*sin(6*theta)
        c6=0.004, phase_c6=0.6,               # cogging, a tenth of the load-dependent part at 65 A
        c12=0.013, phase_c12=4.712, k12=0.0, phase_k12=0.0,
        c18=0.0, phase_c18=0.0, k18=0.0, phase_k18=0.0,
        unb1=0.007, phase_unb1=0.4,
        enc_edge_err_deg=edge, hall_err_deg=hall, grid_offset_deg=grid,
        tq_bw_hz=60.0, tq_noise_nm=0.002, tq_lsb_nm=0.0005,
        i_noise_a=0.15, i_lsb_a=0.08,
    )


PRESETS = {"paper": paper}


def preset_spec(name: str, serial: str | None = None) -> PlantSpec:
    """A preset by name (:data:`PRESETS`), optionally with another serial."""
    if name not in PRESETS:
        raise InputError(None, "preset", f"unknown plant preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]() if serial is None else PRESETS[name](serial=serial)
