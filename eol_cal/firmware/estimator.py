"""Rotor angle and speed estimator of the ECU firmware (seed paper section III.A, eqs. 13-16).

Once per PWM tick (``tick_hz``, 20 kHz on the paper's bench) the firmware samples the encoder
channels A and B and the three hall sensors and updates its estimate:

* a quadrature counter ``q`` (x4, modulo ``4*N_enc``) tracks the encoder position in quarter
  pitches, so reversals, bounces and lost pulses keep the edge grid consistent;
* ``N_c`` (eq. 13) counts ticks between consecutive rising edges of A in the same direction;
  ``omega_hat = P*pi / (N_enc*N_c*T)`` (eq. 15), its sign from B at A's edge;
* ``theta_hat`` is re-anchored to the angle of each A rising edge and advanced by
  ``omega_hat*T`` every tick in between (eq. 16);
* each hall transition gives the absolute angle (the ``hall_angle`` table) and corrects the
  encoder grid's offset ``G`` against it ("the absolute rotor position is updated every 60
  electrical degrees").

:func:`step` is written once with ``xp`` operations only (no Python branch on values), so with
``xp=numpy`` on scalars it is the bit-exact binary32 reference for the C port
(``firmware_params/c/eol_est.c``) and the golden vectors, and with ``xp=jax.numpy`` it traces
inside ``jit``/``vmap``/``lax.scan`` (the plant's ECU). The exact algorithm, state variables,
constants and order of operations are in ``firmware_params/ESTIMATOR.md``; keep the three in step.

The reference is split by concern: :mod:`eol_cal.firmware.estimator_config` (configuration,
options, binary32 constants, hall tables), :mod:`eol_cal.firmware.estimator_step` (state and one
tick) and this module, which runs the tick over whole captures (numpy, JAX) and re-exports the
other two, so ``estimator.X`` names every public piece.
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,union-attr,index"

import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.numerics import exported
from eol_cal.numerics.arrays import Array
from eol_cal.firmware.estimator_config import (
    F32, HALF, HALL_NEXT, I32, INV_TWO_PI, K_ACC, K_PITCH, N_LEARN, NOMINAL_HALL_ANGLE, PI,
    ST_DIR_MISMATCH, ST_EDGE_REJECT, ST_HALL_FAULT, ST_HALL_SEQ, ST_MISSING_EDGE, ST_NO_ANCHOR,
    ST_NO_SPEED, ST_QEP_ERROR, ST_REVERSE, ST_STANDSTILL, STATUS_BITS, STEADY_TICKS, TICK_MASK, TWO_PI,
    Consts, EstimatorConfig, HallTables, consts, hall_tables, wrap, wrap_pm,
)
from eol_cal.firmware.estimator_config import OPTION_FLAGS, options_from_flags
from eol_cal.firmware.estimator_step import (
    EstimatorOut, EstimatorState, PitchSample, init_state, quadrature_phase, step, step_pitch,
)
from eol_cal.firmware.scalar_numpy import SCALAR_NP

if TYPE_CHECKING:
    import jax



#: the estimator's public names, those of estimator_config and estimator_step included
__all__ = [
    "F32",
    "HALF",
    "HALL_NEXT",
    "I32",
    "INV_TWO_PI",
    "K_ACC",
    "K_PITCH",
    "N_LEARN",
    "NOMINAL_HALL_ANGLE",
    "PI",
    "ST_DIR_MISMATCH",
    "ST_EDGE_REJECT",
    "ST_HALL_FAULT",
    "ST_HALL_SEQ",
    "ST_MISSING_EDGE",
    "ST_NO_ANCHOR",
    "ST_NO_SPEED",
    "ST_QEP_ERROR",
    "ST_REVERSE",
    "ST_STANDSTILL",
    "STATUS_BITS",
    "STEADY_TICKS",
    "TICK_MASK",
    "TWO_PI",
    "Consts",
    "EstimatorConfig",
    "HallTables",
    "consts",
    "hall_tables",
    "wrap",
    "wrap_pm",
    "OPTION_FLAGS",
    "options_from_flags",
    "EstimatorOut",
    "EstimatorState",
    "PitchSample",
    "init_state",
    "quadrature_phase",
    "step",
    "step_pitch",
    "run",
    "run_jax",
    "run_jax_chunked",
    "run_jax_batch",
    "start_jax_batch",
    "StartedRun",
    "JAX_CHUNK",
    "JAX_LANES",
]

def run(cfg: EstimatorConfig, enc_a: Array, enc_b: Array, hall: Array) -> EstimatorOut:
    """Run the estimator over sampled signals with numpy, tick by tick (the bit-exact reference).

    The power-on state takes the first sample's levels (:func:`init_state`), then every sample,
    the first included, is one tick.

    Parameters
    ----------
    cfg : EstimatorConfig
    enc_a, enc_b : int arrays (n,)
        Encoder levels per tick (0/1).
    hall : int array (n,)
        Hall state per tick (0..7).

    Returns
    -------
    EstimatorOut of numpy arrays (n,): float32 theta_hat (rad), omega_hat (rad/s), theta_enc
    (rad), int32 status.
    """
    a = np.asarray(enc_a, dtype=np.int32)
    b = np.asarray(enc_b, dtype=np.int32)
    h = np.asarray(hall, dtype=np.int32)
    n = len(a)
    th = np.empty(n, F32)
    om = np.empty(n, F32)
    te = np.empty(n, F32)
    st = np.empty(n, np.int32)
    if n == 0:
        return EstimatorOut(th, om, te, st)
    state = init_state(cfg, h[0], a[0], b[0])
    state = EstimatorState(*(x[()] if x.ndim == 0 else x for x in state))
    for i in range(n):
        state, out = step(cfg, state, a[i], b[i], h[i], xp=SCALAR_NP)
        th[i], om[i], te[i], st[i] = out
    return EstimatorOut(th, om, te, st)


def _jax_tables(cfg: EstimatorConfig, hall_angle: Sequence[float] | None) -> HallTables:
    """The hall lookups of ``hall_angle`` (default: the config's) as JAX arrays, a dynamic argument."""
    import jax.numpy as jnp

    return HallTables(*(jnp.asarray(t) for t in hall_tables(cfg.hall_angle if hall_angle is None else hall_angle)))


def _program_config(cfg: EstimatorConfig) -> EstimatorConfig:
    """``cfg`` with the nominal hall table: the compiled scans get the table as an argument, so
    configurations that differ only in it share one program."""
    return dataclasses.replace(cfg, hall_angle=NOMINAL_HALL_ANGLE)


def run_jax(cfg: EstimatorConfig, enc_a: Array, enc_b: Array, hall: Array,
            hall_angle: Sequence[float] | None = None) -> EstimatorOut:
    """The same as :func:`run` under ``jax.lax.scan`` (float32 tolerance, not bit-exact).

    Accepts leading batch dimensions before the time axis (vmapped).

    Parameters
    ----------
    hall_angle : sequence of 6 float, optional
        The ``hall_angle`` table (rad) to run with instead of ``cfg.hall_angle`` (shared by the
        batch); a dynamic argument of the compiled program.
    """
    import jax
    import jax.numpy as jnp

    a = jnp.asarray(enc_a, jnp.int32)
    b = jnp.asarray(enc_b, jnp.int32)
    h = jnp.asarray(hall, jnp.int32)
    tables = _jax_tables(cfg, hall_angle)
    pcfg = _program_config(cfg)

    def one(a1, b1, h1, tb):
        s0 = init_state(pcfg, h1[0], a1[0], b1[0], xp=jnp)

        def body(s, x):
            return step(pcfg, s, x[0], x[1], x[2], xp=jnp, tables=tb)

        _, out = jax.lax.scan(body, s0, jnp.stack([a1, b1, h1], axis=-1))
        return out

    f = one
    for _ in range(a.ndim - 1):
        f = jax.vmap(f, in_axes=(0, 0, 0, None))
    return jax.jit(f)(a, b, h, tables)


#: ticks per call of the chunked runners' compiled scan
JAX_CHUNK = 1024

#: lanes (captures) of one compiled batched scan: a batch is padded up to the next of these (or
#: split at the last), so a few programs serve every batch size
JAX_LANES = (1, 2, 4, 8, 16, 24, 32, 48, 64)


#: part of the key of the estimator's exported programs: bump it when :func:`step` or the programs change
_EXPORT_TAG = "eol-cal-estimator-2"

#: ``axis_name`` of the batched scan's lanes: the step's A edge event and hall re-anchor run on the
#: ticks some lane has one (:func:`~eol_cal.firmware.scalar_numpy.when`), not on every tick
LANE_AXIS = "lanes"


@functools.lru_cache(maxsize=16)
def _scan_chunk(cfg: EstimatorConfig) -> Callable[..., tuple[jax.Array, ...]]:
    """The jitted scan over one chunk of ticks of a batch of captures, each lane with its own
    state and hall tables (one program per config and lane count; the hall tables are an
    argument, so call it with :func:`_program_config`), on flat arguments (an exported program
    takes and gives plain tuples): ``(*state[B], abh[chunk, B, 3], *tables[B]) -> (*state[B],
    *out[chunk, B])``; :func:`_scan` rebuilds the tuples."""
    import jax
    import jax.numpy as jnp

    def one(s, abh, tables):
        def body(s, x):
            return step(cfg, s, x[0], x[1], x[2], xp=jnp, tables=tables, batch_axis=LANE_AXIS)

        return jax.lax.scan(body, s, abh)

    batched = jax.vmap(one, in_axes=(0, 1, 0), out_axes=(0, 1), axis_name=LANE_AXIS)
    n_state = len(EstimatorState._fields)

    def flat(*args):
        state, out = batched(EstimatorState(*args[:n_state]), args[n_state], HallTables(*args[n_state + 1:]))
        return (*state, *out)

    return jax.jit(flat)


def _program(kind: str, cfg: EstimatorConfig, build: Callable[[EstimatorConfig], Callable[..., tuple]],
             args: tuple) -> Callable[..., tuple[jax.Array, ...]]:
    """``build(cfg)`` (:func:`_scan_chunk`) for ``args``, kept between processes
    (:func:`eol_cal.numerics.exported.kept`, when the CLI or the station set a cache directory):
    the key holds everything that changes the trace (the configuration, the argument shapes and
    dtypes, :data:`_EXPORT_TAG`, the JAX version). The same program either way: its outputs are
    bit for bit the traced one's (tests/test_estimator_export.py).
    """
    return exported.kept(f"est-{kind}", _EXPORT_TAG, cfg, lambda: build(cfg), args)


def _scan(program: Callable[..., tuple[jax.Array, ...]], state: EstimatorState, abh: np.ndarray, tables: HallTables
          ) -> tuple[EstimatorState, EstimatorOut]:
    """One chunk of the batched scan: ``program`` (:func:`_scan_program`) from ``state``."""
    res = program(*state, abh, *tables)
    n_state = len(EstimatorState._fields)
    return EstimatorState(*res[:n_state]), EstimatorOut(*res[n_state:])


def _scan_program(cfg: EstimatorConfig, state: EstimatorState, abh: np.ndarray, tables: HallTables
                  ) -> Callable[..., tuple[jax.Array, ...]]:
    """The compiled chunk of the batched scan (:func:`_scan_chunk`, kept between processes:
    :func:`_program`) for every chunk of a run: its key (the configuration's text, the arguments'
    shapes) built once a run, not once a chunk."""
    return _program("scan", cfg, _scan_chunk, (*state, abh, *tables))


def _lanes(n: int) -> int:
    return next((b for b in JAX_LANES if b >= n), JAX_LANES[-1])


class StartedRun:
    """A :func:`start_jax_batch`'s runs, dispatched: JAX computes them on its own thread while the
    caller goes on; :meth:`result` waits for them."""

    def __init__(self, parts: list[tuple[list[EstimatorOut], list[int]]]) -> None:
        self._parts = parts

    def result(self) -> list[EstimatorOut]:
        """Per capture, numpy arrays, one entry per tick (:func:`run_jax_batch`'s)."""
        got = []
        for outs, lengths in self._parts:
            fields = [np.concatenate([np.asarray(o[f]) for o in outs]) for f in range(len(EstimatorOut._fields))]
            got += [EstimatorOut(*(x[:m, i] for x in fields)) for i, m in enumerate(lengths)]
        return got


def run_jax_batch(cfg: EstimatorConfig, signals: Sequence[tuple[Array, Array, Array]],
                  hall_angles: Sequence[Sequence[float] | None] | None = None,
                  chunk: int = JAX_CHUNK) -> list[EstimatorOut]:
    """:func:`run_jax` for many captures of any lengths at once, one compiled program per lane
    count (:data:`JAX_LANES`) for every length and hall table.

    The captures run side by side (``vmap``: each its own state, the same arithmetic per
    lane as :func:`run_jax_chunked`), in chunks of ``chunk`` ticks under ``jax.lax.scan``, the
    states carried from chunk to chunk; a shorter capture is padded with its last sample and
    missing lanes with copies of the first capture (their outputs are discarded).

    Parameters
    ----------
    cfg : EstimatorConfig
        Shared by the captures, except for the hall table.
    signals : sequence of (enc_a, enc_b, hall)
        Per capture, int arrays (n_i,) of encoder levels (0/1) and hall states (0..7).
    hall_angles : sequence of (6 float or None), optional
        Per capture, the ``hall_angle`` table (rad) to run with instead of ``cfg.hall_angle``
        (``None``: the config's); a dynamic argument of the compiled program.

    Returns
    -------
    list of EstimatorOut
        numpy arrays, one entry per tick, one per capture.
    """
    return start_jax_batch(cfg, signals, hall_angles, chunk).result()


def start_jax_batch(cfg: EstimatorConfig, signals: Sequence[tuple[Array, Array, Array]],
                    hall_angles: Sequence[Sequence[float] | None] | None = None,
                    chunk: int = JAX_CHUNK) -> StartedRun:
    """:func:`run_jax_batch` dispatched, not waited for (its arguments): a caller with other work
    does it while JAX's thread computes (a lot refit reads its next motors meanwhile)."""
    import jax

    if not signals:
        return StartedRun([])
    hall_angles = list(hall_angles) if hall_angles is not None else [None] * len(signals)
    if len(hall_angles) != len(signals):
        raise ValueError(f"{len(hall_angles)} hall tables for {len(signals)} captures")
    B = _lanes(len(signals))
    if len(signals) > B:
        return StartedRun([p for k in range(0, len(signals), B)
                           for p in start_jax_batch(cfg, signals[k:k + B], hall_angles[k:k + B], chunk)._parts])
    lengths = [len(a) for a, _, _ in signals]
    n = max(lengths)
    abh = np.empty((n + (-n) % chunk, B, 3), np.int32)
    for j in range(B):
        i = j if j < len(signals) else 0
        for c, x in enumerate(signals[i]):
            abh[:lengths[i], j, c] = x
        abh[lengths[i]:, j] = abh[lengths[i] - 1, j]
    made: dict[tuple[float, ...], HallTables] = {}  # the captures of one motor share its table
    per_lane = []
    for h in hall_angles:
        table = tuple(cfg.hall_angle if h is None else h)
        if table not in made:
            made[table] = hall_tables(table)
        per_lane.append(made[table])
    per_lane += per_lane[:1] * (B - len(per_lane))
    # numpy in: a jnp.asarray here is a program of its own to look up (~0.03 s of a one-capture fit)
    tables = HallTables(*(np.stack(t) for t in zip(*per_lane, strict=True)))
    pcfg = _program_config(cfg)
    # the power-on state is integer logic and zeros: numpy's is the program's, without a program;
    # committed to the device as the scan's own states are (one program for both)
    state = jax.device_put(init_state(pcfg, abh[0, :, 2], abh[0, :, 0], abh[0, :, 1]), jax.devices()[0])
    outs = []
    program = _scan_program(pcfg, state, abh[:chunk], tables)  # every chunk has the first's shapes
    for k in range(0, len(abh), chunk):
        state, out = _scan(program, state, abh[k:k + chunk], tables)
        outs.append(out)
    return StartedRun([(outs, lengths)])


def run_jax_chunked(cfg: EstimatorConfig, enc_a: Array, enc_b: Array, hall: Array, chunk: int = JAX_CHUNK,
                    hall_angle: Sequence[float] | None = None) -> EstimatorOut:
    """:func:`run_jax` for one capture (1-D inputs) with one compiled program for every length:
    :func:`run_jax_batch` of one capture (:func:`run_jax` traces and compiles anew for every
    capture length).

    Parameters
    ----------
    hall_angle : sequence of 6 float, optional
        The ``hall_angle`` table (rad) to run with instead of ``cfg.hall_angle``: a dynamic
        argument, so every table (the config's included) runs in the same compiled program.

    Returns
    -------
    EstimatorOut
        numpy arrays, one entry per tick.
    """
    return run_jax_batch(cfg, [(enc_a, enc_b, hall)], [hall_angle], chunk)[0]
