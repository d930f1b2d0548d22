"""The estimator's configuration and binary32 constants (ESTIMATOR.md, "Inputs, outputs,
configuration" and "Constants"): everything :mod:`eol_cal.firmware.estimator_step` reads but never changes.

The hall convention (contract section 2), the status bits of the outputs, the switchable options
and the constants derived once at init live here; :mod:`eol_cal.firmware.estimator` re-exports them.
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,return-value"

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple
from collections.abc import Sequence

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware.contract import (
    FLAG_EST_ACCEL_PREDICTION,
    FLAG_EST_CLAMP_TO_NEXT_EDGE,
    FLAG_EST_LEARN_GRID_OFFSET,
    FLAG_EST_LEARN_PITCH_ERRORS,
    FLAG_INTERP_ENABLE,
    FLAGS_ESTIMATOR,
    HALL_NEXT,
    NOMINAL_HALL_ANGLE,
)
from eol_cal.firmware.options import honoured_options

if TYPE_CHECKING:
    from eol_cal.firmware.block import ParamBlock

F32 = np.float32


_INT32_SEEN: dict[object, np.int32] = {}


def I32(x: object, _seen: dict[object, np.int32] = _INT32_SEEN, _new: type[np.int32] = np.int32) -> np.int32:
    """``np.int32(x)``, one numpy scalar per integer constant: the tick-by-tick references build the
    same ~50 constants every tick, a numpy construction each against a dict look-up here (same
    value, same type). A constructor only: the dtype is ``np.int32``."""
    try:
        return _seen[x]  # an equal float or numpy integer finds it too
    except (KeyError, TypeError):  # new, or unhashable (an array)
        pass
    v = _new(x)
    if type(x) is int and len(_seen) < 4096:
        _seen[x] = v
    return v


PI = F32(math.pi)
"""pi rounded to binary32 (0x40490fdb)."""
TWO_PI = F32(2.0 * math.pi)
"""2*pi rounded to binary32 (0x40c90fdb)."""
INV_TWO_PI = F32(1.0 / (2.0 * math.pi))
"""1/(2*pi) rounded to binary32 (0x3e22f983)."""
HALF = F32(0.5)
_F32_ZERO = F32(0.0)
N_LEARN = 16
"""Improvement 2: the grid offset is the running mean of the first N_LEARN hall corrections,
then a first-order filter with gain 1/N_LEARN per hall transition."""
K_ACC = F32(1.0 / 8.0)
"""Gain of the first-order filter on the acceleration estimate (improvement 3)."""
K_PITCH = F32(1.0 / 2.0)
"""Gain of the learned per-edge placement correction per revolution (improvement 4)."""
STEADY_TICKS = 2
"""Improvement 4 learns only while the revolution time changed by at most this many ticks."""
TICK_MASK = (1 << 30) - 1
"""The free-running tick counter of improvement 4 counts modulo 2**30."""

# Hall convention (firmware contract section 2): HALL_NEXT (forward successor of each state) and
# NOMINAL_HALL_ANGLE, both from eol_cal.firmware.contract.

# Status bits of EstimatorOut.status.
ST_STANDSTILL = 1 << 0
"""No valid A edge within ``standstill_ticks``: omega_hat = 0, angle held within the hall sector."""
ST_REVERSE = 1 << 1
"""The last A rising edge was in reverse rotation (B high at A's rising edge)."""
ST_HALL_FAULT = 1 << 2
"""This tick's hall reading is 0 or 7; the last valid state is kept."""
ST_HALL_SEQ = 1 << 3
"""This tick's hall state is not adjacent to the previous one; ignored for the angle."""
ST_NO_ANCHOR = 1 << 4
"""No hall transition seen yet (start-up): the angle is the hall sector's middle."""
ST_QEP_ERROR = 1 << 5
"""A and B both changed in this tick: the step is ambiguous and was not counted."""
ST_EDGE_REJECT = 1 << 6
"""This tick's A edge gave no speed: bounce, interval > 1.5x the previous one, or count mismatch."""
ST_MISSING_EDGE = 1 << 7
"""This tick's A edge closed an interval with one A pulse missing; count corrected by a pitch."""
ST_DIR_MISMATCH = 1 << 8
"""This tick's hall transition runs against the encoder's direction."""
ST_NO_SPEED = 1 << 9
"""omega_hat is not (yet) from a measured interval: start-up, after a reversal or standstill."""

#: THE mapping of the block's estimator option bits (contract ``flags`` bits 2-5) to the
#: configuration's switches; the C port reads the same bits (eol_est_config_t.flags).
OPTION_FLAGS: dict[str, int] = {
    "clamp_to_next_edge": FLAG_EST_CLAMP_TO_NEXT_EDGE,
    "learn_grid_offset": FLAG_EST_LEARN_GRID_OFFSET,
    "accel_prediction": FLAG_EST_ACCEL_PREDICTION,
    "learn_pitch_errors": FLAG_EST_LEARN_PITCH_ERRORS,
}


def options_from_flags(flags: int) -> dict[str, bool]:
    """The configuration's switches a block's ``flags`` word selects.

    The option bits count only with ``INTERP_ENABLE`` set (contract section 2); without it every
    switch is off.
    """
    honoured = honoured_options(flags)
    return {name: bool(honoured & bit) for name, bit in OPTION_FLAGS.items()}

STATUS_BITS = {
    "STANDSTILL": ST_STANDSTILL, "REVERSE": ST_REVERSE, "HALL_FAULT": ST_HALL_FAULT,
    "HALL_SEQ": ST_HALL_SEQ, "NO_ANCHOR": ST_NO_ANCHOR, "QEP_ERROR": ST_QEP_ERROR,
    "EDGE_REJECT": ST_EDGE_REJECT, "MISSING_EDGE": ST_MISSING_EDGE,
    "DIR_MISMATCH": ST_DIR_MISMATCH, "NO_SPEED": ST_NO_SPEED,
}


@dataclass(frozen=True)
class EstimatorConfig:
    """Static configuration of the estimator (hashable: JAX treats it as a static argument).

    Attributes
    ----------
    poles : int
        Number of poles P.
    N_enc : int
        Rising edges of channel A per mechanical revolution (pulses per revolution).
    tick_hz : float
        Estimator tick rate = PWM frequency (Hz); T = 1/tick_hz.
    hall_angle : tuple of 6 float
        Electrical angle (rad) at which hall state s begins in forward rotation, entry s-1.
    standstill_ticks : int
        No A edge within this many ticks -> standstill (omega_hat = 0).
    clamp_to_next_edge : bool
        Improvement 1 (block flag ``EST_CLAMP_TO_NEXT_EDGE``, bit 2): the prediction stays inside
        the current quadrature count (so it never passes the next edge's angle), and the reported
        speed is bounded by what the time since the last edge allows.
    learn_grid_offset : bool
        Improvement 2 (``EST_LEARN_GRID_OFFSET``, bit 3): the encoder-grid offset is the running mean of the hall corrections (the
        first N_LEARN, then a 1/N_LEARN filter; a full correction when the error exceeds half a
        pitch) instead of the last correction whole.
    accel_prediction : bool
        Improvement 3 (``EST_ACCEL_PREDICTION``, bit 4): the prediction between edges extrapolates the filtered acceleration.
    learn_pitch_errors : bool
        Improvement 4 (``EST_LEARN_PITCH_ERRORS``, bit 5): learns each A edge's placement error at steady speed from the time the
        same edge took for a whole revolution, and uses it for the edge angles and the speed.
    """

    poles: int
    N_enc: int
    tick_hz: float
    hall_angle: tuple[float, ...]
    standstill_ticks: int
    clamp_to_next_edge: bool = False
    learn_grid_offset: bool = False
    accel_prediction: bool = False
    learn_pitch_errors: bool = False

    @property
    def options(self) -> int:
        """The switched-on improvements as the block's estimator option bits (contract bits 2-5)."""
        return sum(bit for name, bit in OPTION_FLAGS.items() if getattr(self, name))

    @property
    def flags(self) -> int:
        """The block ``flags`` word that selects this estimator: ``INTERP_ENABLE`` and the option
        bits (what the C port's ``eol_est_config_t.flags`` takes)."""
        return FLAG_INTERP_ENABLE | self.options

    def __post_init__(self) -> None:
        if len(self.hall_angle) != 6:
            raise ValueError(f"hall_angle needs 6 entries, got {len(self.hall_angle)}")
        if self.poles < 2 or self.poles % 2:
            raise ValueError(f"poles {self.poles}: needs an even number >= 2")
        if self.N_enc < 1 or 4 * self.N_enc >= 2**15:
            raise ValueError(f"N_enc {self.N_enc}: needs 1..8191")
        if not self.tick_hz > 0:
            raise ValueError(f"tick_hz {self.tick_hz}: needs > 0")
        if not 1 <= self.standstill_ticks < 2**29:
            # 3 * N_c must fit an int32 (the long-interval test).
            raise ValueError(f"standstill_ticks {self.standstill_ticks}: needs 1..2**29-1")
        # Store as binary32 values so the config means exactly what the firmware sees.
        object.__setattr__(self, "tick_hz", float(F32(self.tick_hz)))
        object.__setattr__(self, "hall_angle", tuple(float(F32(a)) for a in self.hall_angle))

    @classmethod
    def paper(cls, poles: int = 6, N_enc: int = 64, tick_hz: float = 20000.0,
              hall_angle: Sequence[float] = NOMINAL_HALL_ANGLE,
              standstill_s: float = 1.0, **improvements: bool) -> EstimatorConfig:
        """The paper's bench (6 poles, 64 PPR, 20 kHz, nominal halls).

        Parameters
        ----------
        standstill_s : float
            Standstill bound (s); the default 1 s still measures 1 rpm with 64 PPR.
        **improvements
            ``clamp_to_next_edge``, ``learn_grid_offset``, ``accel_prediction``,
            ``learn_pitch_errors`` (bool).
        """
        return cls(poles=poles, N_enc=N_enc, tick_hz=tick_hz, hall_angle=tuple(hall_angle),
                   standstill_ticks=int(round(standstill_s * tick_hz)), **improvements)

    @classmethod
    def from_flags(cls, flags: int, **kwargs: Any) -> EstimatorConfig:
        """The paper's bench running the estimator a block's ``flags`` word selects
        (:func:`options_from_flags`); ``kwargs`` as :meth:`paper` takes them."""
        return cls.paper(**{**options_from_flags(flags), **kwargs})

    @classmethod
    def best(cls, **kwargs: Any) -> EstimatorConfig:
        """The paper's bench with every option on (the ``best`` choice of
        :mod:`eol_cal.firmware.options`: contract bits 2-5 all set)."""
        return cls.from_flags(FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR, **kwargs)

    @classmethod
    def all_improvements(cls, **kwargs: Any) -> EstimatorConfig:
        """The paper's bench with all four improvements switched on (same as :meth:`best`)."""
        return cls.best(**kwargs)

    @classmethod
    def from_block(cls, block: ParamBlock, standstill_s: float = 1.0, **improvements: bool) -> EstimatorConfig:
        """Configuration from a parameter block (anything with ``poles``, ``encoder_ppr``,
        ``tick_hz``, ``hall_angle`` and ``flags``, e.g. :class:`eol_cal.firmware.block.ParamBlock`):
        the options are those its ``flags`` select (:func:`options_from_flags`) unless
        ``improvements`` names them."""
        tick_hz = float(block.tick_hz)
        options = {**options_from_flags(int(block.flags)), **improvements}
        return cls(poles=int(block.poles), N_enc=int(block.encoder_ppr), tick_hz=tick_hz,
                   hall_angle=tuple(float(a) for a in block.hall_angle),
                   standstill_ticks=int(round(standstill_s * tick_hz)), **options)


class Consts(NamedTuple):
    """Binary32 constants derived from the config once, in the order ESTIMATOR.md gives."""

    T: np.float32            # s, tick period: 1 / tick_hz
    DELTA: np.float32        # rad, electrical angle of one encoder pitch: (P * pi) / N_enc
    QUARTER: np.float32      # rad, one quadrature count: DELTA * 0.25
    HALF_QUARTER: np.float32  # rad: QUARTER * 0.5
    HALF_DELTA: np.float32   # rad: DELTA * 0.5
    K_OMEGA: np.float32      # rad/s * ticks: DELTA * tick_hz, omega_hat = K_OMEGA / N_c
    TWO_TICK_HZ: np.float32  # 1/s: tick_hz * 2
    TICK_HZ: np.float32      # 1/s: tick_hz
    K_NDELTA: np.float32     # rad, one mechanical revolution: N_enc * DELTA
    M: int                   # quadrature counts per mechanical revolution: 4 * N_enc
    S: int                   # standstill_ticks
    H_START: np.ndarray      # f32[8] rad, where state s begins forward (0 for s = 0, 7)
    H_WIDTH: np.ndarray      # f32[8] rad, sector width wrap(H_START[next] - H_START[s])
    H_MID: np.ndarray        # f32[8] rad, wrap(H_START + H_WIDTH * 0.5)
    NEXT: np.ndarray         # i32[8] forward successor


def wrap(x: Array, xp: ArrayModule = np) -> Array:
    """Reduce an angle into [0, 2*pi) in binary32 (rad), exactly as the C port does."""
    r = x - TWO_PI * xp.floor(x * INV_TWO_PI)
    r = xp.where(r >= TWO_PI, r - TWO_PI, r)
    return xp.where(r < _F32_ZERO, r + TWO_PI, r)


def wrap_pm(x: Array, xp: ArrayModule = np) -> Array:
    """Reduce an angle into [-pi, pi) in binary32 (rad)."""
    return wrap(x + PI, xp) - PI


class HallTables(NamedTuple):
    """The hall lookups of one ``hall_angle`` table, indexed by the hall state (0 and 7: 0).

    numpy binary32 from :func:`hall_tables`; :func:`step` also takes them as (traced) JAX
    arrays, so one compiled program serves motors with different calibrated tables.

    start : f32[8] rad, where state s begins forward (``Consts.H_START``).
    width : f32[8] rad, sector width ``wrap(start[next] - start[s])`` (``Consts.H_WIDTH``).
    mid : f32[8] rad, ``wrap(start + width * 0.5)`` (``Consts.H_MID``).
    """

    start: Array
    width: Array
    mid: Array


def hall_tables(hall_angle: Sequence[float]) -> HallTables:
    """The binary32 hall lookups of a ``hall_angle`` table (ESTIMATOR.md's H_START/H_WIDTH/H_MID).

    Parameters
    ----------
    hall_angle : sequence of 6 float
        Electrical angle (rad) at which hall state s begins in forward rotation, entry s-1
        (rounded to binary32 first, as the firmware stores it).

    Returns
    -------
    HallTables
        numpy float32 arrays of 8 entries (rad).
    """
    angles = np.asarray(hall_angle, F32)
    if angles.shape != (6,):
        raise ValueError(f"hall_angle needs 6 entries, got shape {angles.shape}")
    start = np.zeros(8, F32)
    start[1:7] = angles
    nxt = np.asarray(HALL_NEXT, np.int32)
    width = np.zeros(8, F32)
    mid = np.zeros(8, F32)
    for s in range(1, 7):
        width[s] = wrap(start[nxt[s]] - start[s])
        mid[s] = wrap(start[s] + width[s] * HALF)
    return HallTables(start=start, width=width, mid=mid)


@functools.lru_cache(maxsize=64)
def consts(cfg: EstimatorConfig) -> Consts:
    """Derive the binary32 constants of ``cfg`` (numpy scalars/arrays; fixed order)."""
    tick_hz = F32(cfg.tick_hz)
    T = F32(1.0) / tick_hz
    DELTA = (F32(cfg.poles) * PI) / F32(cfg.N_enc)
    QUARTER = DELTA * F32(0.25)
    start, width, mid = hall_tables(cfg.hall_angle)
    nxt = np.asarray(HALL_NEXT, np.int32)
    return Consts(T=T, DELTA=DELTA, QUARTER=QUARTER, HALF_QUARTER=QUARTER * HALF,
                  HALF_DELTA=DELTA * HALF, K_OMEGA=DELTA * tick_hz, TWO_TICK_HZ=tick_hz * F32(2.0),
                  TICK_HZ=tick_hz, K_NDELTA=F32(cfg.N_enc) * DELTA,
                  M=4 * cfg.N_enc, S=cfg.standstill_ticks,
                  H_START=start, H_WIDTH=width, H_MID=mid, NEXT=nxt)
