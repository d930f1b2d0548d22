"""The dyno: a speed-controlled load machine coupled to the motor through a torsion shaft.

Two inertias (motor rotor ``J``, dyno ``J_dyno``) joined by a shaft of stiffness ``K_shaft``
(N*m/rad) and damping ``D_shaft`` (N*m*s/rad); the torque transducer sits in that shaft and reads
``T_shaft = K_shaft*twist + D_shaft*(omega_m - omega_d)`` (positive when the motor drives the
dyno). The dyno holds its speed reference with a PI speed controller (its own drive, fast
compared to the profile, slow compared to the ripple). Integration is semi-implicit Euler at the
PWM tick, stable for the shaft mode as long as ``omega_n*dt << 2`` (0.1 for the paper bench).
The twist is a state of its own so that float32 keeps it exact at any absolute angle.
The gains and the frequency response of this line are in :mod:`eol_cal.bench`.
"""

from __future__ import annotations

from typing import Any

from eol_cal.wrap import wrap_2pi

def shaft_torque(twist: Any, omega_m: Any, omega_d: Any, p: Any) -> Any:
    """Torque in the shaft (N*m) from its twist (rad) and the two speeds (rad/s, mechanical)."""
    return p.K_shaft * twist + p.D_shaft * (omega_m - omega_d)


def mech_step(
    theta_m: Any, twist: Any, omega_m: Any, omega_d: Any, x_dyno: Any,
    T_rotor: Any, omega_ref: Any, p: Any, dt: float, xp: Any,
) -> tuple[Any, Any, Any, Any, Any, Any]:
    """Advance the shaft line by one tick.

    Parameters
    ----------
    theta_m : mechanical rotor angle (rad, kept in [0, 2*pi)); twist : shaft twist (rad);
    omega_m, omega_d : motor and dyno speed (rad/s); x_dyno : dyno PI integrator (N*m);
    T_rotor : electromagnetic torque minus ripple acting on the rotor (N*m);
    omega_ref : dyno speed reference (rad/s, signed); p : PlantParams; dt : tick (s).

    Returns
    -------
    theta_m, twist, omega_m, omega_d, x_dyno, T_shaft (N*m, at the start of the tick)
    """
    T_shaft = shaft_torque(twist, omega_m, omega_d, p)
    err = omega_ref - omega_d
    T_dyno = p.Kp_dyno * err + x_dyno
    x_dyno = x_dyno + p.Ki_dyno * dt * err
    omega_m = omega_m + (dt / p.J) * (T_rotor - p.B * omega_m - T_shaft)
    omega_d = omega_d + (dt / p.J_dyno) * (T_shaft + T_dyno)
    twist = twist + dt * (omega_m - omega_d)
    theta_m = theta_m + dt * omega_m
    theta_m = wrap_2pi(theta_m, xp)
    return theta_m, twist, omega_m, omega_d, x_dyno, T_shaft
