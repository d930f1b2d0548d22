"""The bench simulation: a ``lax.scan`` over 20 kHz PWM ticks, ``vmap`` over a lot of motors.

Each tick (see :mod:`eol_cal.plant.control` for the ECU's rates):

1. the encoder and hall levels are sampled at the rotor's actual angle;
2. the firmware's estimator (:mod:`eol_cal.firmware.estimator`, the same code as the golden
   reference) steps once; the mode picks the control angle (``raw`` = its edge-quantised angle
   ``theta_enc``, ``estimated``/``compensated`` = ``theta_hat``);
3. on 420 Hz ticks the command ``i_qo`` and the decoupling speed are taken over; on 1.68 kHz
   ticks the phase currents are sampled, ``i_qc`` is evaluated with the firmware compensator
   (``compensated`` only) and the PI current controller updates the dq voltage reference;
4. the voltage reference is rotated with the latest control angle, limited by the SVPWM inverter,
   and rotated into the rotor's true dq frame; the motor's currents advance exactly over the tick;
5. torque ``kt*i_q`` minus the ripple sources drives the rotor; the shaft and the dyno advance and
   the torque transducer samples the shaft.

Everything runs in float32. The scan is cut into chunks of fixed length so that one compiled
program serves any duration, and each chunk's outputs are copied to the host as they come.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from eol_cal.capture.ecu_state import EcuState, with_ecu_state
from eol_cal.capture.model import Capture
from eol_cal.errors import InputError
from eol_cal.firmware import compensator
from eol_cal.firmware.block import ParamBlock
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE
from eol_cal.mechanics import mech_step
from eol_cal.plant import control, inverter, motor, ripple, sensors, transforms
from eol_cal.plant.ecu import batch_options, estimator_config, learning_pre_roll_s, simulated_ecu_state, true_block
from eol_cal.plant.params import PlantParams, PlantSpec, estimator_tables, sensor_errors, stack_params, to_params
from eol_cal.plant.profile import Profile
from eol_cal.wrap import wrap_2pi
from eol_cal.xla import configure_xla  # noqa: F401 - the CLI's and benchmarks' entry (was defined here)

TWO_PI = 2.0 * math.pi
#: Per-tick outputs of the scan, in this order (float32 columns).
OUT_COLUMNS = ("torque", "enc_a", "enc_b", "hall", "iq_ref", "iqc", "iq", "id", "ia", "ib", "ic",
               "speed", "theta_r", "theta_hat", "theta_enc")
CHUNK_TICKS = 4000


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


@dataclass(frozen=True)
class SimResult:
    """One motor's run: the capture plus the angles (rad) only a simulator knows, for plots."""

    capture: Capture
    theta_r: np.ndarray
    theta_hat: np.ndarray
    theta_enc: np.ndarray


def _rotate(x: Any, y: Any, c: Any, s: Any) -> tuple[Any, Any]:
    """Rotate the vector (x, y) by the angle whose cosine and sine are (c, s)."""
    return c * x - s * y, s * x + c * y


