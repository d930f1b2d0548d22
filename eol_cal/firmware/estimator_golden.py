"""Golden vectors of the estimator: one CSV per scenario, tick by tick, plus their configurations.

``vector_sets()`` is consumed by :mod:`eol_cal.firmware.golden` (``eol-cal golden``), which
writes the files and the manifest. Files:

* ``estimator_configs.csv``: one row per scenario file: the configuration (poles, N_enc,
  tick_hz, hall_angle_1..6, standstill_ticks, block_flags: the parameter block's ``flags`` word
  that selects the estimator options, contract bits 2-5 with ``INTERP_ENABLE``; options: the
  option bits it honours) and the constants the C port derives from it at init (T, DELTA,
  QUARTER, K_OMEGA, K_NDELTA, h_width_s, h_mid_s) as binary32 hex;
* ``estimator_<scenario>.csv``: columns tick, enc_a, enc_b, hall (inputs), theta_hat,
  omega_hat, theta_enc (binary32 hex), status (decimal). The power-on state takes the first
  row's inputs (``eol_est_init(cfg, hall, a, b)``), then every row, the first included, is one
  ``eol_est_step``.

Inputs come from the kinematic signal model (:mod:`eol_cal.firmware.kinematics`) with drawn
sensor errors (64 PPR, edge placement sigma 0.1 mechanical degree, halls within 2 electrical
degrees) and, where the scenario says so, injected glitches.
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,union-attr,index,return-value"

import math
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np

from eol_cal.firmware import estimator as est
from eol_cal.firmware.contract import (
    ESTIMATOR_OPTIONS,
    FLAG_EST_ACCEL_PREDICTION,
    FLAG_EST_CLAMP_TO_NEXT_EDGE,
    FLAG_EST_LEARN_GRID_OFFSET,
    FLAG_EST_LEARN_PITCH_ERRORS,
    FLAG_INTERP_ENABLE,
    FLAGS_ESTIMATOR,
)
from eol_cal.firmware.vectors import f32hex, scenario_rows_in_parallel
from eol_cal.firmware.kinematics import draw_sensor_errors, encoder_hall_signals, speed_profile_angle

TICK_HZ = 20000.0
POLES = 6
N_ENC = 64

#: Exact on a host build with -ffp-contract=off; targets whose FPU rounds differently compare
#: angles modulo 2*pi within ``abs`` and speeds within ``abs``; status bits must match.
TOLERANCE = {
    "theta_hat": {"abs": 1e-4, "unit": "rad", "modulo": "2*pi"},
    "omega_hat": {"abs": 1e-3, "unit": "rad/s"},
    "theta_enc": {"abs": 1e-4, "unit": "rad", "modulo": "2*pi"},
    "status": "exact",
}

SCENARIO_COLUMNS = ("tick", "enc_a", "enc_b", "hall", "theta_hat", "omega_hat", "theta_enc", "status")
CONFIG_COLUMNS = (("file", "poles", "N_enc", "tick_hz")
                  + tuple(f"hall_angle_{s}" for s in range(1, 7))
                  + ("standstill_ticks", "block_flags", "options", "T", "DELTA", "QUARTER", "K_OMEGA", "K_NDELTA")
                  + tuple(f"h_width_{s}" for s in range(1, 7))
                  + tuple(f"h_mid_{s}" for s in range(1, 7)))

Signals = tuple[np.ndarray, np.ndarray, np.ndarray]
Segments = tuple[tuple[float, float, float], ...]


@dataclass(frozen=True)
class Scenario:
    """One estimator scenario: block flags, motion, sensor errors and injected glitches.

    flags : the parameter block's ``flags`` word that selects the estimator (its option bits).
    segments : (seconds, rpm_start, rpm_end) of the mechanical speed profile.
    theta0 : mechanical angle at tick 0 (rad); seed : of the drawn sensor errors.
    inject : edits the sampled (enc_a, enc_b, hall) levels (glitches), or None.
    standstill_s : the standstill bound (s) of the configuration.
    """

    flags: int
    segments: Segments
    seed: int
    description: str
    theta0: float = 0.3
    inject: Callable[[np.ndarray, np.ndarray, np.ndarray], Signals] | None = None
    standstill_s: float = 1.0

    @property
    def cfg(self) -> est.EstimatorConfig:
        """The estimator configuration the block's flags select on the paper's bench."""
        return est.EstimatorConfig.from_flags(self.flags, tick_hz=TICK_HZ, standstill_s=self.standstill_s)

    def theta_m(self) -> np.ndarray:
        """True mechanical angle at every tick (rad)."""
        return speed_profile_angle(self.segments, TICK_HZ, self.theta0)

    def clean_signals(self) -> Signals:
        """Sampled levels before any glitch is injected."""
        errors = draw_sensor_errors(np.random.default_rng(self.seed), N_ENC)
        return encoder_hall_signals(self.theta_m(), POLES, N_ENC, errors)

    def signals(self) -> Signals:
        """Sampled levels enc_a, enc_b, hall (int32) as the estimator sees them."""
        a, b, h = self.clean_signals()
        return (a, b, h) if self.inject is None else self.inject(a.copy(), b.copy(), h.copy())


def _rising(x: np.ndarray, after: int) -> int:
    """First tick >= after where x goes 0 -> 1."""
    idx = np.flatnonzero((x[1:] == 1) & (x[:-1] == 0)) + 1
    return int(idx[idx >= after][0])


def _lose_a_pulse(a: np.ndarray, b: np.ndarray, h: np.ndarray) -> Signals:
    r = _rising(a, 1500)
    f = r + int(np.argmax(a[r:] == 0))
    a[r:f] = 0  # one A pulse lost; B still toggles
    return a, b, h


def _bounce(a: np.ndarray, b: np.ndarray, h: np.ndarray) -> Signals:
    r = _rising(a, 1200)
    a[r + 1] = 0  # A: 0 1 0 1 around its rising edge
    r2 = _rising(a, 2000)
    a[r2 + 1], a[r2 + 3] = 0, 0  # a longer bounce: 1 0 1 0 1
    rb = _rising(b, 2400)
    b[rb + 1] = 0  # B bounces too
    return a, b, h


HALL_GLITCH_TICKS = {"zero": (700, 701), "seven": (1500,), "opposite": (2200,)}


def _hall_glitch(a: np.ndarray, b: np.ndarray, h: np.ndarray) -> Signals:
    for i in HALL_GLITCH_TICKS["zero"]:
        h[i] = 0
    for i in HALL_GLITCH_TICKS["seven"]:
        h[i] = 7
    for i in HALL_GLITCH_TICKS["opposite"]:
        h[i] = 7 - h[i]  # the opposite sector for one tick: not adjacent
    return a, b, h


#: block flags: the paper's estimator (no option), and every option
_PAPER = FLAG_INTERP_ENABLE
_ALL = FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR
_SHORT = 0.05  # s, standstill bound of the stop-and-go scenarios
_STOP_GO = ((0.1, 60.0, 60.0), (0.03, 60.0, 0.0), (0.12, 0.0, 0.0), (0.05, 0.0, 60.0), (0.1, 60.0, 60.0))

#: file name -> scenario
SCENARIOS: dict[str, Scenario] = {
    "estimator_const_60rpm.csv": Scenario(_PAPER, ((0.3, 60.0, 60.0),), 1,
                                          "paper estimator, constant 60 rpm forward, 0.3 s"),
    "estimator_ramp_30_85rpm.csv": Scenario(_PAPER, ((0.05, 30.0, 30.0), (0.4, 30.0, 85.0)), 2,
                                            "paper estimator, 30 rpm then a ramp to 85 rpm in 0.4 s"),
    # Starts just short of a hall boundary (electrical 60 deg = mechanical 20 deg) so the 1.3 s
    # see the anchor and two A edges 0.94 s apart.
    "estimator_creep_1rpm.csv": Scenario(_PAPER, ((1.3, 1.0, 1.0),), 3,
                                         "paper estimator, 1 rpm creep (an edge every 0.94 s), 1.3 s",
                                         theta0=math.radians(19.5)),
    "estimator_standstill_restart.csv": Scenario(_PAPER, _STOP_GO, 4,
                                                 "paper estimator, standstill_ticks 1000: 60 rpm, stop, rest, restart",
                                                 standstill_s=_SHORT),
    "estimator_standstill_restart_all.csv": Scenario(
        _ALL, _STOP_GO, 4, "every option, standstill_ticks 1000: 60 rpm, stop, rest, restart", standstill_s=_SHORT),
    "estimator_reversal.csv": Scenario(_PAPER, ((0.1, 60.0, 60.0), (0.1, 60.0, -60.0), (0.1, -60.0, -60.0)), 5,
                                       "paper estimator, 60 rpm forward, through zero to 60 rpm reverse"),
    "estimator_reverse_60rpm.csv": Scenario(_PAPER, ((0.2, -60.0, -60.0),), 6,
                                            "paper estimator, constant 60 rpm in reverse"),
    "estimator_missing_edge.csv": Scenario(_PAPER, ((0.15, 60.0, 60.0),), 7,
                                           "paper estimator, 60 rpm, one A pulse lost", inject=_lose_a_pulse),
    "estimator_edge_bounce.csv": Scenario(_PAPER, ((0.15, 60.0, 60.0),), 8,
                                          "paper estimator, 60 rpm, A bounces twice, B once", inject=_bounce),
    "estimator_hall_glitch.csv": Scenario(_PAPER, ((0.15, 60.0, 60.0),), 9,
                                          "paper estimator, 60 rpm, hall reads 0, 7 and the opposite sector briefly",
                                          inject=_hall_glitch),
    # 240 rpm for 0.45 s: almost two revolutions, so improvement 4 learns during the second.
    "estimator_all_240rpm.csv": Scenario(_ALL, ((0.45, 240.0, 240.0),), 10,
                                          "every option, 240 rpm for 0.45 s (pitch learning starts)"),
    # each option alone, in a motion where it acts
    "estimator_clamp_to_next_edge.csv": Scenario(
        _PAPER | FLAG_EST_CLAMP_TO_NEXT_EDGE, ((0.05, 60.0, 60.0), (0.25, 60.0, 15.0)), 11,
        "EST_CLAMP_TO_NEXT_EDGE alone: 60 rpm, then slowing to 15 rpm in 0.25 s"),
    "estimator_learn_grid_offset.csv": Scenario(
        _PAPER | FLAG_EST_LEARN_GRID_OFFSET, ((0.3, 60.0, 60.0),), 12,
        "EST_LEARN_GRID_OFFSET alone: constant 60 rpm, 0.3 s"),
    "estimator_accel_prediction.csv": Scenario(
        _PAPER | FLAG_EST_ACCEL_PREDICTION, ((0.05, 30.0, 30.0), (0.25, 30.0, 90.0)), 13,
        "EST_ACCEL_PREDICTION alone: 30 rpm, then a ramp to 90 rpm in 0.25 s"),
    "estimator_learn_pitch_errors.csv": Scenario(
        _PAPER | FLAG_EST_LEARN_PITCH_ERRORS, ((0.45, 240.0, 240.0),), 14,
        "EST_LEARN_PITCH_ERRORS alone: 240 rpm for 0.45 s (pitch learning starts)"),
}

DESCRIPTIONS = {name: sc.description for name, sc in SCENARIOS.items()}
DESCRIPTIONS["estimator_configs.csv"] = (
    "configuration of each estimator_*.csv (block_flags: the parameter block's flags word, bit 1 "
    "INTERP_ENABLE with the estimator options "
    + ", ".join(f"{bit} {name}" for name, bit in ESTIMATOR_OPTIONS.items())
    + "; options: the option bits it selects) and the constants eol_est_init derives from it")


def config_row(name: str, sc: Scenario) -> list[str]:
    """The ``estimator_configs.csv`` row of scenario file ``name``."""
    cfg = sc.cfg
    c = est.consts(cfg)
    return ([name, str(cfg.poles), str(cfg.N_enc), f32hex(cfg.tick_hz)]
            + [f32hex(x) for x in cfg.hall_angle]
            + [str(cfg.standstill_ticks), str(sc.flags), str(cfg.options), f32hex(c.T), f32hex(c.DELTA), f32hex(c.QUARTER),
               f32hex(c.K_OMEGA), f32hex(c.K_NDELTA)]
            + [f32hex(c.H_WIDTH[s]) for s in range(1, 7)]
            + [f32hex(c.H_MID[s]) for s in range(1, 7)])


def scenario_rows(cfg: est.EstimatorConfig, a: np.ndarray, b: np.ndarray, h: np.ndarray) -> list[list[str]]:
    """Rows of one scenario file: inputs and the numpy reference's outputs, tick by tick."""
    out = est.run(cfg, a, b, h)
    th = out.theta_hat.view(np.uint32)
    om = out.omega_hat.view(np.uint32)
    te = out.theta_enc.view(np.uint32)
    return [[str(i), str(int(a[i])), str(int(b[i])), str(int(h[i])), f"{int(th[i]):08x}", f"{int(om[i]):08x}",
             f"{int(te[i]):08x}", str(int(out.status[i]))] for i in range(len(a))]


def vector_sets(names: list[str] | None = None) -> dict[str, tuple[tuple[str, ...], list[list[str]]]]:
    """Every estimator vector set (or those in ``names``), ``{file name: (columns, rows)}``.

    ``estimator_configs.csv`` always comes first and lists the chosen scenarios.
    """
    chosen = list(SCENARIOS) if names is None else [n for n in SCENARIOS if n in names]
    sets: dict[str, tuple[tuple[str, ...], list[list[str]]]] = {
        "estimator_configs.csv": (CONFIG_COLUMNS, [config_row(n, SCENARIOS[n]) for n in chosen])}
    rows = scenario_rows_in_parallel(_rows_of, chosen, lambda n: sum(s[0] for s in SCENARIOS[n].segments))
    for n in chosen:
        sets[n] = (SCENARIO_COLUMNS, rows[n])
    return sets


def _rows_of(name: str) -> list[list[str]]:
    """:func:`scenario_rows` of scenario file ``name`` (a worker process's task)."""
    return scenario_rows(SCENARIOS[name].cfg, *SCENARIOS[name].signals())
