"""The bench simulation: a ``lax.scan`` over 20 kHz PWM ticks of a lot of motors, the tick ``vmap``-ped.

One tick is :mod:`eol_cal.plant.tick`'s (sensors, estimator, ECU, inverter, motor, shaft), then the
ECU identifier's background slice for the whole lot (:func:`eol_cal.plant.tick.background`); for a
lot whose ECUs identify, the slices that evaluate run out of the tick loop
(:func:`_identifying_ticks`), in the same order.

Everything runs in float32. The scan is cut into chunks of fixed length so that one compiled
program serves any duration, and each chunk's outputs are copied to the host as they come.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from eol_cal.capture.ecu_state import EcuState, with_ecu_state
from eol_cal.capture.data import Capture
from eol_cal.errors import InputError
from eol_cal.domain.bench_mechanics import SIMULATED_BENCH_KEY, model_digest
from eol_cal.firmware.block import ParamBlock
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE
from eol_cal.firmware.mech import MechConsts, block_mech_tables
from eol_cal.firmware.settling import settle_s
from eol_cal.plant import control
from eol_cal.plant.ecu_model import batch_options, estimator_config, simulated_ecu_state, true_block
from eol_cal.plant.params import PlantSpec, to_params
from eol_cal.plant.profile import Profile
from eol_cal.plant.tick import (
    BATCH_AXIS, OUT_COLUMNS, TWO_PI, PlantSimConfig, background, background_heavy, background_idle, background_pending,
    initial_carry, sense, tick,
)
from eol_cal.numerics import exported
from eol_cal.numerics.packing import Packing, pack, pack_stacked, packing_of, unpack
from eol_cal.numerics.xla import configure_xla  # noqa: F401 - the CLI's and benchmarks' entry (was defined here)

#: ticks of one draw of sensor noise (and the unit of a chunk's length)
NOISE_BLOCK = 1000


@dataclass(frozen=True)
class PlantCarry:
    """Where a run of :func:`simulate` ended: the scan's state (plant, estimator, ECU, identifier;
    every motor of the batch; packed, :mod:`eol_cal.numerics.packing`, as ``packing`` says) and the
    configuration it was compiled for, to go on from (``simulate(resume=...)``): the motor turns
    on and the ECU keeps what it learned."""

    cfg: PlantSimConfig
    state: Any
    packing: Packing


@dataclass(frozen=True)
class SimResult:
    """One motor's run: the capture plus the angles (rad) only a simulator knows, for plots and tests.

    ``mech_active`` (0/1 per sample): the ECU's mechanical-order compensation was identified and
    running; ``theta_m`` the rotor's true mechanical angle (rad, [0, 2*pi)).
    """

    capture: Capture
    theta_r: np.ndarray
    theta_hat: np.ndarray
    theta_enc: np.ndarray
    mech_active: np.ndarray | None = None
    theta_m: np.ndarray | None = None


_COMPILED: dict[tuple, Any] = {}  # compiled chunks, and primes with their carry's packing
# held while a program of _COMPILED is built: a what-if batch's motor threads asked for the same
# program at once, and each traced and compiled its own (three compiles of the prime where one does:
# 0.7 CPU s alone, 2.2-2.5 s each beside the others, 2026-12-02); one jitted function called from
# several threads compiles once (JAX waits)
_BUILDING = threading.Lock()


def _built(cache: dict, key: Any, build: Callable[[], Any]) -> Any:
    """``cache[key]``, made by ``build()`` under :data:`_BUILDING` when it is not there yet."""
    with _BUILDING:
        got = cache.get(key)
        if got is None:
            got = cache[key] = build()
    return got

#: part of the key of the plant's exported programs (with the package's code digest: any change to
#: the code traces them afresh)
_EXPORT_TAG = "eol-cal-plant-1"
_KEYS: dict[int, Callable] = {}  # the motors' noise keys of a seed, by the batch's size

def _chunk_fn(cfg: PlantSimConfig, n_ticks: int, unroll: int, p_pack: Packing, c_pack: Packing) -> Callable:
    """Compiled ``(params, carry, shared_xs, keys, first_block) -> (carry, outputs)`` for a batch,
    its parameters and carry packed as ``p_pack`` and ``c_pack`` say (:mod:`eol_cal.numerics.packing`:
    a few arrays to dispatch, not one per leaf).

    ``keys`` holds one PRNG key per motor; the sensor noise of every block of :data:`NOISE_BLOCK`
    ticks is drawn from ``fold_in(key, block)`` (its torque-transducer draws, one a tick, and its
    current-sensor draws, three a current-control tick), so a run does not depend on how it is
    cut into chunks.
    """
    return _built(_COMPILED, (cfg, n_ticks, unroll, p_pack, c_pack),
                  lambda: _build_chunk(cfg, n_ticks, unroll, p_pack, c_pack))


def _build_chunk(cfg: PlantSimConfig, n_ticks: int, unroll: int, p_pack: Packing, c_pack: Packing) -> Callable:
    import jax
    import jax.numpy as jnp

    n_blocks = n_ticks // NOISE_BLOCK
    n_cc = _cc_per_block(cfg)

    def block_noise(key, block):
        k_tq, k_i = jax.random.split(jax.random.fold_in(key, block))
        return (jax.random.normal(k_tq, (NOISE_BLOCK,), dtype=jnp.float32),
                jax.random.normal(k_i, (n_cc, 3), dtype=jnp.float32))

    def motor_noise(key, first_block):
        tq_noise, i_noise = jax.vmap(block_noise, in_axes=(None, 0))(key, first_block + jnp.arange(n_blocks))
        return tq_noise.reshape(-1), i_noise.reshape(-1, 3)

    # the scan over the batch's ticks, each tick vmapped over the motors: the identifier's
    # background (tick.background) then branches once for the whole batch
    one_tick = jax.vmap(lambda p, i_noise, c, x: tick(cfg, p, i_noise, c, x), in_axes=(0, 0, 0, (None,) * 5 + (0,)),
                        axis_name=BATCH_AXIS)

    def chunk(p, carry, shared, keys, first_block):
        p, carry = unpack(p_pack, p), unpack(c_pack, carry)
        tq_noise, i_noise = jax.vmap(motor_noise, in_axes=(0, None))(keys, first_block)
        xs = (*shared, tq_noise.T)
        if cfg.mech is None:
            def body(c, x):
                c, y = one_tick(p, i_noise, c, x)
                return background(cfg, p, c), y

            carry, ys = jax.lax.scan(body, carry, xs, unroll=unroll)
        else:
            carry, ys = _identifying_ticks(cfg, p, lambda c, x: one_tick(p, i_noise, c, x), carry, xs, n_ticks)
        return pack(c_pack, carry, jnp), ys.transpose(1, 2, 0)  # motor- and channel-major: the host converts contiguous rows

    return jax.jit(chunk)


def _identifying_ticks(cfg: PlantSimConfig, p: Any, one_tick: Callable, carry: Any, xs: tuple, n_ticks: int
                       ) -> tuple[Any, Any]:
    """``lax.scan(tick, then background)`` over a chunk's ticks for a batch whose ECUs identify,
    with the background's evaluation out of the tick loop, as the firmware runs it out of its
    interrupt.

    The ticks run in an inner loop, each followed by the identifier's background slice while it
    computes nothing (:func:`eol_cal.plant.tick.background_idle`); the inner loop stops after a
    tick where some motor's slice computes (an evaluation's first slice, a revolution mark's
    check: a few per revolution and motor), and the outer loop runs that slice for the batch
    (:func:`eol_cal.plant.tick.background_heavy`) before going on: every tick and slice in the
    scan's order, the same arithmetic. The evaluation's sums are library kernels of XLA's CPU
    backend, which keep the loop around them from being compiled into one kernel
    (:mod:`eol_cal.numerics.xla`); with them out of it, the inner loop is one (layout 2, batch of
    64: ~1.5x faster per tick where the process enables the loop kernel). Runs unrolled 1.
    """
    import jax
    import jax.numpy as jnp

    n_out = len(OUT_COLUMNS)
    ys0 = jnp.zeros((n_ticks, jax.tree_util.tree_leaves(carry)[0].shape[0], n_out), jnp.float32)

    def inner(state):
        t, c, ys, _ = state
        x = tuple(jax.lax.dynamic_index_in_dim(a, t, keepdims=False) for a in xs)
        c, y = one_tick(c, x)
        pending = background_pending(c)
        # the idle slice's few counters by select, not a branch (a branch's operands, the whole
        # carry, would be copied every tick); the selects keep every other value as it is
        idle = background_idle(cfg, p, c)
        c = jax.tree_util.tree_map(lambda k, i: jnp.where(pending, k, i), c, idle)
        return t + 1, c, jax.lax.dynamic_update_index_in_dim(ys, y, t, 0), pending

    def outer(state):
        t, c, ys, pending = jax.lax.while_loop(lambda s: (s[0] < n_ticks) & ~s[3], inner, state)
        c = jax.lax.cond(pending, lambda c: background_heavy(cfg, p, c), lambda c: c, c)
        return t, c, ys, jnp.zeros_like(pending)

    state = (jnp.int32(0), carry, ys0, jnp.bool_(False))
    _, carry, ys, _ = jax.lax.while_loop(lambda s: s[0] < n_ticks, outer, state)
    return carry, ys


def _kept(name: str, parts: tuple, build: Callable[[], Callable], args: tuple) -> Callable:
    """``build()`` (a jitted program of the plant) for ``args``, kept between processes where a
    cache directory is set (:func:`eol_cal.numerics.exported.kept`; a station's first motor then
    reads its plant's programs instead of tracing them): keyed by ``parts`` (the static
    configuration and packings), the argument shapes and the package's code
    (:func:`~eol_cal.numerics.exported.code_digest`); bit for bit the traced program's (test)."""
    if exported.cache_dir() is None:  # no digest of the sources to make
        return build()
    return exported.kept(name, _EXPORT_TAG, (exported.code_digest(), parts), build, args)


