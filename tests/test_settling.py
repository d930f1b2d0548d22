"""The ECU's settling after a reset (eol_cal.firmware.settling): one rule for the simulated rig's
pre-roll and the station's lead-in."""

from __future__ import annotations

import dataclasses

import pytest

from eol_cal.analysis.fit.table import uncompensated_block
from eol_cal.firmware.block import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE
from eol_cal.firmware.contract import FLAG_EST_LEARN_PITCH_ERRORS, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
from eol_cal.firmware.settling import IDENTIFY_REVS, IDENTIFY_RPM, block_settle_s, lead_in_plan, settle_s
from eol_cal.domain.motor_params import load_motor
from eol_cal.plant.ecu_model import true_block
from eol_cal.plant.presets import preset_spec


def test_without_pitch_learning_the_first_edges_are_enough():
    assert settle_s(0, 60.0) == settle_s(FLAGS_ESTIMATOR & ~FLAG_EST_LEARN_PITCH_ERRORS, 60.0) == pytest.approx(0.3)
    assert settle_s(FLAGS_ESTIMATOR, 0.0) == pytest.approx(0.3)  # standstill learns nothing


def test_pitch_learning_and_identification_take_revolutions_within_bounds():
    assert settle_s(FLAGS_ESTIMATOR, 60.0) == pytest.approx(1.5)
    assert settle_s(FLAGS_ESTIMATOR, -120.0) == pytest.approx(0.75)  # either direction
    assert settle_s(FLAGS_ESTIMATOR, 1.0) == pytest.approx(2.0)  # at most 2 s of learning
    assert settle_s(FLAGS_ESTIMATOR, 60.0, identifies=True) == pytest.approx(IDENTIFY_REVS)
    assert settle_s(FLAGS_ESTIMATOR, 3.0, identifies=True) == pytest.approx(10.0)
    assert settle_s(FLAGS_ESTIMATOR, 6000.0, identifies=True) == pytest.approx(0.3)


def test_the_block_the_ecu_booted_says_what_it_needs():
    motor = load_motor("paper")
    assert block_settle_s(None, 60.0) == pytest.approx(0.3)
    assert block_settle_s(uncompensated_block("M-1", motor, options=FLAGS_ESTIMATOR), 60.0) == pytest.approx(1.5)
    assert block_settle_s(uncompensated_block("M-1", motor, options=0), 60.0) == pytest.approx(0.3)
    spec = preset_spec("paper", serial="M-1")
    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR
    identifying = true_block(spec, flags=flags | FLAG_MECH_COMP_ENABLE, mech=True)
    assert block_settle_s(identifying, 60.0) == pytest.approx(4.0)
    # the mechanical part present but not enabled: pitch learning alone
    assert block_settle_s(true_block(spec, flags=flags, mech=True), 60.0) == pytest.approx(1.5)
    assert block_settle_s(dataclasses.replace(identifying, mech=None), 60.0) == pytest.approx(1.5)


def test_an_identifying_ecu_is_identified_at_its_own_speed_first():
    motor = load_motor("paper")
    spec = preset_spec("paper", serial="M-1")
    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR
    identifying = true_block(spec, flags=flags | FLAG_MECH_COMP_ENABLE, mech=True)
    # four revolutions at 200 rpm, then the first edges' settling at the capture's speed
    assert lead_in_plan(identifying, 60.0) == pytest.approx((IDENTIFY_RPM, 1.2, 0.3))
    assert lead_in_plan(identifying, -60.0) == pytest.approx((-IDENTIFY_RPM, 1.2, 0.3))  # signed as the capture
    # a capture as fast or faster identifies at its own speed
    assert lead_in_plan(identifying, 300.0) == (None, 0.0, pytest.approx(0.8))
    assert lead_in_plan(identifying, IDENTIFY_RPM) == (None, 0.0, pytest.approx(1.2))
    # pitch learning alone, the paper's estimator, no block, standstill: at the capture's speed
    learning = uncompensated_block("M-1", motor, options=FLAGS_ESTIMATOR)
    assert lead_in_plan(learning, 60.0) == (None, 0.0, pytest.approx(1.5))
    assert lead_in_plan(uncompensated_block("M-1", motor, options=0), 60.0) == (None, 0.0, pytest.approx(0.3))
    assert lead_in_plan(None, 60.0) == (None, 0.0, pytest.approx(0.3))
    assert lead_in_plan(identifying, 0.0) == (None, 0.0, pytest.approx(0.3))
