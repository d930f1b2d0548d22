"""Motor-to-motor production spread: ``--seed`` draws one motor as built.

Distributions (one motor per seed, numpy's PCG64 ``default_rng(seed)``; documented in
``docs/plant.md``):

======================  ==============================================================
k6                      normal, mean 0.00062 N*m/A (seed eq. 18), sigma 15 %, >= 0
phase_k6                normal, mean 0, sigma 0.15 rad (about 9 electrical degrees of 6th)
c6 (cogging)            uniform 0.002 .. 0.008 N*m, phase uniform [0, 2*pi)
c12, k12                c12 uniform 0.004 .. 0.016 N*m; k12 half-normal sigma 0.00004 N*m/A;
                        phases uniform
c18                     uniform 0 .. 0.004 N*m, phase uniform (k18 = 0)
unb1 (order 1)          Rayleigh, scale 0.005 N*m, phase uniform
R_s                     R_s_scale normal, mean 1, sigma 3 % (wire and joint spread)
temperature             uniform 20 .. 40 degC winding temperature at test (R_s follows it)
encoder, halls          :func:`eol_cal.firmware.kinematics.draw_sensor_errors`: pulse placement
                        sigma 0.1 mechanical degrees, hall switching points sigma 2/3
                        electrical degrees truncated at 2, grid offset uniform over a pitch
======================  ==============================================================

The bench itself (transducer, shaft, dyno) is the base preset's.
"""

from __future__ import annotations

import math

import numpy as np

from eol_cal.plant.params import PlantSpec
from eol_cal.plant.presets import paper

K6_NOMINAL = 0.00062


def draw_motor(seed: int, base: PlantSpec | None = None, serial: str | None = None) -> PlantSpec:
    """One motor from the production spread around ``base`` (default: the ``paper`` bench).

    Parameters
    ----------
    seed : int
        Seed of the draw; the same seed gives the same motor.
    base : PlantSpec, optional
        Bench and nominal motor data.
    serial : str, optional
        Serial; default ``SIM-<seed>``.
    """
    from eol_cal.firmware.kinematics import draw_sensor_errors

    base = paper() if base is None else base
    rng = np.random.default_rng(seed)
    u = lambda: float(rng.uniform(0.0, 2.0 * math.pi))  # noqa: E731 - a phase
    k6 = max(0.0, float(rng.normal(K6_NOMINAL, 0.15 * K6_NOMINAL)))
    spec = base.replace(
        serial=serial if serial is not None else f"SIM-{seed:06d}",
        k6=k6, phase_k6=float(rng.normal(0.0, 0.15)),
        c6=float(rng.uniform(0.002, 0.008)), phase_c6=u(),
        c12=float(rng.uniform(0.004, 0.016)), phase_c12=u(),
        k12=abs(float(rng.normal(0.0, 0.00004))), phase_k12=u(),
        c18=float(rng.uniform(0.0, 0.004)), phase_c18=u(), k18=0.0, phase_k18=0.0,
        unb1=float(rng.rayleigh(0.005)), phase_unb1=u(),
        R_s_scale=float(rng.normal(1.0, 0.03)), temp_degC=float(rng.uniform(20.0, 40.0)),
    )
    err = draw_sensor_errors(rng, base.motor.N_enc)
    return spec.replace(
        enc_edge_err_deg=tuple(float(v) for v in np.degrees(err.edge_error)),
        hall_err_deg=tuple(float(v) for v in np.degrees(np.asarray(err.hall_offset).ravel())),
        grid_offset_deg=float(np.degrees(err.grid_offset)),
    )


def vary(base: PlantSpec, seed: int) -> PlantSpec:
    """:func:`draw_motor` around ``base``, keeping its serial (the dyno simulator's call)."""
    return draw_motor(seed, base, serial=base.serial)


def draw_spec(seed: int, serial: str | None = None) -> PlantSpec:
    """:func:`draw_motor` around the ``paper`` bench (the station demo's call)."""
    return draw_motor(seed, serial=serial)
