"""Many power-ups of the firmware's identifier at once (JAX, vmapped): the kinematic sensor model
(:mod:`eol_cal.firmware.kinematics`) turning at a speed profile, the estimator with its pitch
samples and the identifier (:mod:`eol_cal.firmware.mech`) tick by tick, per power-up its own
encoder, halls, block, start angle and speed.

Used by the identification tests (thousands of power-ups) and the study of the margins
(``bench/bench_mech_id.py``); the numpy reference of one ECU is :func:`eol_cal.firmware.mech_run.run_mech`.
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="union-attr,operator,assignment"
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.firmware import estimator as est
from eol_cal.firmware.contract import FLAG_INTERP_ENABLE, FLAGS_ESTIMATOR
from eol_cal.firmware.estimator_step import EstimatorState, init_state, step_pitch
from eol_cal.firmware.kinematics import SensorErrors, encoder_hall_signals, hall_angle_of, pulse_at
from eol_cal.firmware.mech import (
    EV_RESET_EVAL,
    EV_RESET_FAULT,
    EV_RESET_FRACTION,
    MechConsts,
    MechState,
    MechTables,
    mech_init,
    mech_tables,
)
from eol_cal.firmware.mech_tick import batched_background_few, batched_tick
from eol_cal.firmware.mech_params import MechParams

if TYPE_CHECKING:
    import jax

TICK_HZ = 20000.0
#: ticks per compiled chunk of the scan
CHUNK = 4000
_RESETS = EV_RESET_FAULT | EV_RESET_FRACTION | EV_RESET_EVAL
#: the power-ups' vmapped axis
_AXIS = "powerups"
#: power-ups whose background evaluation is computed together (a round; more rounds when more need it)
_FEW = 8
#: the compiled scan's carry over a batch: shaft angle, estimator and identifier states, and the
#: tracking (first identifying tick, its r, ticks identified wrong, identifier resets)
_Carry = tuple["jax.Array", EstimatorState, MechState, tuple["jax.Array", "jax.Array", "jax.Array", "jax.Array"]]


@dataclass(frozen=True)
class PowerUp:
    """One power-up: the motor's sensors, the block's mechanical part, the motion.

    errors : the motor's encoder and hall errors (the truth the signals come from);
    mech : the block's mechanical part (its fingerprint measured or true);
    theta0 : mechanical angle at power-on (rad); rpm0, rpm1 : speed at power-on and after the
    ramp (mechanical rpm, signed), the ramp over [ramp_s[0], ramp_s[1]] s;
    jitter_deg : white noise on the angle the sensors see (mechanical degrees per tick);
    frame_pulse : the model's pulse that is pulse 0 of the block's frame (0: the block's frame is the
    model's pulse numbering, a true fingerprint; a fingerprint measured at end of line is in the
    frame of its first capture window's count).
    """

    errors: SensorErrors
    mech: MechParams
    theta0: float
    rpm0: float
    rpm1: float | None = None
    ramp_s: tuple[float, float] = (0.0, 0.0)
    jitter_deg: float = 0.0
    frame_pulse: int = 0

    def truth_r(self, poles: int) -> int:
        """The offset the identifier must find: firmware pulse 0 in the block's frame."""
        N = len(self.errors.edge_error)
        a, b, _ = encoder_hall_signals(np.float64(self.theta0), poles, N, self.errors)
        return (pulse_at(self.theta0, self.errors, int(a), int(b)) - self.frame_pulse) % N


@dataclass(frozen=True)
class PowerUpResult:
    """Per power-up (numpy arrays): the truth and what the identifier did.

    truth : offset r the block's frame has; first_id_s : time of the first identification (s, NaN
    if none); r_first : r it identified first (-1 none); wrong_ticks : ticks active with r != truth;
    active_end : identified at the end; resets : withdrawals; score, margin : last evaluation's.
    """

    truth: np.ndarray
    first_id_s: np.ndarray
    r_first: np.ndarray
    wrong_ticks: np.ndarray
    active_end: np.ndarray
    resets: np.ndarray
    score: np.ndarray
    margin: np.ndarray

    @property
    def right(self) -> np.ndarray:
        """Per power-up: it identified the true frame and never applied a wrong one (the switch's
        calibration counts these, firmware_params/MECH.md)."""
        return np.isfinite(self.first_id_s) & (self.r_first == self.truth) & (self.wrong_ticks == 0)


def _stack(items: Sequence) -> list:
    return [np.stack(x) for x in zip(*items, strict=True)]


def simulate_powerups(pus: Sequence[PowerUp], seconds: float, poles: int = 6, flags: int | None = None,
                      seed: int = 0, lead_s: float = 0.0) -> PowerUpResult:
    """Run the power-ups for ``seconds`` each (one vmapped batch; every power-up's own sensors,
    block and motion). ``flags``: the block's flags word selecting the estimator (default every
    option, which the identifier needs); ``seed``: the jitter's draws (numpy's generator)."""
    import jax
    import jax.numpy as jnp

    flags = FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR if flags is None else flags
    N = len(pus[0].errors.edge_error)
    cfg = est.EstimatorConfig.from_flags(flags, poles=poles, N_enc=N, tick_hz=TICK_HZ)
    mc = MechConsts.of(cfg)
    B = len(pus)
    edge = np.stack([np.asarray(p.errors.edge_error, float) for p in pus])
    hall = np.stack([np.asarray(p.errors.hall_offset, float) for p in pus])
    grid = np.array([float(p.errors.grid_offset) for p in pus])
    hts = [est.hall_tables(hall_angle_of(p.errors)) for p in pus]
    tables = est.HallTables(*(jnp.asarray(np.stack([t[i] for t in hts])) for i in range(3)))
    tbs = [mech_tables(p.mech, lead_s, True, N) for p in pus]
    tb = MechTables(*(jnp.asarray(x) for x in _stack(tbs)))
    w0 = np.array([p.rpm0 for p in pus]) * 2 * math.pi / 60
    w1 = np.array([p.rpm1 if p.rpm1 is not None else p.rpm0 for p in pus]) * 2 * math.pi / 60
    r0 = np.array([p.ramp_s[0] for p in pus]) * TICK_HZ
    r1 = np.maximum(np.array([p.ramp_s[1] for p in pus]) * TICK_HZ, r0 + 1)
    jit = np.radians([p.jitter_deg for p in pus])
    th0 = np.array([p.theta0 for p in pus])
    truth = np.array([p.truth_r(poles) for p in pus], np.int32)

    f32 = jnp.float32
    E, H, G = (jnp.asarray(x, f32) for x in (edge, hall, grid))
    a0, b0, h0 = jax.vmap(lambda th, e, h, g: encoder_hall_signals(th, poles, N, SensorErrors(e, h, g), xp=jnp))(
        jnp.asarray(th0, f32), E, H, G)
    es = jax.vmap(lambda h, a, b: init_state(cfg, h, a, b, xp=jnp))(h0, a0, b0)
    ms = jax.vmap(lambda _: mech_init(N, xp=jnp))(jnp.arange(B))
    track = (jnp.full(B, -1, jnp.int32), jnp.full(B, -1, jnp.int32), jnp.zeros(B, jnp.int32), jnp.zeros(B, jnp.int32))
    consts = tuple(jnp.asarray(x, f32) for x in (w0, w1, r0, r1)) + (jnp.asarray(truth), E, H, G)
    chunk = _chunk_fn(cfg, mc, poles)
    carry = (jnp.asarray(th0, f32), es, ms, track)
    noisy = np.flatnonzero(jit)
    rng = np.random.default_rng(seed)
    n_chunks = int(math.ceil(seconds * TICK_HZ / CHUNK))
    for c in range(n_chunks):
        # the jitter drawn here, a chunk at a time, while XLA's thread runs the chunk before (JAX's
        # threefry inside the scan was ~30 % of its CPU: rolled loops of small operations each tick)
        noise = np.zeros((CHUNK, B), np.float32)
        noise[:, noisy] = rng.standard_normal((CHUNK, noisy.size), np.float32) * jit[noisy].astype(np.float32)
        carry = chunk(carry, consts, tables, tb, jnp.int32(c * CHUNK), noise)
    _, _, ms, (first, rfirst, wrong, resets) = carry
    first = np.asarray(first)
    return PowerUpResult(truth=truth, first_id_s=np.where(first >= 0, first / TICK_HZ, np.nan),
                         r_first=np.asarray(rfirst), wrong_ticks=np.asarray(wrong),
                         active_end=np.asarray(ms.active), resets=np.asarray(resets),
                         score=np.asarray(ms.score), margin=np.asarray(ms.margin))


@functools.lru_cache(maxsize=8)
def _chunk_fn(cfg: est.EstimatorConfig, mc: MechConsts, poles: int
              ) -> Callable[[_Carry, tuple[jax.Array, ...], est.HallTables, MechTables, jax.Array, np.ndarray], _Carry]:
    """The jitted scan over CHUNK ticks of a batch (one compile per configuration and batch shape); its
    last argument the chunk's jitter (CHUNK, power-ups), rad mechanical."""
    import jax
    import jax.numpy as jnp

    f32 = jnp.float32
    N = cfg.N_enc

    def sig(th, e, h, g):
        return encoder_hall_signals(th, poles, N, SensorErrors(e, h, g), xp=jnp)

    @jax.jit
    def chunk(carry, consts, tables, tb, start, noise):
        w0_, w1_, r0_, r1_, tr, E, H, G = consts

        def body(c, xs):
            i, jitter = xs
            th, es, ms, (first, rfirst, wrong, resets) = c
            k = (start + i).astype(f32)
            w = w0_ + (w1_ - w0_) * jnp.clip((k - r0_) / (r1_ - r0_), 0.0, 1.0)
            th = jnp.mod(th + w * f32(1.0 / TICK_HZ), f32(2 * math.pi))
            ths = th + jitter
            a, b, h = jax.vmap(sig)(ths, E, H, G)
            # the edge event, the re-anchor and the identifier's interrupt part only on the ticks some
            # power-up needs them (the same result: batch_axis, batched_tick); an edge's entry of the
            # pitch tables written alone (scatter_tables: this scan is no loop kernel)
            es, eo, ps = jax.vmap(lambda s, a, b, h, t: step_pitch(cfg, s, a, b, h, xp=jnp, tables=t, batch_axis=_AXIS,
                                                                   scatter_tables=True),
                                  axis_name=_AXIS)(es, a, b, h, tables)
            ms, mo = jax.vmap(lambda m, t, s, o, p: batched_tick(mc, t, m, s, o, p, _AXIS, scatter=True), axis_name=_AXIS)(
                ms, tb, es, eo, ps)
            # the background's arithmetic only for the power-ups that need it (the same identification;
            # the score and margin within a few units in the last place: batched_background_few)
            ms = batched_background_few(mc, tb, ms, es, _FEW)
            on = mo.active != 0
            new_first = (first < 0) & on
            first = jnp.where(new_first, start + i, first)
            rfirst = jnp.where(new_first, mo.r, rfirst)
            wrong = wrong + (on & (mo.r != tr)).astype(jnp.int32)
            resets = resets + ((mo.events & _RESETS) != 0).astype(jnp.int32)
            return (th, es, ms, (first, rfirst, wrong, resets)), None

        carry, _ = jax.lax.scan(body, carry, (jnp.arange(CHUNK, dtype=jnp.int32), noise))
        return carry

    return chunk