def _motor_keys(seed: int, n_motors: int) -> Any:
    """``jax.random.split(jax.random.PRNGKey(seed), n_motors)``: one compiled call for a seed in
    int32's range (the same keys; the two calls one by one cost ~0.5 ms, a one-motor second's
    twentieth), the calls one by one for another."""
    import jax

    if not -2**31 <= seed < 2**31:
        return jax.random.split(jax.random.PRNGKey(seed), n_motors)
    fn = _built(_KEYS, n_motors, lambda: jax.jit(lambda s: jax.random.split(jax.random.PRNGKey(s), n_motors)))
    return fn(seed)


def _cc_per_block(cfg: PlantSimConfig) -> int:
    """Current-noise draws of a noise block: more than the current-control ticks it can hold."""
    return math.ceil(NOISE_BLOCK * cfg.f_cc / cfg.f_pwm) + 1


def _cc_index(cc: np.ndarray, n_cc: int, chunk_ticks: int) -> np.ndarray:
    """For each tick of a run cut into chunks of ``chunk_ticks`` (whole noise blocks), the
    current-noise draw a current-control tick reads in its chunk's draws: its block's, in the
    order of the block's current-control ticks."""
    per_block = cc.reshape(-1, NOISE_BLOCK)
    j = np.maximum(np.cumsum(per_block, axis=1, dtype=np.int32) - 1, 0)
    block_in_chunk = np.arange(len(per_block), dtype=np.int32) % np.int32(chunk_ticks // NOISE_BLOCK)
    return (j + np.int32(n_cc) * block_in_chunk[:, None]).reshape(-1)


def chunk_ticks_for(n_motors: int) -> int:
    """Ticks per compiled scan call for a batch of ``n_motors``: about 64 000 motor-ticks of outputs
    per call (they stay in the CPU's caches: at 64 motors, 1000-tick chunks run ~20 % faster
    than 4000-tick ones), at least one noise block, at most four."""
    return NOISE_BLOCK * max(1, min(4, 64 // max(1, n_motors)))


def _prime_fn(cfg: PlantSimConfig, p_pack: Packing, i_pack: Packing) -> tuple[Callable, Packing]:
    """Compiled ``(params, carry) -> carry`` that turns a batch's initial ``(plant, estimator state,
    ECU, identifier state)`` (packed as ``i_pack`` says) into the scan's carry with the first
    tick's :class:`eol_cal.plant.tick.Sensed`, packed; and that carry's packing."""
    return _built(_COMPILED, (cfg, "prime", p_pack, i_pack), lambda: _build_prime(cfg, p_pack, i_pack))


def _build_prime(cfg: PlantSimConfig, p_pack: Packing, i_pack: Packing) -> tuple[Callable, Packing]:
    import jax
    import jax.numpy as jnp

    def one_motor(p, carry):
        plant, est_state, ecu, mech_state = carry
        est_state, sensed = sense(cfg, p, plant.theta_m, est_state, mech_state)
        return plant, est_state, ecu, sensed

    def primed(p, carry):
        p, carry = unpack(p_pack, p), unpack(i_pack, carry)
        carry = jax.vmap(one_motor, axis_name=BATCH_AXIS)(p, carry)
        # From power-on the identifier's first slice computes nothing (no evaluation is due
        # before a revolution of samples, no mark check before one identified): background's
        # branch takes its idle side, which alone compiles and runs in a fraction of the time
        return carry if cfg.mech is None else background_idle(cfg, p, carry)

    # the carry's layout, from one motor's shapes (tracing only)
    shapes = [tuple(jax.ShapeDtypeStruct((1, n), d) for n, d in zip(pk.sizes, pk.dtypes, strict=True))
              for pk in (p_pack, i_pack)]
    c_pack = packing_of(jax.eval_shape(primed, *shapes), lead=1)
    return jax.jit(lambda p, carry: pack(c_pack, primed(p, carry), jnp)), c_pack


def simulate(
    specs: PlantSpec | Sequence[PlantSpec],
    profile: Profile,
    mode: str = "estimated",
    blocks: ParamBlock | Sequence[ParamBlock | None] | None = None,
    seed: int = 0,
    pre_roll_s: float | None = None,
    chunk_ticks: int | None = None,
    unroll: int = 1,
    progress: Callable[[float], None] | None = None,
    ecu_estimator: str | None = None,
    recorded: Callable[[list[SimResult]], None] | None = None,
    resume: PlantCarry | None = None,
    carry_out: list[PlantCarry] | None = None,
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
        :func:`eol_cal.firmware.settling.settle_s` (longer when the estimator learns pitch errors).
    chunk_ticks : int, optional
        Scan chunk length (ticks, a multiple of :data:`NOISE_BLOCK`; speed only): default
        :func:`chunk_ticks_for` the batch.
    unroll : int
        Unroll factor of the scan (speed only; a lot whose ECUs identify runs its split loop,
        :func:`_identifying_ticks`, unrolled 1).
    progress : callable, optional
        Called with the fraction done after each chunk.
    ecu_estimator : str, optional
        Overrides the blocks' estimator options: ``paper``, ``best``, option names joined by
        ``+`` or a hex mask (:func:`eol_cal.firmware.options.parse_options`); for runs without
        a block.
    recorded : callable, optional
        Called after each chunk that recorded ticks with the results so far: each motor's first
        recorded ticks, final (views into the arrays the next chunks fill on; copy what is kept).
        A real-time dyno simulator answers them while the rest is computed.
    resume : PlantCarry, optional
        Go on from where an earlier run of the same batch, mode and blocks ended (its
        ``carry_out``): no pre-roll, no fresh start; the profile's first tick follows that run's
        last (the ECU's control-rate phase restarts, a glitch of one command period; use a ramp
        first). Refused for another configuration.
    carry_out : list, optional
        The run's end state is appended to it (:class:`PlantCarry`), a few ticks into the last
        chunk's padding.

    Returns
    -------
    list of SimResult
    """
    if mode not in control.MODES:
        raise InputError(None, "mode", f"unknown mode {mode!r}; known: {', '.join(control.MODES)}")
    specs = [specs] if isinstance(specs, PlantSpec) else list(specs)
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
    identifies = False
    for spec, block in zip(specs, blocks, strict=True):
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
            mtb = block_mech_tables(block)
            identifies |= bool(mtb.enabled) and mode != "raw"
        else:
            tc = tp = np.zeros(16, np.float32)
            lead = lim = 0.0
            hall = NOMINAL_HALL_ANGLE
            mtb = None
        params.append(to_params(spec, tc, tp, lead, lim, hall_angle=hall, mech_tb=mtb))
    lens = {len(p.table_const) for p in params}
    if len(lens) != 1:
        raise InputError(None, "blocks", "a batch must share one table length")
    # the lot's parameters as one array (a few arrays for the compiled calls to take, not one a leaf)
    p_pack = packing_of(params[0])
    batch = pack_stacked(p_pack, params)
    options = batch_options(effective, ecu_estimator)

    est_cfg = estimator_config(specs[0], options=options)
    identifies &= est_cfg.learn_pitch_errors
    cfg = PlantSimConfig(poles=m0.poles, N_enc=m0.N_enc, f_pwm=m0.f_pwm, f_cc=m0.f_cc, f_cmd=m0.f_cmd,
                    # nominal table: each motor's own travels in its PlantParams (one program for all)
                    mode=mode, estimator=est_cfg,
                    dead_time=any(s.dead_time_s > 0 for s in specs),
                    mech=MechConsts.of(est_cfg) if identifies else None)

    speed_rpm, i_qo = profile.ticks(m0.f_pwm, m0.kt)
    if resume is not None:
        if resume.cfg != cfg:
            raise InputError(None, "resume", "the run to go on from was made for other motors, mode or blocks")
        pre_roll_s = 0.0
    elif pre_roll_s is None:
        pre_roll_s = settle_s(options, float(speed_rpm[0]), identifies)
    n_pre = int(round(pre_roll_s * m0.f_pwm))
    speed_rpm = np.concatenate([np.full(n_pre, speed_rpm[0]), speed_rpm])
    i_qo = np.concatenate([np.full(n_pre, i_qo[0]), i_qo])
    n_total = len(speed_rpm)
    omega_ref = (speed_rpm * TWO_PI / 60.0).astype(np.float32)
    i_qo = i_qo.astype(np.float32)
    cc = control.rate_flags(n_total, m0.f_pwm, m0.f_cc)
    cmd = control.rate_flags(n_total, m0.f_pwm, m0.f_cmd)

    if resume is not None:
        carry, c_pack = resume.state, resume.packing
    else:
        rng = np.random.default_rng(seed)
        carries = [initial_carry(cfg, p, s, float(rng.uniform(0.0, TWO_PI)), float(omega_ref[0]), float(i_qo[0]))
                   for p, s in zip(params, specs, strict=True)]
        i_pack = packing_of(carries[0])
        traced_prime, c_pack = _prime_fn(cfg, p_pack, i_pack)
        initial = pack_stacked(i_pack, carries)
        prime = _kept("plant-prime", (cfg, p_pack, i_pack), lambda: traced_prime, (batch, initial))
        carry = prime(batch, initial)
    keys = _motor_keys(seed, len(specs))

    chunk_ticks = chunk_ticks_for(len(specs)) if chunk_ticks is None else int(chunk_ticks)
    if chunk_ticks < NOISE_BLOCK or chunk_ticks % NOISE_BLOCK:
        raise InputError(None, "chunk_ticks", f"{chunk_ticks}: needs a multiple of {NOISE_BLOCK}")
    n_cc = _cc_per_block(cfg)
    # the recorded ticks (after the pre-roll) go straight into the captures' arrays, converted to
    # their dtypes on the way (one pass over the outputs; no float32 copy of the whole run first)
    n_rec = n_total - n_pre
    cols = {name: np.empty((len(specs), n_rec), _DTYPES.get(name, np.float64)) for name in OUT_COLUMNS}
    # The last chunk runs padded (its extra ticks are dropped with the carry after them).
    pad = -n_total % chunk_ticks
    inputs = tuple(np.pad(a, (0, pad), mode="edge") for a in (omega_ref, i_qo, cc, cmd))
    inputs += (_cc_index(inputs[2], n_cc, chunk_ticks),)
    fn = _kept("plant-chunk", (cfg, chunk_ticks, unroll, p_pack, c_pack),
               lambda: _chunk_fn(cfg, chunk_ticks, unroll, p_pack, c_pack),
               (batch, carry, tuple(a[:chunk_ticks] for a in inputs), keys, np.int32(0)))
    t = np.arange(n_rec, dtype=np.float64) / m0.f_pwm
    t.flags.writeable = False  # one time base shared by the lot's captures

    def results(n: int) -> list[SimResult]:
        return [_to_result(t[:n], {name: c[i, :n] for name, c in cols.items()}, specs[i], profile, mode, blocks[i],
                           states[i]) for i in range(len(specs))]

    for start in range(0, n_total, chunk_ticks):
        stop = min(start + chunk_ticks, n_total)
        shared = tuple(a[start:start + chunk_ticks] for a in inputs)
        carry, ys = fn(batch, carry, shared, keys, np.int32(start // NOISE_BLOCK))
        lo = max(start, n_pre)
        if lo < stop:
            ys = np.asarray(ys)
            for k, name in enumerate(OUT_COLUMNS):
                cols[name][:, lo - n_pre:stop - n_pre] = ys[:, k, lo - start:stop - start]
            if recorded is not None and stop < n_total:
                recorded(results(stop - n_pre))
        if progress is not None:
            progress(stop / n_total)
    if carry_out is not None:
        carry_out.append(PlantCarry(cfg, carry, c_pack))
    return results(n_rec)


#: capture dtypes of the scan's outputs (float64 otherwise): digital levels as the readers give them
_DTYPES = {"enc_a": np.int8, "enc_b": np.int8, "hall": np.int8}


def _to_result(t: np.ndarray, col: dict[str, np.ndarray], spec: PlantSpec, profile: Profile, mode: str,
               block: ParamBlock | None, ecu: EcuState) -> SimResult:
    m = spec.motor
    n = len(t)
    channels: dict[str, np.ndarray] = {name: col[name] for name in ("enc_a", "enc_b", "hall", "torque", "iq_ref",
                                                                    "iqc", "iq", "id", "ia", "ib", "ic", "speed")}
    channels["temp"] = np.full(n, spec.temp_degC)
    metadata: dict[str, str | int | float] = {
        "serial": spec.serial, "poles": m.poles, "encoder_ppr": m.N_enc, "kt": m.kt,
        "source": "plant", "comment": f"eol-cal plant, mode {mode}, profile {profile.name}",
        # the bench the plant simulated: a fit whose bench file makes the same torque path knows it
        # exactly (eol_cal.analysis.bench_provenance)
        SIMULATED_BENCH_KEY: model_digest(spec.mechanics),
    }
    metadata = with_ecu_state(metadata, ecu, ecu)  # the simulated ECU runs one block all along
    truth = spec.truth()
    truth.update({"mode": mode, "profile": profile.name})
    if block is not None and mode == "compensated":
        truth.update({"block_k6": block.k6, "block_c6": block.c6, "block_lead_s": block.lead_s})
    cap = Capture(t=t, channels=channels, metadata=metadata, truth=truth, source="<plant>")
    return SimResult(cap, col["theta_r"], col["theta_hat"], col["theta_enc"], col["mech_active"].astype(np.int8),
                     col["theta_m"])