def _tick(cfg: PlantSimConfig, p: PlantParams, carry: tuple, x: tuple) -> tuple[tuple, Any]:
    import jax.numpy as jnp

    from eol_cal.firmware import estimator, kinematics

    plant, est_state, ecu = carry
    omega_ref, i_qo_prof, cc_flag, cmd_flag, noise = x
    pp = cfg.poles // 2
    dt = 1.0 / cfg.f_pwm
    T_cc = 1.0 / cfg.f_cc

    # One sin/cos pair of the rotor angle serves every rotation and every ripple harmonic.
    theta_m = plant.theta_m
    cos_m, sin_m = jnp.cos(theta_m), jnp.sin(theta_m)
    cos_r, sin_r = cos_m, sin_m
    for _ in range(pp - 1):
        cos_r, sin_r = _rotate(cos_r, sin_r, cos_m, sin_m)
    omega_r = pp * plant.omega_m

    # 1-2: sensors and the firmware's estimator
    enc_a, enc_b, hall = kinematics.encoder_hall_signals(theta_m, cfg.poles, cfg.N_enc, sensor_errors(p), xp=jnp)
    # the motor's own hall table (its block's, a traced parameter): cfg.estimator's stays unread
    est_state, est = estimator.step(cfg.estimator, est_state, enc_a, enc_b, hall, xp=jnp,
                                    tables=estimator_tables(p))
    theta_c = est.theta_enc if cfg.mode == "raw" else est.theta_hat
    cos_c, sin_c = jnp.cos(theta_c), jnp.sin(theta_c)

    # 3: command / speed at 420 Hz, current control at 1.68 kHz
    i_qo = jnp.where(cmd_flag, i_qo_prof, ecu.i_qo)
    omega_c = jnp.where(cmd_flag, est.omega_hat, ecu.omega_c)
    i_al, i_be = _rotate(plant.i_d, plant.i_q, cos_r, sin_r)
    i_a, i_b, i_c = transforms.alphabeta_to_abc(i_al, i_be)
    m_al, m_be = transforms.abc_to_alphabeta(sensors.current_reading(i_a, noise[1], p, jnp),
                                             sensors.current_reading(i_b, noise[2], p, jnp),
                                             sensors.current_reading(i_c, noise[3], p, jnp))
    i_d_meas, i_q_meas = _rotate(m_al, m_be, cos_c, -sin_c)
    if cfg.mode == "compensated":
        i_qc_new = compensator.i_qc(est.theta_hat, est.omega_hat, i_qo, p.table_const,
                                    p.table_per_amp, p.lead_s, p.iqc_limit, xp=jnp)
    else:
        i_qc_new = jnp.zeros_like(i_qo)
    ecu = ecu._replace(i_qo=i_qo, omega_c=omega_c)
    x_d, x_q, u_d, u_q = control.pi_current_step(ecu, i_d_meas, i_q_meas, i_qo + i_qc_new, p, T_cc, jnp)
    ecu = control.EcuState(
        x_d=jnp.where(cc_flag, x_d, ecu.x_d), x_q=jnp.where(cc_flag, x_q, ecu.x_q),
        u_d=jnp.where(cc_flag, u_d, ecu.u_d), u_q=jnp.where(cc_flag, u_q, ecu.u_q),
        i_qo=i_qo, omega_c=omega_c, i_qc=jnp.where(cc_flag, i_qc_new, ecu.i_qc),
    )

    # 4: PWM with the latest angle, inverter, motor currents
    u_al, u_be = _rotate(ecu.u_d, ecu.u_q, cos_c, sin_c)
    u_al, u_be = inverter.limit_voltage(u_al, u_be, p.u_dc, jnp)
    if cfg.dead_time:
        e_al, e_be = inverter.dead_time_error(i_a, i_b, i_c, p.u_dead, jnp)
        u_al, u_be = u_al + e_al, u_be + e_be
    v_d, v_q = _rotate(u_al, u_be, cos_r, -sin_r)
    T_e = motor.electromagnetic_torque(plant.i_d, plant.i_q, p, cfg.poles)
    T_rotor = T_e - ripple.ripple_torque(cos_r, sin_r, cos_m, sin_m, plant.i_q, p)
    i_d, i_q = motor.current_step(plant.i_d, plant.i_q, v_d, v_q, omega_r, p)

    # 5: shaft, dyno, transducer
    theta_m, twist, omega_m, omega_d, x_dyno, T_shaft = mech_step(
        theta_m, plant.twist, plant.omega_m, plant.omega_d, plant.x_dyno, T_rotor, omega_ref, p, dt, jnp)
    y_tq, torque = sensors.transducer_step(plant.y_tq, T_shaft, noise[0], p, jnp)

    f32 = jnp.float32
    theta_r = wrap_2pi(pp * plant.theta_m, jnp)
    out = jnp.stack([
        torque, enc_a.astype(f32), enc_b.astype(f32), hall.astype(f32), i_qo, ecu.i_qc,
        plant.i_q, plant.i_d, i_a, i_b, i_c, omega_d * (60.0 / TWO_PI),
        theta_r, est.theta_hat, est.theta_enc,
    ])
    plant = PlantState(theta_m, twist, omega_m, omega_d, x_dyno, i_d, i_q, y_tq)
    return (plant, est_state, ecu), out


_COMPILED: dict[tuple, Callable] = {}

def _chunk_fn(cfg: PlantSimConfig, n_ticks: int, unroll: int) -> Callable:
    """Compiled ``(params, carry, shared_xs, keys, start) -> (carry, outputs)`` for a batch.

    ``keys`` holds one PRNG key per motor; the chunk's sensor noise is drawn from
    ``fold_in(key, start)`` so a run does not depend on how it is cut into chunks' dispatches.
    """
    key = (cfg, n_ticks, unroll)
    if key in _COMPILED:
        return _COMPILED[key]
    import jax
    import jax.numpy as jnp

    def one_motor(p, carry, shared, key, start):
        noise = jax.random.normal(jax.random.fold_in(key, start), (n_ticks, 4), dtype=jnp.float32)
        xs = (*shared, noise)
        carry, ys = jax.lax.scan(lambda c, x: _tick(cfg, p, c, x), carry, xs, unroll=unroll)
        return carry, ys.T  # channel-major: the host converts contiguous rows

    fn = jax.jit(jax.vmap(one_motor, in_axes=(0, 0, None, 0, None)))
    _COMPILED[key] = fn
    return fn


