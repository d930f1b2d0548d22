"""Measurement chain of the bench and the ECU: torque transducer, phase-current sensors.

The encoder and hall levels come from the firmware reference's kinematic signal model
(:func:`eol_cal.firmware.kinematics.encoder_hall_signals`, the same edge-placement and
hall-mounting error model the estimator is tested against), sampled every tick at the rotor's
actual angle by :mod:`eol_cal.plant.simulate`.
"""

from __future__ import annotations

import math
from typing import Protocol

from eol_cal.numerics.arrays import Array, ArrayModule


class SensorCoefficients(Protocol):
    """The transducers' coefficients (a plant's parameters hold them)."""

    @property
    def tq_gain(self) -> Array: ...  # 1, from lowpass_gain

    @property
    def tq_noise_nm(self) -> Array: ...  # N*m rms

    @property
    def tq_lsb_nm(self) -> Array: ...  # N*m

    @property
    def i_noise_a(self) -> Array: ...  # A rms

    @property
    def i_lsb_a(self) -> Array: ...  # A


def lowpass_gain(bw_hz: Array, dt: float, xp: ArrayModule) -> Array:
    """Per-tick gain of an exact first-order low-pass with corner ``bw_hz`` (Hz)."""
    return 1.0 - xp.exp(-2.0 * math.pi * bw_hz * dt)


def quantise(x: Array, lsb: Array, xp: ArrayModule) -> Array:
    """An ADC's mid-tread quantisation to steps of ``lsb`` (same unit as ``x``)."""
    return xp.round(x / lsb) * lsb


def transducer_step(y: Array, T_shaft: Array, noise: Array, p: SensorCoefficients, xp: ArrayModule) -> tuple[Array, Array]:
    """Torque transducer: first-order bandwidth, additive noise, ADC resolution.

    Parameters
    ----------
    y : filtered state (N*m); T_shaft : shaft torque (N*m); noise : a standard normal draw;
    p : SensorCoefficients with ``tq_gain`` (from :func:`lowpass_gain`), ``tq_noise_nm`` (N*m rms),
    ``tq_lsb_nm`` (N*m).

    Returns
    -------
    (new state, reading) both N*m: the state after the tick under the shaft torque held over it,
    and the reading of the output half a tick on, the mean of the states at the tick's start and
    end (to O(dt^2)): the plant holds each tick's torque from the tick's start angle, half a tick
    behind its continuous model, so this reading is in step with that angle (issue 34: the state
    at the tick's end, a tick ahead, led the continuous chain by 25 us).
    """
    y_next = y + p.tq_gain * (T_shaft - y)
    return y_next, quantise(0.5 * (y + y_next) + p.tq_noise_nm * noise, p.tq_lsb_nm, xp)


def current_reading(i_x: Array, noise: Array, p: SensorCoefficients, xp: ArrayModule) -> Array:
    """A phase-current sensor with noise ``i_noise_a`` (A rms) and ADC step ``i_lsb_a`` (A)."""
    return quantise(i_x + p.i_noise_a * noise, p.i_lsb_a, xp)

