"""SPMSM in the rotor dq frame (seed eqs. 1-3), one PWM tick at a time.

Voltage equations (seed eq. 2)::

    L_d di_d/dt = v_d - R_s i_d + omega_r L_q i_q
    L_q di_q/dt = v_q - R_s i_q - omega_r L_d i_d - omega_r psi_f

Over one PWM period ``dt`` the inverter holds its average voltage, so each axis is a first-order
R-L circuit driven by a constant: it is integrated exactly (``a = exp(-R_s dt / L)``) with the
speed-dependent coupling and back-EMF frozen over the tick. At 20 kHz and the paper's
L/R = 3 ms this is exact to well below the current sensors' resolution.
"""

from __future__ import annotations

from typing import Protocol

from eol_cal.numerics.arrays import Array, ArrayModule


class MachineCoefficients(Protocol):
    """The dq machine's coefficients (a plant's parameters hold them)."""

    @property
    def a_d(self) -> Array: ...  # 1, from rl_coefficients

    @property
    def b_d(self) -> Array: ...  # 1/ohm

    @property
    def a_q(self) -> Array: ...  # 1

    @property
    def b_q(self) -> Array: ...  # 1/ohm

    @property
    def L_d(self) -> Array: ...  # H

    @property
    def L_q(self) -> Array: ...  # H

    @property
    def psi_f(self) -> Array: ...  # V*s


def rl_coefficients(R_s: Array, L: Array, dt: float, xp: ArrayModule) -> tuple[Array, Array]:
    """Exact discretisation of ``L di/dt = v - R_s i`` over ``dt`` (s).

    Returns ``(a, b)`` with ``i(t+dt) = a*i(t) + b*v``; ``a`` is 1, ``b`` is 1/ohm.
    """
    a = xp.exp(-R_s * dt / L)
    return a, (1.0 - a) / R_s


def current_step(i_d: Array, i_q: Array, v_d: Array, v_q: Array, omega_r: Array, p: MachineCoefficients) -> tuple[Array, Array]:
    """Advance the dq currents (A) by one tick under the dq voltages ``v_d, v_q`` (V).

    ``omega_r`` is the electrical speed (rad/s); ``p`` carries ``a_d, b_d, a_q, b_q`` from
    :func:`rl_coefficients` and ``L_d, L_q, psi_f`` (H, H, V*s).
    """
    i_d_next = p.a_d * i_d + p.b_d * (v_d + omega_r * p.L_q * i_q)
    i_q_next = p.a_q * i_q + p.b_q * (v_q - omega_r * p.L_d * i_d - omega_r * p.psi_f)
    return i_d_next, i_q_next


def electromagnetic_torque(i_d: Array, i_q: Array, p: MachineCoefficients, poles: int) -> Array:
    """Seed eq. (3): ``3/2 * P/2 * (psi_f i_q + (L_d - L_q) i_d i_q)`` (N*m)."""
    return 0.75 * poles * (p.psi_f * i_q + (p.L_d - p.L_q) * i_d * i_q)