def _initial_carry(cfg: PlantSimConfig, p: PlantParams, spec: PlantSpec, theta_m0: float,
                   omega_m0: float, i_qo0: float) -> tuple:
    """Steady state at the profile's first point: speed, current, shaft twist, controller memory."""

    from eol_cal.firmware import estimator, kinematics

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
    ecu = control.EcuState(*(np.asarray(v, dtype=np.float32) for v in ecu))
    est_state = type(est_state)(*(np.asarray(v) for v in est_state))
    return plant, est_state, ecu


def simulate(
    specs: PlantSpec | Sequence[PlantSpec],
    profile: Profile,
    mode: str = "estimated",
    blocks: ParamBlock | Sequence[ParamBlock | None] | None = None,
    seed: int = 0,
    pre_roll_s: float | None = None,
    chunk_ticks: int = CHUNK_TICKS,
    unroll: int = 1,
    progress: Callable[[float], None] | None = None,
    ecu_estimator: str | None = None,
) -> list[SimResult]:
    """Simulate one motor or a lot of motors through a test profile.

    Parameters
    ----------
    specs : PlantSpec or sequence of PlantSpec
        The motors (one capture each). All must share poles, N_enc and the ECU rates.
    profile : Profile
        Speed and load segments (see :mod:`eol_cal.plant.profile`).
    mode : {"raw", "estimated", "compensated"}
        Control angle and compensation (paper Figs. 10, 11, 12).
    blocks : ParamBlock or sequence, optional
        Parameter block per motor: its tables for ``compensated`` (missing ones are made from the
        plant's true ripple, :func:`true_block`), its ``hall_angle`` and the estimator options
        its flags select (bits 2-5 with ``INTERP_ENABLE``) for the ECU's estimator in every mode
        (nominal table and the paper's estimator without a block). Motors of one batch may carry
        different tables but must select the same estimator options.
    seed : int
        Seed of the sensor noise.
    pre_roll_s : float, optional
        Time (s) simulated at the profile's first point before recording starts, so the
        estimator has seen its first edges and hall transition; default
        :func:`learning_pre_roll_s` (longer when the estimator learns pitch errors).
    chunk_ticks, unroll : int
        Scan chunk length (ticks) and unroll factor (speed only).
    progress : callable, optional
        Called with the fraction done after each chunk.
    ecu_estimator : str, optional
        Overrides the blocks' estimator options: ``paper``, ``best``, option names joined by
        ``+`` or a hex mask (:func:`eol_cal.firmware.options.parse_options`); for runs without
        a block.

    Returns
    -------
    list of SimResult
    """
    import jax

    if mode not in control.MODES:
        raise InputError(None, "mode", f"unknown mode {mode!r}; known: {', '.join(control.MODES)}")
    single = isinstance(specs, PlantSpec)
    specs = [specs] if single else list(specs)
    if not specs:
        raise InputError(None, "motors", "no motor to simulate")
    m0 = specs[0].motor
    for s in specs:
        if (s.motor.poles, s.motor.N_enc, s.motor.f_pwm, s.motor.f_cc, s.motor.f_cmd) != (
                m0.poles, m0.N_enc, m0.f_pwm, m0.f_cc, m0.f_cmd):
            raise InputError(None, "motors", "a batch must share poles, N_enc and ECU rates")
    if blocks is None or isinstance(blocks, ParamBlock):
        blocks = [blocks] * len(specs)
    blocks = list(blocks)
    if len(blocks) != len(specs):
        raise InputError(None, "blocks", f"{len(blocks)} blocks for {len(specs)} motors")

    params = []
    states = []
    effective = []
    for spec, block in zip(specs, blocks):
        states.append(simulated_ecu_state(spec, mode, block))
        if block is None:
            block = true_block(spec) if mode == "compensated" else None
        effective.append(block)
        if block is not None:
            if (block.poles, block.encoder_ppr) != (spec.motor.poles, spec.motor.N_enc):
                raise InputError(None, "block", f"block is for P={block.poles}, {block.encoder_ppr} PPR; "
                                 f"motor has P={spec.motor.poles}, {spec.motor.N_enc} PPR")
            tc, tp, lead, lim = block.table_const, block.table_per_amp, block.lead_s, block.iqc_limit
            hall = block.hall_angle
        else:
            tc = tp = np.zeros(16, np.float32)
            lead = lim = 0.0
            hall = NOMINAL_HALL_ANGLE
        params.append(to_params(spec, tc, tp, lead, lim, hall_angle=hall))
    lens = {len(p.table_const) for p in params}
    if len(lens) != 1:
        raise InputError(None, "blocks", "a batch must share one table length")
    batch = stack_params(params)
    options = batch_options(effective, ecu_estimator)

    cfg = PlantSimConfig(poles=m0.poles, N_enc=m0.N_enc, f_pwm=m0.f_pwm, f_cc=m0.f_cc, f_cmd=m0.f_cmd,
                    # nominal table: each motor's own travels in its PlantParams (one program for all)
                    mode=mode, estimator=estimator_config(specs[0], options=options),
                    dead_time=any(s.dead_time_s > 0 for s in specs))

    speed_rpm, i_qo = profile.ticks(m0.f_pwm, m0.kt)
    if pre_roll_s is None:
        pre_roll_s = learning_pre_roll_s(options, float(speed_rpm[0]))
    n_pre = int(round(pre_roll_s * m0.f_pwm))
    speed_rpm = np.concatenate([np.full(n_pre, speed_rpm[0]), speed_rpm])
    i_qo = np.concatenate([np.full(n_pre, i_qo[0]), i_qo])
    n_total = len(speed_rpm)
    omega_ref = (speed_rpm * TWO_PI / 60.0).astype(np.float32)
    i_qo = i_qo.astype(np.float32)
    cc = control.rate_flags(n_total, m0.f_pwm, m0.f_cc)
    cmd = control.rate_flags(n_total, m0.f_pwm, m0.f_cmd)

    rng = np.random.default_rng(seed)
    carries = [_initial_carry(cfg, p, s, float(rng.uniform(0.0, TWO_PI)), float(omega_ref[0]), float(i_qo[0]))
               for p, s in zip(params, specs)]
    carry = jax.tree_util.tree_map(lambda *a: np.stack(a), *carries)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(specs))

    fn = _chunk_fn(cfg, chunk_ticks, unroll)
    out = np.empty((len(specs), len(OUT_COLUMNS), n_total), np.float32)
    # The last chunk runs padded (its extra ticks are dropped with the carry after them).
    pad = -n_total % chunk_ticks
    inputs = tuple(np.pad(a, (0, pad), mode="edge") for a in (omega_ref, i_qo, cc, cmd))
    for start in range(0, n_total, chunk_ticks):
        stop = min(start + chunk_ticks, n_total)
        shared = tuple(a[start:start + chunk_ticks] for a in inputs)
        carry, ys = fn(batch, carry, shared, keys, np.int32(start))
        out[:, :, start:stop] = np.asarray(ys)[:, :, : stop - start]
        if progress is not None:
            progress(stop / n_total)
    results = []
    for i in range(len(specs)):
        results.append(_to_result(out[i, :, n_pre:], specs[i], cfg, profile, mode, blocks[i], states[i]))
    return results


