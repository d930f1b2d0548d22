"""Kinematic sensor-signal model: encoder A/B and hall levels from the rotor's mechanical angle.

Shared by the estimator's golden vectors and benchmark and by the plant's sensors, so the ECU
sees the same signal model everywhere. Pure functions of position (no time, no state), written
with ``xp`` operations so they run under numpy and trace under ``jax.numpy``:

* Channel A has ``N_enc`` pulses per mechanical revolution, high for half a pitch; pulse ``k``
  rises at mechanical angle ``grid_offset + 2*pi*k/N_enc + edge_error[k]``. The whole pulse
  (rising and falling edge) carries the placement error of its magnet pole, and channel B reads
  the same wheel a quarter pitch later, so in forward rotation A leads B by a quarter pitch.
* Hall sensor U, V, W (bits 0, 1, 2) is nominally high for electrical angle in
  [0, 180), [120, 300), [240, 60) degrees (firmware contract section 2); each of its two
  switching points has its own mounting error ``hall_offset[sensor, 0 rising | 1 falling]``
  (rad, electrical, "rising"/"falling" as seen in forward rotation).
* Electrical angle ``theta_e = (P/2) * theta_m``: mechanical angle 0 is electrical angle 0.

Being position-based, the model has no hysteresis and no chatter; glitches (bounce, lost
pulses, hall states 0/7) are injected on top of the sampled levels where a test needs them.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware.contract import NOMINAL_HALL_ANGLE


class SensorErrors(NamedTuple):
    """Manufacturing errors of one motor's position sensors.

    edge_error : array (N_enc,)
        Placement error of encoder pulse k (rad, mechanical), |error| < a quarter pitch.
    hall_offset : array (3, 2)
        Switching-point error of hall U, V, W at its rising [., 0] and falling [., 1] point
        in forward rotation (rad, electrical).
    grid_offset : float
        Mechanical angle of pulse 0's nominal rising edge (rad, mechanical).
    """

    edge_error: Any
    hall_offset: Any
    grid_offset: Any


def ideal_sensor_errors(N_enc: int, grid_offset: float = 0.0) -> SensorErrors:
    """Error-free sensors (edges on the nominal grid, halls at their nominal angles)."""
    return SensorErrors(np.zeros(N_enc), np.zeros((3, 2)), float(grid_offset))


def draw_sensor_errors(rng: np.random.Generator, N_enc: int, edge_sigma_mech_deg: float = 0.1,
                       hall_sigma_elec_deg: float = 2.0 / 3.0, hall_max_elec_deg: float = 2.0,
                       grid_offset: float | None = None) -> SensorErrors:
    """Draw one motor's sensor errors.

    Parameters
    ----------
    rng : numpy Generator
    N_enc : int
        Encoder pulses per mechanical revolution.
    edge_sigma_mech_deg : float
        Standard deviation of each pulse's placement error (mechanical degrees), normal.
    hall_sigma_elec_deg, hall_max_elec_deg : float
        Hall switching-point errors: normal with this standard deviation, truncated at
        +-hall_max_elec_deg (electrical degrees) - "within 2 electrical degrees" read as 3 sigma.
    grid_offset : float, optional
        Mechanical angle of pulse 0 (rad); uniform over one pitch when omitted.

    Returns
    -------
    SensorErrors
    """
    pitch = 2.0 * math.pi / N_enc
    edge = np.radians(edge_sigma_mech_deg) * rng.standard_normal(N_enc)
    edge = np.clip(edge, -0.2 * pitch, 0.2 * pitch)
    hall = np.empty(6)
    for i in range(6):
        x = rng.standard_normal() * hall_sigma_elec_deg
        while abs(x) > hall_max_elec_deg:
            x = rng.standard_normal() * hall_sigma_elec_deg
        hall[i] = x
    g = rng.uniform(0.0, pitch) if grid_offset is None else float(grid_offset)
    return SensorErrors(edge, np.radians(hall).reshape(3, 2), g)


def _channel(u: Any, eps_table: Any, N_enc: int, xp: Any) -> Any:
    # u in pitches; pulse k nominally high on [k, k + 0.5), shifted by its error eps (pitches).
    k = xp.floor(u + 0.25)
    kk = xp.mod(k, N_enc).astype(xp.int32)
    fr = u - k - xp.asarray(eps_table)[kk]
    return ((fr >= 0.0) & (fr < 0.5)).astype(xp.int32)


def encoder_hall_signals(theta_m: Array, poles: int, N_enc: int,
                         errors: SensorErrors | None = None, xp: ArrayModule = np) -> tuple[Array, Array, Array]:
    """Encoder and hall levels at mechanical rotor angle ``theta_m``.

    Parameters
    ----------
    theta_m : array_like
        Mechanical rotor angle (rad), any shape; + is forward rotation. Under float32 (JAX)
        pass it reduced to [0, 2*pi) to keep its resolution.
    poles : int
        Number of poles P.
    N_enc : int
        Pulses per mechanical revolution of channel A.
    errors : SensorErrors, optional
        Sensor errors; ideal sensors when omitted.
    xp : numpy or jax.numpy

    Returns
    -------
    enc_a, enc_b : int32 arrays (0/1), hall : int32 array (U | V<<1 | W<<2), all of
    ``theta_m``'s shape.
    """
    if errors is None:
        errors = ideal_sensor_errors(N_enc)
    theta_m = xp.asarray(theta_m)
    scale = N_enc / (2.0 * math.pi)
    eps = xp.asarray(errors.edge_error) * scale
    u = (theta_m - errors.grid_offset) * scale
    enc_a = _channel(u, eps, N_enc, xp)
    enc_b = _channel(u - 0.25, eps, N_enc, xp)

    theta_e = theta_m * (poles / 2.0)
    off = xp.asarray(errors.hall_offset)
    two_pi = 2.0 * math.pi
    hall = xp.zeros(xp.shape(theta_m), xp.int32)  # theta_m is an array here (asarray above)
    for j in range(3):
        rise = j * (two_pi / 3.0) + off[j, 0]
        fall = j * (two_pi / 3.0) + math.pi + off[j, 1]
        high = xp.mod(theta_e - rise, two_pi) < xp.mod(fall - rise, two_pi)
        hall = hall + high.astype(xp.int32) * (1 << j)
    return enc_a, enc_b, hall


def electrical_angle(theta_m: Array, poles: int, xp: ArrayModule = np) -> Array:
    """True electrical angle (rad, [0, 2*pi)) of mechanical angle ``theta_m`` (rad)."""
    return xp.mod(xp.asarray(theta_m) * (poles / 2.0), 2.0 * math.pi)


def speed_profile_angle(segments: Any, tick_hz: float, theta0: float = 0.0) -> np.ndarray:
    """Mechanical angle at every tick of a piecewise-linear speed profile.

    Parameters
    ----------
    segments : sequence of (seconds, rpm_start, rpm_end)
        Consecutive segments; the speed (rpm, mechanical, signed: + forward) ramps linearly
        from ``rpm_start`` to ``rpm_end`` over ``seconds``.
    tick_hz : float
        Sample rate (Hz); sample n is at t = n / tick_hz.
    theta0 : float
        Mechanical angle at t = 0 (rad).

    Returns
    -------
    ndarray (float64)
        theta_m (rad) at each tick, exact for the piecewise-linear speed.
    """
    out = []
    theta = float(theta0)
    for seconds, rpm0, rpm1 in segments:
        n = int(round(seconds * tick_hz))
        tau = np.arange(n) / tick_hz
        w0 = rpm0 * 2.0 * math.pi / 60.0
        acc = (rpm1 - rpm0) * 2.0 * math.pi / 60.0 / seconds if seconds > 0 else 0.0
        out.append(theta + w0 * tau + 0.5 * acc * tau**2)
        theta = theta + w0 * n / tick_hz + 0.5 * acc * (n / tick_hz) ** 2
    return np.concatenate(out) if out else np.zeros(0)


#: hall sensor and switching point (``hall_offset[sensor, 0 rising | 1 falling]``) at which each
#: state s begins in forward rotation (contract section 2: 5 at 0, 1 at 60, 3 at 120, 2 at 180,
#: 6 at 240, 4 at 300 degrees)
_STATE_SWITCH = {5: (0, 0), 1: (2, 1), 3: (1, 0), 2: (0, 1), 6: (2, 0), 4: (1, 1)}


def hall_angle_of(errors: SensorErrors) -> tuple[float, ...]:
    """The true ``hall_angle`` table of a motor's halls (rad electrical, entry s-1: where state s
    begins in forward rotation): the contract's nominal table plus each switching point's error."""
    off = np.asarray(errors.hall_offset, dtype=float)
    return tuple(float(NOMINAL_HALL_ANGLE[s - 1] + off[_STATE_SWITCH[s]]) for s in range(1, 7))


def fingerprint_of(errors: SensorErrors, poles: int) -> tuple[np.ndarray, float]:
    """The true fingerprint of a motor's encoder in its own pulse numbering (firmware_params/MECH.md).

    Returns ``(fingerprint, grid_phase)``: the placement error of each A edge (rad electrical,
    mean 0; entry ``2k`` pulse k's forward edge, ``2k + 1`` its reverse edge, which in this model
    carries the same error) and the electrical angle (rad, [0, 2*pi)) of the frame's quadrature
    boundary 0 on the mean grid: a quarter pitch before pulse 0's mean rising edge. This is what a
    perfect end-of-line measurement writes into a layout-2 block whose frame is the model's pulse
    numbering.
    """
    e = np.asarray(errors.edge_error, dtype=float)
    N = e.size
    pp = poles / 2.0
    f = pp * (e - e.mean())
    fp = np.repeat(f, 2)
    quarter = pp * 2.0 * math.pi / N / 4.0
    grid_phase = float(np.mod(pp * (errors.grid_offset + e.mean()) - quarter, 2.0 * math.pi))
    return fp, grid_phase


def pulse_at(theta_m: float, errors: SensorErrors, a0: int, b0: int) -> int:
    """The model's pulse index whose A rising edge is quadrature boundary 1 of a count started at
    mechanical angle ``theta_m`` with levels ``(a0, b0)``: the offset ``r`` the firmware's identifier
    must find when the block's frame is the model's pulse numbering (firmware pulse 0 = this pulse)."""
    N = len(errors.edge_error)
    u = (float(theta_m) - float(errors.grid_offset)) * N / (2.0 * math.pi)
    phase = 2 * int(b0) + (int(a0) ^ int(b0))
    return int(round(u - phase / 4.0 + 0.125)) % N
