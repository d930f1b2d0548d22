"""Look-up lead of the compensator: the current loop's lag at the 6th harmonic.

The compensating current ``i_qc`` is a command; the torque follows the current, and the current
lags its command. To cancel the ripple at angle theta the firmware must therefore read the table
ahead, at ``theta_hat + omega_hat * lead_s`` (contract section 2). Model of the lag:

- the closed current loop as a first-order low-pass with the bandwidth the PI controller is tuned
  for (``MotorParams.current_bw_hz``): phase ``atan(omega_6 / omega_bw)``;
- the controller's sample-and-hold delays: half a current-control period (the voltage reference is
  held between updates) and half a PWM period (the modulator holds each duty cycle):
  ``T_d = 0.5 / f_cc + 0.5 / f_pwm``, phase ``omega_6 * T_d``.

With ``omega_6 = 6 |omega_e|`` at the operating speed, ``lead_s = lag / omega_6``. At low speed this
tends to ``1 / omega_bw + T_d`` (the loop's time constant plus the hold delays).
"""

from __future__ import annotations

import math

from eol_cal.domain.motor_params import MotorParams


def hold_delay_s(motor: MotorParams) -> float:
    """Sample-and-hold delay of the current control and the PWM (s): ``0.5/f_cc + 0.5/f_pwm``."""
    return 0.5 / motor.f_cc + 0.5 / motor.f_pwm


def current_loop_lag_rad(omega_h: float, motor: MotorParams) -> float:
    """Phase lag of the current response at angular frequency ``omega_h`` (rad/s), in rad.

    Parameters
    ----------
    omega_h : float
        Angular frequency of the commanded harmonic (rad/s), >= 0.
    motor : MotorParams
        ``current_bw_hz`` (Hz), ``f_cc`` and ``f_pwm`` (Hz).
    """
    omega_bw = 2.0 * math.pi * motor.current_bw_hz
    return math.atan(omega_h / omega_bw) + omega_h * hold_delay_s(motor)


def auto_lead_s(speed_rpm: float, motor: MotorParams, order: int = 6) -> float:
    """Look-up lead (s) that makes up for the current loop's lag at ``order`` x the electrical speed.

    Parameters
    ----------
    speed_rpm : float
        Operating mechanical speed (rpm), either sign.
    motor : MotorParams
        Poles, current bandwidth and rates.
    order : int
        Harmonic the lead is matched at (6: the table's fundamental).

    Returns
    -------
    float
        lead_s (s), > 0.
    """
    omega_e = abs(speed_rpm) * 2.0 * math.pi / 60.0 * motor.pole_pairs
    omega_h = order * omega_e
    if omega_h == 0.0:
        return 1.0 / (2.0 * math.pi * motor.current_bw_hz) + hold_delay_s(motor)
    return current_loop_lag_rad(omega_h, motor) / omega_h
