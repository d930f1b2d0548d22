"""The ECU's control as the paper runs it on the TMS320F28335 (seed section IV, Fig. 7).

Three rates:

- every PWM tick (20 kHz): the estimator runs on the sensor levels, and the held dq voltage
  reference is turned into the stator-frame vector with the *latest* angle (so the modulator's
  angle moves between current-control updates);
- current control (1.68 kHz, :func:`current_task`): phase currents are sampled, transformed with
  the latest angle, and a PI controller with decoupling updates the dq voltage reference; in
  ``compensated`` mode the compensating current ``i_qc`` from the parameter block's tables is
  added to the command (seed eq. 20);
- command and speed (420 Hz): the nominal current ``i_qo`` and the speed used for decoupling
  are taken over.

20 kHz / 1.68 kHz = 11.9 is not an integer: a phase accumulator (:func:`rate_flags`) fires the
slower tasks on the first tick at or after their ideal instant, so they run every 11 or 12 ticks
(47 or 48 for 420 Hz) and average exactly to their nominal rates, as a timer interrupt on a
PWM-synchronous ISR does. The PI integrates with the nominal period 1/1.68 kHz.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from fractions import Fraction
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware import compensator
from eol_cal.plant import inverter, sensors, transforms

if TYPE_CHECKING:
    from eol_cal.plant.params import PlantParams

MODES = ("raw", "estimated", "compensated")


class ControllerState(NamedTuple):
    """Controller memory (float32 scalars per motor).

    x_d, x_q: PI integrators (V); u_d, u_q: held voltage reference in the controller's frame (V);
    i_qo: held nominal q current (A); omega_c: held electrical speed for decoupling (rad/s);
    i_qc: compensating current of the last current-control step (A).
    """

    x_d: Array
    x_q: Array
    u_d: Array
    u_q: Array
    i_qo: Array
    omega_c: Array
    i_qc: Array


def rate_flags(n_ticks: int, f_tick: float, f_task: float, start: int = 0) -> np.ndarray:
    """Ticks on which a task of rate ``f_task`` (Hz) runs, from a phase accumulator (bool array).

    Tick ``k`` (absolute index ``start + i``) fires when ``floor(k*f_task/f_tick)`` increases,
    i.e. on the first tick at or after each of the task's ideal instants; tick 0 fires.
    Integer arithmetic on the ratio: 1680/20000 is not float-exact and a drifting float
    accumulator would shift the schedule over long runs.
    """
    period = _rate_period(f_tick, f_task)
    phase = start % period.size
    return np.resize(np.concatenate((period[phase:], period[:phase])), n_ticks)


@functools.lru_cache(maxsize=16)
def _rate_period(f_tick: float, f_task: float) -> np.ndarray:
    """:func:`rate_flags`' ticks ``0 .. den - 1`` (read-only; kept: a run's two rates cost ~0.1 ms
    to derive, 1 % of a one-motor simulated second)."""
    r = Fraction(f_task).limit_denominator(10**6) / Fraction(f_tick).limit_denominator(10**6)
    # floor((k + den) num / den) = floor(k num / den) + num: the flags repeat every den ticks
    # (20 kHz / 1.68 kHz: 250), one period computed and repeated from the run's phase
    k = np.arange(r.denominator, dtype=np.int64)
    period = (k * r.numerator) // r.denominator > ((k - 1) * r.numerator) // r.denominator
    period.setflags(write=False)
    return period


def pi_current_step(
    st: ControllerState, i_d_meas: Array, i_q_meas: Array, i_q_ref: Array, p: PlantParams, T_cc: float, xp: ArrayModule,
) -> tuple[Array, Array, Array, Array]:
    """One current-control update (all in the controller's dq frame).

    PI with decoupling (``-omega L_q i_q`` on d, ``+omega (L_d i_d + psi_f)`` on q, nominal motor
    data), limited to the inverter's ``u_dc/sqrt(3)``; the integrators hold while the output is
    limited (conditional integration anti-windup). ``i_d`` is commanded to zero (MTPA of an
    SPMSM, seed section II.B). Returns ``(x_d, x_q, u_d, u_q)`` (V).
    """
    e_d = 0.0 - i_d_meas
    e_q = i_q_ref - i_q_meas
    w = st.omega_c
    u_d = p.Kp_d * e_d + st.x_d - w * p.L_q_nom * i_q_meas
    u_q = p.Kp_q * e_q + st.x_q + w * (p.L_d_nom * i_d_meas + p.psi_f_nom)
    u_max = p.u_dc / inverter.SQRT3
    mag = xp.sqrt(u_d * u_d + u_q * u_q)
    free = mag <= u_max
    scale = xp.minimum(1.0, u_max / xp.maximum(mag, 1e-9))
    x_d = xp.where(free, st.x_d + p.Ki_d * T_cc * e_d, st.x_d)
    x_q = xp.where(free, st.x_q + p.Ki_q * T_cc * e_q, st.x_q)
    return x_d, x_q, u_d * scale, u_q * scale


def current_task(
    st: ControllerState, i_abc: tuple[Array, Array, Array], noise: Array, theta_hat: Array, omega_hat: Array,
    i_qo_cmd: Array, cmd: Array, cos_c: Array, sin_c: Array, p: PlantParams, T_cc: float, compensate: bool,
    xp: ArrayModule, mech: Callable[[Array], tuple[Array, Array]] | None = None,
) -> ControllerState:
    """One run of the 1.68 kHz current-control task (with the 420 Hz command task where ``cmd``).

    Takes over the command ``i_qo_cmd`` (A) and the estimator's speed ``omega_hat`` (rad/s) for
    decoupling on command ticks; samples the phase currents ``i_abc`` (A) with the sensors'
    ``noise`` (three standard normal draws) and turns them into the controller's frame with the
    control angle (``cos_c``, ``sin_c``); in compensated mode adds the block's ``i_qc`` at the
    estimator's ``theta_hat``, ``omega_hat`` (:func:`eol_cal.firmware.compensator.i_qc`), with a
    layout-2 block's mechanical orders once identified (``mech``: ``i_qo -> (on, current A)``,
    :func:`eol_cal.firmware.mech.mech_sum`); and updates the PI (:func:`pi_current_step`). Returns
    the controller memory after the task.
    """
    i_qo = xp.where(cmd, i_qo_cmd, st.i_qo)
    omega_c = xp.where(cmd, omega_hat, st.omega_c)
    m_al, m_be = transforms.abc_to_alphabeta(*(sensors.current_reading(i, n, p, xp) for i, n in zip(i_abc, noise, strict=True)))
    i_d_meas, i_q_meas = cos_c * m_al + sin_c * m_be, cos_c * m_be - sin_c * m_al
    if compensate:
        mech_on, mech_sum = (None, None) if mech is None else mech(i_qo)
        i_qc = compensator.i_qc(theta_hat, omega_hat, i_qo, p.table_const, p.table_per_amp, p.lead_s,
                                p.iqc_limit, xp=xp, mech_on=mech_on, mech_sum=mech_sum)
    else:
        i_qc = xp.zeros_like(i_qo)
    st = st._replace(i_qo=i_qo, omega_c=omega_c)
    x_d, x_q, u_d, u_q = pi_current_step(st, i_d_meas, i_q_meas, i_qo + i_qc, p, T_cc, xp)
    return ControllerState(x_d=x_d, x_q=x_q, u_d=u_d, u_q=u_q, i_qo=i_qo, omega_c=omega_c, i_qc=i_qc)


def initial_ecu(i_qo: float | np.floating, omega_r: float | np.floating, p: PlantParams, xp: ArrayModule
                ) -> ControllerState:
    """Controller memory in steady state at ``i_qo`` (A) and ``omega_r`` (rad/s electrical)."""
    R = p.Ki_q / p.Kp_q * p.L_q_nom  # nominal R_s recovered from the tuning
    x_d = xp.zeros_like(p.Kp_d)
    x_q = R * i_qo + 0.0 * p.Kp_q
    u_d = -omega_r * p.L_q_nom * i_qo
    u_q = x_q + omega_r * p.psi_f_nom
    z = xp.zeros_like(p.Kp_d)
    return ControllerState(x_d, x_q, u_d, u_q, z + i_qo, z + omega_r, z)
