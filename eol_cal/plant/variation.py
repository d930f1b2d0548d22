"""Motor-to-motor production spread: ``--seed`` draws one motor as built.

The distributions are data: a spread file (:mod:`eol_cal.plant.spread`; the default one is
``eol_cal/spreads/default.toml``, documented there and in ``docs/plant.md``). In short, the
default spread:

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

from eol_cal.plant.params import PlantSpec
from eol_cal.plant.spread import Spread, load_spread

K6_NOMINAL = 0.00062


def draw_motor(seed: int, base: PlantSpec | None = None, serial: str | None = None,
               spread: Spread | None = None) -> PlantSpec:
    """One motor from the production spread around ``base`` (default: the ``paper`` bench).

    Parameters
    ----------
    seed : int
        Seed of the draw; the same seed gives the same motor.
    base : PlantSpec, optional
        Bench and nominal motor data.
    serial : str, optional
        Serial; default ``SIM-<seed>``.
    spread : Spread, optional
        The distributions (:func:`eol_cal.plant.spread.load_spread`); default the built-in
        ``default`` spread.
    """
    return (spread or load_spread("default")).draw(seed, base, serial)


def vary(base: PlantSpec, seed: int) -> PlantSpec:
    """:func:`draw_motor` around ``base``, keeping its serial (the dyno simulator's call)."""
    return draw_motor(seed, base, serial=base.serial)


def draw_spec(seed: int, serial: str | None = None) -> PlantSpec:
    """:func:`draw_motor` around the ``paper`` bench (the station demo's call)."""
    return draw_motor(seed, serial=serial)