def _to_result(y: np.ndarray, spec: PlantSpec, cfg: PlantSimConfig, profile: Profile, mode: str,
               block: ParamBlock | None, ecu: EcuState) -> SimResult:
    m = spec.motor
    col = dict(zip(OUT_COLUMNS, y))
    n = y.shape[1]
    t = np.arange(n, dtype=np.float64) / m.f_pwm
    channels: dict[str, np.ndarray] = {}
    for name in ("enc_a", "enc_b", "hall"):
        channels[name] = col[name].astype(np.int64)
    for name in ("torque", "iq_ref", "iqc", "iq", "id", "ia", "ib", "ic", "speed"):
        channels[name] = col[name].astype(np.float64)
    channels["temp"] = np.full(n, spec.temp_degC)
    metadata: dict[str, str | int | float] = {
        "serial": spec.serial, "poles": m.poles, "encoder_ppr": m.N_enc, "kt": m.kt,
        "source": "plant", "comment": f"eol-cal plant, mode {mode}, profile {profile.name}",
    }
    metadata = with_ecu_state(metadata, ecu, ecu)  # the simulated ECU runs one block all along
    truth = spec.truth()
    truth.update({"mode": mode, "profile": profile.name})
    if block is not None and mode == "compensated":
        truth.update({"block_k6": block.k6, "block_c6": block.c6, "block_lead_s": block.lead_s})
    cap = Capture(t=t, channels=channels, metadata=metadata, truth=truth, source="<plant>")
    return SimResult(cap, col["theta_r"].astype(np.float64), col["theta_hat"].astype(np.float64),
                     col["theta_enc"].astype(np.float64))
