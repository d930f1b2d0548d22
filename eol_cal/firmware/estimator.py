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
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Sequence

import numpy as np

from eol_cal.arrays import Array, ArrayModule

if TYPE_CHECKING:
    from eol_cal.firmware.block import ParamBlock

F32 = np.float32
I32 = np.int32

PI = F32(math.pi)
"""pi rounded to binary32 (0x40490fdb)."""
TWO_PI = F32(2.0 * math.pi)
"""2*pi rounded to binary32 (0x40c90fdb)."""
INV_TWO_PI = F32(1.0 / (2.0 * math.pi))
"""1/(2*pi) rounded to binary32 (0x3e22f983)."""
HALF = F32(0.5)
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

# Hall convention (firmware contract section 2): U = bit0, V = bit1, W = bit2; forward rotation
# steps 5 -> 1 -> 3 -> 2 -> 6 -> 4 -> 5. Indexed by the state; 0 and 7 are faults.
HALL_NEXT = (0, 3, 6, 2, 5, 1, 4, 0)
"""Forward successor of hall state s (``HALL_NEXT[s]``); 0 for the fault states 0 and 7."""
NOMINAL_HALL_ANGLE = tuple(math.radians(d) for d in (60.0, 180.0, 120.0, 300.0, 0.0, 240.0))
"""Nominal ``hall_angle`` (rad, electrical), contract order: entry s-1 is where state s begins."""

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

FLAG_CLAMP_TO_NEXT_EDGE = 0x1
FLAG_LEARN_GRID_OFFSET = 0x2
FLAG_ACCEL_PREDICTION = 0x4
FLAG_LEARN_PITCH_ERRORS = 0x8

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
        Improvement 1: the prediction stays inside the current quadrature count (so it never
        passes the next edge's angle), and the reported speed is bounded by what the time since
        the last edge allows.
    learn_grid_offset : bool
        Improvement 2: the encoder-grid offset is the running mean of the hall corrections (the
        first N_LEARN, then a 1/N_LEARN filter; a full correction when the error exceeds half a
        pitch) instead of the last correction whole.
    accel_prediction : bool
        Improvement 3: the prediction between edges extrapolates the filtered acceleration.
    learn_pitch_errors : bool
        Improvement 4: learns each A edge's placement error at steady speed from the time the
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
    def flags(self) -> int:
        """The improvement switches as the C port's ``flags`` bits (EOL_EST_* in eol_est.h)."""
        return (FLAG_CLAMP_TO_NEXT_EDGE * self.clamp_to_next_edge
                | FLAG_LEARN_GRID_OFFSET * self.learn_grid_offset
                | FLAG_ACCEL_PREDICTION * self.accel_prediction
                | FLAG_LEARN_PITCH_ERRORS * self.learn_pitch_errors)

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
              standstill_s: float = 1.0, **improvements: bool) -> "EstimatorConfig":
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
    def best(cls, **kwargs: Any) -> "EstimatorConfig":
        """The paper's bench with the best combination of bench/bench_estimator.py: improvements
        1, 2 and 4 (3, the acceleration-aware prediction, measured no gain there)."""
        kwargs.setdefault("clamp_to_next_edge", True)
        kwargs.setdefault("learn_grid_offset", True)
        kwargs.setdefault("learn_pitch_errors", True)
        return cls.paper(**kwargs)

    @classmethod
    def all_improvements(cls, **kwargs: Any) -> "EstimatorConfig":
        """The paper's bench with all four improvements switched on."""
        kwargs.setdefault("accel_prediction", True)
        return cls.best(**kwargs)

    @classmethod
    def from_block(cls, block: ParamBlock, standstill_s: float = 1.0, **improvements: bool) -> "EstimatorConfig":
        """Configuration from a parameter block (anything with ``poles``, ``encoder_ppr``,
        ``tick_hz``, ``hall_angle``, e.g. :class:`eol_cal.firmware.block.ParamBlock`)."""
        tick_hz = float(block.tick_hz)
        return cls(poles=int(block.poles), N_enc=int(block.encoder_ppr), tick_hz=tick_hz,
                   hall_angle=tuple(float(a) for a in block.hall_angle),
                   standstill_ticks=int(round(standstill_s * tick_hz)), **improvements)


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
    return xp.where(r < F32(0.0), r + TWO_PI, r)


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
    nxt = np.asarray(HALL_NEXT, I32)
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
    nxt = np.asarray(HALL_NEXT, I32)
    return Consts(T=T, DELTA=DELTA, QUARTER=QUARTER, HALF_QUARTER=QUARTER * HALF,
                  HALF_DELTA=DELTA * HALF, K_OMEGA=DELTA * tick_hz, TWO_TICK_HZ=tick_hz * F32(2.0),
                  TICK_HZ=tick_hz, K_NDELTA=F32(cfg.N_enc) * DELTA,
                  M=4 * cfg.N_enc, S=cfg.standstill_ticks,
                  H_START=start, H_WIDTH=width, H_MID=mid, NEXT=nxt)


