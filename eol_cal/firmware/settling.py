"""How long the shaft must turn after an ECU reset before the firmware runs what its block says.

After a reset the estimator has seen no encoder edge and no hall transition; with
``EST_LEARN_PITCH_ERRORS`` it learns the encoder's pitch errors over the first revolutions, and a
block with mechanical tables (layout 2) compensates the rotor's mechanical orders only once the
identifier has found the rotor's mechanical frame (firmware_params/MECH.md: three revolutions of
samples). A capture that starts earlier records the firmware still learning. The simulated rig
gives its plant this time before each recording (:func:`eol_cal.plant.simulate.simulate`), and a
station turns the shaft for it before the first capture after each reset (the *lead-in*,
:func:`eol_cal.dyno.profile_run.run_profile`): one rule for both.
"""

from __future__ import annotations

import math

from eol_cal.firmware.block import ParamBlock
from eol_cal.firmware.contract import FLAG_EST_LEARN_PITCH_ERRORS
from eol_cal.firmware.mech import block_mech_tables
from eol_cal.firmware.options import honoured_options

#: mechanical revolutions an identifying ECU needs: one revolution before the estimator measures
#: pitches, one of samples and one more to confirm (firmware_params/MECH.md), and one of margin
IDENTIFY_REVS = 4.0
#: mechanical revolutions of pitch-error learning before its estimate is used
LEARN_REVS = 1.5
#: the estimator's first edges and hall transition, s (every estimator)
FIRST_EDGES_S = 0.3
#: speed (rpm) an identifying ECU's lead-in turns at when the capture's is slower: four
#: revolutions in 1.2 s instead of 4 s at 60 rpm. bench/bench_lead_in.py (8 production motors,
#: the firmware twin): the compensated p-p at 60 rpm after it 0.88 % median (worst 1.17) against
#: 0.95 % (1.23) after the four revolutions at 60 rpm, the angle error 0.175 deg rms against
#: 0.157; at 300 rpm and above the angle error grows further (0.21, 0.39 deg at 600).
IDENTIFY_RPM = 200.0


def settle_s(options: int, speed_rpm: float, identifies: bool = False) -> float:
    """Time (s) the shaft must turn at ``speed_rpm`` (rpm) after a reset before the firmware's angle
    is settled.

    Parameters
    ----------
    options : int
        The estimator option bits (contract flags bits 2-5) the ECU runs.
    speed_rpm : float
        The shaft's speed (rpm).
    identifies : bool
        The ECU identifies the rotor's mechanical frame (a block with mechanical tables and pitch
        learning).

    Returns
    -------
    float
        :data:`FIRST_EDGES_S` without pitch learning (or at standstill); with it
        :data:`LEARN_REVS` revolutions within 0.3-2 s, or :data:`IDENTIFY_REVS` revolutions (at
        most 10 s) for an identifying ECU, so its compensation runs from the first recorded sample.
    """
    if not options & FLAG_EST_LEARN_PITCH_ERRORS or speed_rpm == 0.0:
        return FIRST_EDGES_S
    if identifies:
        return min(10.0, max(FIRST_EDGES_S, IDENTIFY_REVS * 60.0 / abs(speed_rpm)))
    return min(2.0, max(FIRST_EDGES_S, LEARN_REVS * 60.0 / abs(speed_rpm)))


def lead_in_plan(block: ParamBlock | None, speed_rpm: float) -> tuple[float | None, float, float]:
    """Where and how long the shaft turns after a reset before a capture at ``speed_rpm`` (rpm)
    counts, for an ECU that booted ``block``: ``(point_rpm, point_s, at_speed_s)``.

    An identifying ECU (:func:`block_settle_s`) whose capture turns slower than
    :data:`IDENTIFY_RPM` is identified there first: ``point_rpm`` that speed (signed as the
    capture's), ``point_s`` its four revolutions, then the ramp to the capture's speed and
    ``at_speed_s`` = :data:`FIRST_EDGES_S` of settling there. Every other ECU settles at the
    capture's speed: ``(None, 0.0, block_settle_s(block, speed_rpm))``. Pitch learning alone is
    not moved: at 200-300 rpm its angle error grows by 40-55 % (bench/bench_lead_in.py
    ``--case calibration``) for 0.6 s saved.
    """
    at_speed_s = block_settle_s(block, speed_rpm)
    if block is None or speed_rpm == 0.0 or abs(speed_rpm) >= IDENTIFY_RPM or not identifies(block):
        return None, 0.0, at_speed_s
    return math.copysign(IDENTIFY_RPM, speed_rpm), block_settle_s(block, IDENTIFY_RPM), FIRST_EDGES_S


def identifies(block: ParamBlock) -> bool:
    """Whether an ECU that booted ``block`` identifies the rotor's mechanical frame (mechanical
    tables enabled and pitch learning)."""
    return bool(block_mech_tables(block).enabled) and bool(honoured_options(block.flags) & FLAG_EST_LEARN_PITCH_ERRORS)


def block_settle_s(block: ParamBlock | None, speed_rpm: float) -> float:
    """:func:`settle_s` for an ECU that booted ``block`` (None: no valid bank, the paper's estimator)."""
    if block is None:
        return settle_s(0, speed_rpm)
    return settle_s(honoured_options(block.flags), speed_rpm, identifies(block))
