"""Average model of the 12 V space-vector PWM inverter.

Over one PWM period the inverter delivers, on average, the commanded stationary-frame voltage
vector as long as it lies inside the hexagon's inscribed circle of radius ``u_dc/sqrt(3)`` (the
linear range of SVPWM); a longer command is shortened to that circle keeping its angle. Dead time
(optional) loses ``u_dc * t_dead * f_pwm`` volts in each phase against that phase's current.
"""

from __future__ import annotations

import math

from eol_cal.numerics.arrays import Array, ArrayModule

SQRT3 = math.sqrt(3.0)


def limit_voltage(u_alpha: Array, u_beta: Array, u_dc: Array, xp: ArrayModule) -> tuple[Array, Array]:
    """Shorten ``(u_alpha, u_beta)`` (V) to the SVPWM linear limit ``u_dc/sqrt(3)``."""
    u_max = u_dc / SQRT3
    mag = xp.sqrt(u_alpha * u_alpha + u_beta * u_beta)
    scale = xp.minimum(1.0, u_max / xp.maximum(mag, 1e-9))
    return u_alpha * scale, u_beta * scale


def dead_time_error(i_a: Array, i_b: Array, i_c: Array, u_dead: Array, xp: ArrayModule) -> tuple[Array, Array]:
    """Average voltage lost to dead time, as an alpha-beta vector (V).

    ``u_dead = u_dc * t_dead * f_pwm`` (V) per phase, opposing each phase current (A); the sign
    is smoothed over 0.5 A because the real switch-node voltage follows the current through zero.
    """
    e_a = -u_dead * xp.tanh(i_a / 0.5)
    e_b = -u_dead * xp.tanh(i_b / 0.5)
    e_c = -u_dead * xp.tanh(i_c / 0.5)
    return (2.0 * e_a - e_b - e_c) / 3.0, (e_b - e_c) / SQRT3