class EstimatorState(NamedTuple):
    """Everything the estimator keeps between ticks (int32 / float32, scalars or batched).

    Batched states: any leading shape with ``xp=numpy`` (bit-exact per element) as long as
    ``learn_pitch_errors`` is off; with it on, batch through ``jax.vmap`` (its per-motor tables
    are indexed per motor).

    phase : quadrature phase of (A, B): (0,0)=0, (1,0)=1, (1,1)=2, (0,1)=3.
    q : quadrature count, 0 .. 4*N_enc-1.
    n : ticks since the last A edge event, saturating at standstill_ticks + 1.
    k_last : quadrature boundary index of the last A edge event (its angle is G + k*QUARTER).
    dir_last : direction of the last A edge event (+1, -1; 0 before the first).
    nc_prev : N_c of the last measured interval (ticks; 0 = none).
    against : a quadrature step against dir_last happened since the last edge event (0/1).
    omega : omega_hat from the last measured interval (rad/s electrical, signed).
    alpha : filtered acceleration estimate (rad/s^2 electrical), improvement 3 only.
    adv : angle advanced since the last edge event (rad electrical).
    G : encoder-grid offset: electrical angle of quadrature boundary 0 (rad, [0, 2*pi)).
    hall_last : last valid hall reading (1..6; 0 = none yet).
    sector : last hall state reached through an adjacent transition or at start-up (0 = none).
    anchored : a hall transition has set G (0/1).
    n_anchor : hall corrections since the anchor or the last count slip, saturating at N_LEARN.
    tick : free-running tick counter modulo 2**30 (improvement 4).
    run : measured intervals in a row in one direction, saturating at N_enc (improvement 4).
    R_prev : revolution time at the previous measured edge (ticks; improvement 4).
    c_tab : f32[2*N_enc] learned placement error of each A edge (rad electrical, index k >> 1;
        improvement 4, else empty).
    ts : i32[2*N_enc] tick of each A edge's last event (improvement 4, else empty).
    """

    phase: Array
    q: Array
    n: Array
    k_last: Array
    dir_last: Array
    nc_prev: Array
    against: Array
    omega: Array
    alpha: Array
    adv: Array
    G: Array
    hall_last: Array
    sector: Array
    anchored: Array
    n_anchor: Array
    tick: Array
    run: Array
    R_prev: Array
    c_tab: Array
    ts: Array


class EstimatorOut(NamedTuple):
    """Per-tick outputs.

    theta_hat : estimated electrical angle (rad, [0, 2*pi)).
    omega_hat : estimated electrical speed (rad/s, signed; + = forward).
    theta_enc : raw edge-quantised electrical angle, the angle of the last A edge event
        (rad, [0, 2*pi)); the paper's 'raw' encoder angle.
    status : ST_* bits (int32).
    """

    theta_hat: Array
    omega_hat: Array
    theta_enc: Array
    status: Array


def _tab(table: np.ndarray, idx: Array, xp: ArrayModule) -> Array:
    """``table[idx]`` for a constant or traced table and a (possibly traced) int32 index."""
    return table[idx] if xp is np or xp is _SCALAR_NP else xp.asarray(table)[idx]


class _ScalarNumpy:
    """numpy for one motor's scalars, minus the 0-d array round trips of ``np.where`` & co.

    Selections and min/max pick one of their (already binary32) operands, so the arithmetic and
    its results are those of ``xp=numpy`` exactly; :func:`run` uses it for speed only.
    """

    int32 = np.int32
    float32 = np.float32
    floor = staticmethod(np.floor)
    asarray = staticmethod(np.asarray)
    zeros = staticmethod(np.zeros)
    zeros_like = staticmethod(np.zeros_like)

    @staticmethod
    def where(c: Array, x: Array, y: Array) -> Array:
        return x if c else y

    @staticmethod
    def minimum(x: Array, y: Array) -> Array:
        return x if x < y else y

    @staticmethod
    def maximum(x: Array, y: Array) -> Array:
        return x if x > y else y

    @staticmethod
    def abs(x: Array) -> Array:
        return -x if x < 0 else x


