"""One 20 kHz PWM tick of the bench (the body of :func:`eol_cal.plant.simulate.simulate`'s scan):
the sensors, the ECU's estimator and controller, the inverter, the motor, the shaft and the dyno.

Each tick (see :mod:`eol_cal.plant.control` for the ECU's rates):

1. the encoder and hall levels are sampled at the rotor's actual angle;
2. the firmware's estimator (:mod:`eol_cal.firmware.estimator`, the same code as the golden
   reference) steps once; the mode picks the control angle (``raw`` = its edge-quantised angle
   ``theta_enc``, ``estimated``/``compensated`` = ``theta_hat``); with a layout-2 block whose
   ``MECH_COMP_ENABLE`` is honoured, the identifier (:mod:`eol_cal.firmware.mech`) steps too;
3. on 420 Hz ticks the command ``i_qo`` and the decoupling speed are taken over; on 1.68 kHz
   ticks the phase currents are sampled, ``i_qc`` is evaluated with the firmware compensator
   (``compensated`` only; the mechanical orders added once identified) and the PI current
   controller updates the dq voltage reference;
4. the voltage reference is rotated with the latest control angle, limited by the SVPWM inverter,
   and rotated into the rotor's true dq frame; the motor's currents advance exactly over the tick;
5. torque ``kt*i_q`` minus the ripple sources drives the rotor; the shaft and the dyno advance and
   the torque transducer follows the shaft. The ripple held over the tick is its start angle's,
   so the chain runs half a tick behind that angle: the reading recorded beside it is the
   transducer's output half a tick on, the mean of its states at the tick's start and end
   (:func:`eol_cal.plant.sensors.transducer_step`). Recorded at the tick's end it led its
   continuous model by 25 us, which a 60 Hz transducer's fitted gain turned into a k6 bias of
   -0.12 % (issue 34).

Everything runs in float32, on numpy arrays for the initial state and traced JAX arrays in the scan.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from eol_cal.domain.bench_mechanics import mech_step
from eol_cal.firmware import estimator, kinematics, mech_tick
from eol_cal.firmware.mech import mech_init, mech_sum
from eol_cal.numerics.wrap import wrap_2pi
from eol_cal.plant import control, inverter, machine, ripple, sensors, transforms
from eol_cal.plant.params import PlantParams, PlantSpec, estimator_tables, mech_tables_of, sensor_errors

TWO_PI = 2.0 * math.pi
#: Per-tick outputs of the scan, in this order (float32 columns).
OUT_COLUMNS = ("torque", "enc_a", "enc_b", "hall", "iq_ref", "iqc", "iq", "id", "ia", "ib", "ic",
               "speed", "theta_r", "theta_hat", "theta_enc", "mech_active", "theta_m")
#: the name of the motors' axis: :func:`tick` and :func:`sense` run ``jax.vmap``-ped with it
BATCH_AXIS = "motors"


@dataclass(frozen=True)
class PlantSimConfig:
    """Static (compile-time) configuration of a plant simulation: rates, sizes, mode (not the
    ECU simulator's :class:`eol_cal.ecu.simconfig.SimConfig`)."""

    poles: int
    N_enc: int
    f_pwm: float
    f_cc: float
    f_cmd: float
    mode: str
    estimator: Any
    dead_time: bool = False
    mech: Any = None  # eol_cal.firmware.mech.MechConsts when a block of the batch identifies, else None


class PlantState(NamedTuple):
    """Continuous states of motor, shaft and dyno (float32): rad, rad, rad/s, rad/s, N*m, A, A, N*m."""

    theta_m: Any
    twist: Any
    omega_m: Any
    omega_d: Any
    x_dyno: Any
    i_d: Any
    i_q: Any
    y_tq: Any


def _rotate(x: Any, y: Any, c: Any, s: Any) -> tuple[Any, Any]:
    """Rotate the vector (x, y) by the angle whose cosine and sine are (c, s)."""
    return c * x - s * y, s * x + c * y


class Sensed(NamedTuple):
    """What the sensors and the ECU's estimator give at the start of a tick (rotor angle theta_m):
    encoder and hall levels, the estimator's outputs, and the cosines and sines of the actual
    mechanical angle and of the ECU's control angle (every rotation of the tick).

    The scan computes them at the end of the tick before, from the state it hands over: the
    same arithmetic, but each sine and cosine once (XLA fuses, and so repeats, a value computed
    inside the tick into every consumer; a sine costs ~50 multiplications on the CPU).
    """

    enc_a: Any
    enc_b: Any
    hall: Any
    est: Any
    cos_m: Any
    sin_m: Any
    cos_c: Any
    sin_c: Any
    # layout 2 (contract revision 1.2): the identifier's state after this tick (None without)
    mech: Any = None


def _mech_replaced(carry: tuple, step: Callable[[Any, Any], Any]) -> tuple:
    """``carry`` with its identifier state ``m`` replaced by ``step(m, estimator state)``."""
    plant, est_state, ecu, sensed = carry
    return plant, est_state, ecu, sensed._replace(mech=step(sensed.mech, est_state))


def background(cfg: PlantSimConfig, p: PlantParams, carry: tuple) -> tuple:
    """The identifier's background slice after a tick (:func:`eol_cal.firmware.mech_tick.mech_step`'s
    second half) for a whole batch: ``p`` and ``carry`` batched as the scan holds them (leading axis
    the motors). Nothing without ``cfg.mech``.

    Run outside the per-motor ``vmap`` so that the evaluation's arithmetic runs only on the ticks
    some motor needs it (:func:`eol_cal.firmware.mech_tick.batched_background`).
    """
    if cfg.mech is None:
        return carry
    return _mech_replaced(carry, lambda ms, es: mech_tick.batched_background(cfg.mech, mech_tables_of(p), ms, es))


def background_pending(carry: tuple) -> Any:
    """Whether :func:`background` computes something after this tick for some motor of the batch
    (an evaluation's first slice, a revolution mark's check: a few per revolution and motor)."""
    import jax.numpy as jnp

    return jnp.any(mech_tick.background_heavy(carry[3].mech))


def background_idle(cfg: PlantSimConfig, p: PlantParams, carry: tuple) -> tuple:
    """:func:`background` where :func:`background_pending` is false, without the evaluation."""
    import jax.numpy as jnp

    return _mech_replaced(carry, lambda ms, es: mech_tick.mech_background_idle(cfg.mech, ms, xp=jnp))


def background_heavy(cfg: PlantSimConfig, p: PlantParams, carry: tuple) -> tuple:
    """:func:`background` where :func:`background_pending` is true: every motor's slice."""
    return _mech_replaced(carry, lambda ms, es: mech_tick.batched_background_all(cfg.mech, mech_tables_of(p), ms, es))


def sense(cfg: PlantSimConfig, p: PlantParams, theta_m: Any, est_state: Any, mech_state: Any = None
           ) -> tuple[Any, Sensed]:
    """Steps 1-2 of a tick at rotor angle ``theta_m`` (rad): the levels, the estimator's step (and
    with ``cfg.mech`` the identifier's interrupt part, from ``mech_state``: :attr:`Sensed.mech`;
    :func:`background` then runs its background slice over the batch). One motor of a batch
    ``jax.vmap``-ped over :data:`BATCH_AXIS`."""
    import jax.numpy as jnp

    enc_a, enc_b, hall = kinematics.encoder_hall_signals(theta_m, cfg.poles, cfg.N_enc, sensor_errors(p), xp=jnp)
    # the motor's own hall table (its block's, a traced parameter): cfg.estimator's stays unread
    if cfg.mech is None:
        est_state, est = estimator.step(cfg.estimator, est_state, enc_a, enc_b, hall, xp=jnp,
                                        tables=estimator_tables(p), batch_axis=BATCH_AXIS)
    else:
        est_state, est, pitch = estimator.step_pitch(cfg.estimator, est_state, enc_a, enc_b, hall, xp=jnp,
                                                     tables=estimator_tables(p), batch_axis=BATCH_AXIS)
        # the interrupt's part, on the ticks some motor of the batch needs it; the background slice
        # follows for the whole batch (:func:`background`)
        mech_state, _ = mech_tick.batched_tick(cfg.mech, mech_tables_of(p), mech_state, est_state, est, pitch,
                                               BATCH_AXIS)
    theta_c = est.theta_enc if cfg.mode == "raw" else est.theta_hat
    return est_state, Sensed(enc_a, enc_b, hall, est, jnp.cos(theta_m), jnp.sin(theta_m), jnp.cos(theta_c),
                             jnp.sin(theta_c), mech_state)


def tick(cfg: PlantSimConfig, p: PlantParams, i_noise: Any, carry: tuple, x: tuple) -> tuple[tuple, Any]:
    """One PWM tick of one motor (traced, inside the scan): ``carry`` is ``(PlantState, estimator
    state, ECU's ControllerState, Sensed)``, ``x`` the tick's inputs ``(omega_ref rad/s, i_qo A,
    current-control flag, command flag, current-noise index, torque-noise draw)``, ``i_noise`` the
    chunk's current-sensor draws; returns the next carry and the tick's :data:`OUT_COLUMNS`."""
    import jax
    import jax.numpy as jnp

    plant, est_state, ecu, sensed = carry
    omega_ref, i_qo_prof, cc_flag, cmd_flag, cc_index, tq_noise = x
    pp = cfg.poles // 2
    dt = 1.0 / cfg.f_pwm
    T_cc = 1.0 / cfg.f_cc

    # 1-2: sensors and the firmware's estimator at this tick's angle (computed at the end of the last)
    est = sensed.est
    cos_m, sin_m, cos_c, sin_c = sensed.cos_m, sensed.sin_m, sensed.cos_c, sensed.sin_c
    # One sin/cos pair of the rotor angle serves every rotation and every ripple harmonic.
    cos_r, sin_r = cos_m, sin_m
    for _ in range(pp - 1):
        cos_r, sin_r = _rotate(cos_r, sin_r, cos_m, sin_m)
    omega_r = pp * plant.omega_m

    # 3: command / speed at 420 Hz, current control at 1.68 kHz (every motor of a batch on the
    # same ticks: a branch that runs on those ticks only)
    i_al, i_be = _rotate(plant.i_d, plant.i_q, cos_r, sin_r)
    i_a, i_b, i_c = transforms.alphabeta_to_abc(i_al, i_be)

    mech_on = None if cfg.mech is None else sensed.mech.active != 0

    def mech_current(i_qo: Any) -> tuple[Any, Any]:
        """Layout 2: whether the mechanical orders are compensated, and their current (A)."""
        return mech_on, mech_sum(cfg.mech, mech_tables_of(p), sensed.mech.r, est_state.q, est.theta_hat,
                                 est.omega_hat, i_qo, xp=jnp)

    def current_task(ecu: control.ControllerState) -> control.ControllerState:
        return control.current_task(ecu, (i_a, i_b, i_c), i_noise[cc_index], est.theta_hat, est.omega_hat,
                                    i_qo_prof, cmd_flag, cos_c, sin_c, p, T_cc, cfg.mode == "compensated", jnp,
                                    mech=None if cfg.mech is None else mech_current)

    ecu = jax.lax.cond(cc_flag, current_task, lambda e: e, ecu)

    # 4: PWM with the latest angle, inverter, motor currents
    u_al, u_be = _rotate(ecu.u_d, ecu.u_q, cos_c, sin_c)
    u_al, u_be = inverter.limit_voltage(u_al, u_be, p.u_dc, jnp)
    if cfg.dead_time:
        e_al, e_be = inverter.dead_time_error(i_a, i_b, i_c, p.u_dead, jnp)
        u_al, u_be = u_al + e_al, u_be + e_be
    v_d, v_q = _rotate(u_al, u_be, cos_r, -sin_r)
    T_e = machine.electromagnetic_torque(plant.i_d, plant.i_q, p, cfg.poles)
    T_rotor = T_e - ripple.ripple_torque(cos_r, sin_r, cos_m, sin_m, plant.i_q, p)
    i_d, i_q = machine.current_step(plant.i_d, plant.i_q, v_d, v_q, omega_r, p)

    # 5: shaft, dyno, transducer
    theta_m, twist, omega_m, omega_d, x_dyno, T_shaft = mech_step(
        plant.theta_m, plant.twist, plant.omega_m, plant.omega_d, plant.x_dyno, T_rotor, omega_ref, p, dt, jnp)
    y_tq, torque = sensors.transducer_step(plant.y_tq, T_shaft, tq_noise, p, jnp)

    f32 = jnp.float32
    theta_r = wrap_2pi(pp * plant.theta_m, jnp)
    out = jnp.stack([
        torque, sensed.enc_a.astype(f32), sensed.enc_b.astype(f32), sensed.hall.astype(f32), ecu.i_qo, ecu.i_qc,
        plant.i_q, plant.i_d, i_a, i_b, i_c, omega_d * (60.0 / TWO_PI),
        theta_r, est.theta_hat, est.theta_enc,
        jnp.zeros_like(torque) if mech_on is None else mech_on.astype(f32), wrap_2pi(plant.theta_m, jnp),
    ])
    plant = PlantState(theta_m, twist, omega_m, omega_d, x_dyno, i_d, i_q, y_tq)
    # the next tick's sensors and estimator step
    est_state, sensed = sense(cfg, p, theta_m, est_state, sensed.mech)
    return (plant, est_state, ecu, sensed), out


def initial_carry(cfg: PlantSimConfig, p: PlantParams, spec: PlantSpec, theta_m0: float,
                   omega_m0: float, i_qo0: float) -> tuple:
    """Steady state at the profile's first point: speed, current, shaft twist, controller memory."""
    m = spec.motor
    T0 = m.kt * i_qo0 - m.B * omega_m0
    f = np.float32
    ps = PlantParams(*(np.asarray(a) for a in p))
    a0, b0, hall0 = kinematics.encoder_hall_signals(np.float64(theta_m0), cfg.poles, cfg.N_enc,
                                                    sensor_errors(ps), xp=np)
    plant = PlantState(f(theta_m0), f(T0 / spec.mechanics.K_shaft), f(omega_m0), f(omega_m0), f(-T0),
                       f(0.0), f(i_qo0), f(T0))
    est_state = estimator.init_state(cfg.estimator, int(hall0), int(a0), int(b0), xp=np)
    ecu = control.initial_ecu(f(i_qo0), f(cfg.poles // 2 * omega_m0), ps, np)
    ecu = control.ControllerState(*(np.asarray(v, dtype=np.float32) for v in ecu))
    est_state = type(est_state)(*(np.asarray(v) for v in est_state))
    mech_state = None
    if cfg.mech is not None:
        mech_state = type(mech_init(cfg.N_enc))(*(np.asarray(v) for v in mech_init(cfg.N_enc)))
    return plant, est_state, ecu, mech_state
