"""How long the shaft must turn after an ECU reset before the firmware runs what its block says.

After a reset the estimator has seen no encoder edge and no hall transition; with
``EST_LEARN_PITCH_ERRORS`` it learns the encoder's pitch errors over the first revolutions, and a
block with mechanical tables (layout 2) compensates the rotor's mechanical orders only once the
identifier has found the rotor's mechanical frame (firmware_params/MECH.md: three revolutions of
samples). A capture that starts earlier records the firmware still learning. The simulated rig
gives its plant this time before each recording (:func:`eol_cal.plant.simulate.simulate`), and a
station turns the shaft for it before the first capture after each reset (the *lead-in*,
:func:`eol_cal.dyno.client.run_profile`): one rule for both.
"""

from __future__ import annotations

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


def block_settle_s(block: ParamBlock | None, speed_rpm: float) -> float:
    """:func:`settle_s` for an ECU that booted ``block`` (None: no valid bank, the paper's estimator)."""
    if block is None:
        return settle_s(0, speed_rpm)
    options = honoured_options(block.flags)
    identifies = bool(block_mech_tables(block).enabled) and bool(options & FLAG_EST_LEARN_PITCH_ERRORS)
    return settle_s(options, speed_rpm, identifies)