_SCALAR_NP = _ScalarNumpy()


def _set(arr: Array, idx: Array, val: Array, xp: ArrayModule) -> Array:
    """``arr`` with ``arr[idx] = val`` (a copy under numpy, a functional update under JAX)."""
    if not hasattr(arr, "at"):
        out = arr.copy()
        out[idx] = val
        return out
    return arr.at[idx].set(val)


def _dq(q: Array, k_last: Array, M: int, xp: ArrayModule) -> Array:
    """Signed quadrature counts from boundary ``k_last`` to count ``q``, in [-M/2, M/2)."""
    return (q - k_last + I32(M + M // 2)) % I32(M) - I32(M // 2)


def quadrature_phase(enc_a: Array, enc_b: Array) -> Array:
    """Position of the encoder levels (0/1 integers) in one quadrature cycle, forward: 00 -> 10 -> 11 -> 01 is 0, 1, 2, 3."""
    return I32(2) * enc_b + (enc_a ^ enc_b)


def init_state(cfg: EstimatorConfig, hall0: Array, enc_a0: Array = 0, enc_b0: Array = 0,
               xp: ArrayModule = np) -> EstimatorState:
    """Power-on state from the first sample of the halls (and the encoder levels).

    Parameters
    ----------
    cfg : EstimatorConfig
    hall0 : int or int array
        Hall state at power-on (0..7; 0 and 7 leave the sector unknown until a valid reading).
    enc_a0, enc_b0 : int or int array
        Encoder levels at power-on (0/1), so the first tick counts no spurious step.
    xp : numpy or jax.numpy
    """
    h = xp.asarray(hall0).astype(xp.int32)
    a = xp.asarray(enc_a0).astype(xp.int32) + xp.zeros_like(h)
    b = xp.asarray(enc_b0).astype(xp.int32) + xp.zeros_like(h)
    valid = (h >= 1) & (h <= 6)
    L = 2 * cfg.N_enc if cfg.learn_pitch_errors else 0
    h = xp.where(valid, h, xp.zeros_like(h))
    zi = xp.zeros_like(h)
    zf = zi.astype(xp.float32)
    ph = quadrature_phase(a, b)
    return EstimatorState(phase=ph, q=ph, n=zi, k_last=zi, dir_last=zi, nc_prev=zi, against=zi,
                          omega=zf, alpha=zf, adv=zf, G=zf, hall_last=h, sector=h, anchored=zi,
                          n_anchor=zi, tick=zi, run=zi, R_prev=zi,
                          c_tab=xp.zeros(h.shape + (L,), xp.float32),
                          ts=xp.zeros(h.shape + (L,), xp.int32))


def step(cfg: EstimatorConfig, state: EstimatorState, enc_a: Array, enc_b: Array, hall: Array,
         xp: ArrayModule = np, tables: HallTables | None = None) -> tuple[EstimatorState, EstimatorOut]:
    """One PWM tick of the estimator (ESTIMATOR.md, "Per tick").

    Parameters
    ----------
    cfg : EstimatorConfig
        Static; its booleans select code paths at trace time.
    state : EstimatorState
    enc_a, enc_b : int (0/1) or int arrays
        Encoder channel levels sampled this tick.
    hall : int (0..7) or int array
        Hall bits U | V<<1 | W<<2 sampled this tick.
    xp : numpy or jax.numpy
    tables : HallTables, optional
        One motor's hall lookups (f32[8] each, rad; may be traced), used instead of those of
        ``cfg.hall_angle``: a calibrated table is data, not a reason to compile again.

    Returns
    -------
    (new state, EstimatorOut)
    """
    c = consts(cfg)
    ht = HallTables(c.H_START, c.H_WIDTH, c.H_MID) if tables is None else tables
    i32, f32 = xp.int32, xp.float32
    M, S = c.M, c.S
    one = I32(1)
    s = state

    # 1. Quadrature decoding (x4). A rising edge: phase 0->1 forward, 3->2 reverse.
    a = i32(enc_a)
    b = i32(enc_b)
    ph = quadrature_phase(a, b)
    d = (ph - s.phase + I32(4)) % I32(4)
    stp = xp.where(d == 1, one, xp.where(d == 3, -one, I32(0)))
    qep_err = d == 2
    q = (s.q + stp + I32(M)) % I32(M)
    a_rise = ((d == 1) & (ph == 1)) | ((d == 3) & (ph == 2))
    edir = xp.where(ph == 1, one, -one)
    k = xp.where(edir > 0, q, (q + one) % I32(M))
    against = s.against | i32(((stp != 0) & (stp == -s.dir_last)))
    n1 = xp.minimum(s.n + one, I32(S + 1))

    # 2. A edge event: bounce (same boundary again), measured interval, or re-reference only.
    bounce = a_rise & (k == s.k_last) & (edir == s.dir_last)
    ev = a_rise & ~bounce
    same_dir = edir == s.dir_last
    pitch_ok = k == (s.k_last + I32(4) * edir + I32(M)) % I32(M)
    interval = ev & same_dir & pitch_ok & (n1 <= I32(S))
    long_iv = interval & (s.nc_prev > 0) & (I32(2) * n1 > I32(3) * s.nc_prev)
    missing = long_iv & (against != 0)
    reject = long_iv & (against == 0)
    measured = interval & ~long_iv
    nc_eff = xp.where(missing, n1 // I32(2), n1)
    omega_new = f32(edir) * (c.K_OMEGA / f32(nc_eff))
    # A lost A pulse leaves the count one pitch behind: put it back.
    fix = xp.where(missing, I32(4) * edir, I32(0))
    q = (q + fix + I32(M)) % I32(M)
    k = (k + fix + I32(M)) % I32(M)
    speed_upd = measured | missing
    if cfg.learn_pitch_errors:
        tick = (s.tick + one) & I32(TICK_MASK)
        i_new = k >> one
        c_old = s.c_tab[s.k_last >> one]
        c_new = s.c_tab[i_new]
        R = xp.maximum((tick - s.ts[i_new]) & I32(TICK_MASK), one)
        learn = measured & (s.run >= I32(cfg.N_enc)) & (xp.abs(R - s.R_prev) <= I32(STEADY_TICKS))
        # At steady speed the same edge's revolution time gives the true speed, so this pitch's
        # real size is N_enc*DELTA * N_c / R; its edge sits that far from the previous one.
        pitch = f32(n1) * (c.K_NDELTA / f32(R))
        target = c_old + f32(edir) * (pitch - c.DELTA)
        c_new = xp.where(learn, c_new + K_PITCH * (target - c_new), c_new)
        c_tab = _set(s.c_tab, i_new, c_new, xp)
        ts = _set(s.ts, i_new, xp.where(ev, tick, s.ts[i_new]), xp)
        R_prev = xp.where(measured, R, s.R_prev)
        run = xp.where(measured, xp.minimum(s.run + one, I32(cfg.N_enc)),
                       xp.where(ev, I32(0), s.run))
        omega_new = xp.where(measured, f32(edir)
                             * (((c.DELTA + f32(edir) * (c_new - c_old)) * c.TICK_HZ)
                                / f32(n1)), omega_new)
    else:
        tick, run, R_prev, c_tab, ts = s.tick, s.run, s.R_prev, s.c_tab, s.ts
    omega = xp.where(speed_upd, omega_new,
                     xp.where(ev & ~same_dir, F32(0.0), s.omega))
    nc_prev = xp.where(speed_upd, nc_eff,
                       xp.where(reject, n1, xp.where(ev, I32(0), s.nc_prev)))
    if cfg.accel_prediction:
        consecutive = measured & (s.nc_prev > 0)
        alpha_raw = (omega_new - s.omega) * (c.TWO_TICK_HZ / f32((n1 + s.nc_prev)))
        alpha = xp.where(consecutive, s.alpha + K_ACC * (alpha_raw - s.alpha),
                         xp.where(ev & ~(missing | reject), F32(0.0), s.alpha))
    else:
        alpha = s.alpha
    n = xp.where(ev, I32(0), n1)
    k_last = xp.where(ev, k, s.k_last)
    dir_last = xp.where(ev, edir, s.dir_last)
    against = xp.where(ev, I32(0), against)

    # 3. Standstill and the prediction between edges (eq. 16).
    still = n > I32(S)
    nc_prev = xp.where(still, I32(0), nc_prev)
    # omega_hat is valid exactly while nc_prev > 0 (a measured interval since the last break).
    speed_ok = nc_prev > 0
    omega = xp.where(speed_ok, omega, F32(0.0))
    run = xp.where(still, I32(0), run)
    alpha = xp.where(still, F32(0.0), alpha)
    if cfg.accel_prediction:
        # omega from an interval is the mean over it: the speed at its middle, N_c/2 ticks back.
        tau = (f32(nc_prev) * HALF + f32(n)) * c.T
        omega_pred = omega + alpha * tau
    else:
        omega_pred = omega
    adv = xp.where(ev, F32(0.0), s.adv + omega_pred * c.T)
    if cfg.clamp_to_next_edge:
        # The rotor is inside the current quadrature count: the prediction never passes its far
        # boundary (so never the next edge) and catches up with its near one. Not after a step
        # against the direction since the last edge: then the count may be a lost pulse behind.
        lo = f32(_dq(q, k_last, M, xp)) * c.QUARTER
        adv = xp.where(against == 0, xp.minimum(xp.maximum(adv, lo), lo + c.QUARTER), adv)

    # 4. Halls: validity, sequence, absolute re-anchor at transitions.
    h = i32(hall)
    hv = (h >= 1) & (h <= 6)
    hl = s.hall_last
    trans = hv & (h != hl) & (hl != 0)
    fwd = trans & (h == _tab(c.NEXT, hl, xp))
    rev = trans & (hl == _tab(c.NEXT, xp.where(hv, h, I32(0)), xp))
    adj = fwd | rev
    jump = trans & ~adj
    first = hv & (hl == 0)
    hb = xp.where(fwd, _tab(ht.start, xp.where(hv, h, I32(0)), xp), _tab(ht.start, hl, xp))
    # First anchor without an edge yet: the grid reference is the current count's middle.
    no_edge = dir_last == 0
    k_last = xp.where(adj & (s.anchored == 0) & no_edge, q, k_last)
    c_last = c_tab[k_last >> one] if cfg.learn_pitch_errors else F32(0.0)
    rel = f32(k_last) * c.QUARTER + c_last
    # Without a valid speed the best position is the middle of the current quadrature count.
    cell = f32(_dq(q, k_last, M, xp)) * c.QUARTER + c.HALF_QUARTER
    adv_eff = xp.where(speed_ok, adv, cell)
    theta_pred = wrap(wrap(s.G + rel, xp) + adv_eff, xp)
    e = wrap_pm(hb - theta_pred, xp)
    big = xp.abs(e) > c.HALF_DELTA
    if cfg.learn_grid_offset:
        # Running mean of the corrections over the first N_LEARN transitions, then a first-order
        # filter; an error over half a pitch is a count slip and is taken whole.
        gain = F32(1.0) / f32((xp.minimum(s.n_anchor + one, I32(N_LEARN))))
        g = xp.where(big, e, e * gain)
    else:
        g = e
    G = xp.where(adj & (s.anchored != 0), wrap(s.G + g, xp),
                 xp.where(adj, wrap(hb - (rel + adv_eff), xp), s.G))
    anchored = xp.where(adj, one, s.anchored)
    n_anchor = xp.where(adj & ((s.anchored == 0) | big), one,
                        xp.where(adj, xp.minimum(s.n_anchor + one, I32(N_LEARN)), s.n_anchor))
    hdir = xp.where(fwd, one, -one)
    dir_mismatch = adj & (dir_last != 0) & (hdir != dir_last)
    hall_last = xp.where(hv, h, hl)
    sector = xp.where(adj | first, h, s.sector)

    # 5. Outputs.
    theta_enc = wrap(G + rel, xp)
    theta = wrap(theta_enc + adv_eff, xp)
    start = _tab(ht.start, sector, xp)
    width = _tab(ht.width, sector, xp)
    dd = wrap(theta - start, xp)
    outside = dd > width
    end = wrap(start + width, xp)
    clamped = xp.where(outside, xp.where(dd - width < TWO_PI - dd, end, start), theta)
    theta = xp.where(still, clamped, theta)
    unanchored = anchored == 0
    mid = _tab(ht.mid, sector, xp)
    theta = xp.where(unanchored, mid, theta)
    theta_enc = xp.where(unanchored, mid, theta_enc)
    omega_out = omega_pred
    if cfg.clamp_to_next_edge:
        # No edge for n ticks: |speed| cannot exceed a pitch per n ticks.
        bound = c.K_OMEGA / f32(xp.maximum(n, one))
        omega_out = xp.where(n > 0, xp.minimum(xp.maximum(omega_out, -bound), bound), omega_out)
    no_speed = (nc_prev == 0) & ~speed_upd

    status = (i32(still) * I32(ST_STANDSTILL)
              | i32((dir_last < 0)) * I32(ST_REVERSE)
              | i32((~hv)) * I32(ST_HALL_FAULT)
              | i32(jump) * I32(ST_HALL_SEQ)
              | i32(unanchored) * I32(ST_NO_ANCHOR)
              | i32(qep_err) * I32(ST_QEP_ERROR)
              | i32((bounce | reject | (ev & ~speed_upd))) * I32(ST_EDGE_REJECT)
              | i32(missing) * I32(ST_MISSING_EDGE)
              | i32(dir_mismatch) * I32(ST_DIR_MISMATCH)
              | i32(no_speed) * I32(ST_NO_SPEED))

    new = EstimatorState(phase=ph, q=q, n=n, k_last=k_last, dir_last=dir_last, nc_prev=nc_prev,
                         against=against, omega=omega, alpha=alpha, adv=adv, G=G,
                         hall_last=hall_last, sector=sector, anchored=anchored,
                         n_anchor=n_anchor, tick=tick, run=run, R_prev=R_prev, c_tab=c_tab, ts=ts)
    return new, EstimatorOut(theta_hat=theta, omega_hat=omega_out, theta_enc=theta_enc,
                             status=status)


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
    a = np.asarray(enc_a, dtype=I32)
    b = np.asarray(enc_b, dtype=I32)
    h = np.asarray(hall, dtype=I32)
    n = len(a)
    th = np.empty(n, F32)
    om = np.empty(n, F32)
    te = np.empty(n, F32)
    st = np.empty(n, I32)
    if n == 0:
        return EstimatorOut(th, om, te, st)
    state = init_state(cfg, h[0], a[0], b[0])
    state = EstimatorState(*(x[()] if x.ndim == 0 else x for x in state))
    for i in range(n):
        state, out = step(cfg, state, a[i], b[i], h[i], xp=_SCALAR_NP)
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


#: ticks per call of :func:`run_jax_chunked`'s compiled scan
JAX_CHUNK = 4096


@functools.lru_cache(maxsize=16)
def _scan_chunk(cfg: EstimatorConfig):
    """The jitted scan over one chunk of ticks, state carried in and out (one per config; the
    hall tables are an argument, so call it with :func:`_program_config`)."""
    import jax
    import jax.numpy as jnp

    def chunk(s, abh, tables):
        def body(s, x):
            return step(cfg, s, x[0], x[1], x[2], xp=jnp, tables=tables)

        return jax.lax.scan(body, s, abh)

    return jax.jit(chunk)


def run_jax_chunked(cfg: EstimatorConfig, enc_a: Array, enc_b: Array, hall: Array, chunk: int = JAX_CHUNK,
                    hall_angle: Sequence[float] | None = None) -> EstimatorOut:
    """:func:`run_jax` for one capture (1-D inputs) with one compiled program for every length.

    The ticks run in chunks of ``chunk`` under ``jax.lax.scan``, the state carried from chunk to
    chunk and the last chunk padded with the last sample (its outputs and the final state are
    discarded): :func:`run_jax` traces and compiles anew for every capture length.

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
    import jax.numpy as jnp

    abh = np.stack([np.asarray(enc_a), np.asarray(enc_b), np.asarray(hall)], axis=-1).astype(np.int32)
    n = len(abh)
    abh = np.concatenate([abh, np.repeat(abh[-1:], (-n) % chunk, axis=0)])
    tables = _jax_tables(cfg, hall_angle)
    pcfg = _program_config(cfg)
    scan = _scan_chunk(pcfg)
    state = init_state(pcfg, jnp.int32(abh[0, 2]), jnp.int32(abh[0, 0]), jnp.int32(abh[0, 1]), xp=jnp)
    outs = []
    for k in range(0, len(abh), chunk):
        state, out = scan(state, abh[k:k + chunk], tables)
        outs.append(out)
    return EstimatorOut(*(np.concatenate([np.asarray(o[i]) for o in outs])[:n] for i in range(len(EstimatorOut._fields))))
