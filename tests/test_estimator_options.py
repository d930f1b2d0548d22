"""Contract revision 1.1: the estimator options (block flags bits 2-5) from a written choice to the
block, its check, and the estimator the golden vectors run."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eol_cal.errors import InputError
from eol_cal.firmware import block as pb
from eol_cal.firmware import contract as C
from eol_cal.firmware import estimator as E
from eol_cal.firmware import estimator_golden as G
from eol_cal.firmware import golden
from eol_cal.firmware.options import option_names, options_label, parse_options


def test_the_option_bits_as_the_contract_states_them():
    assert (C.FLAG_EST_CLAMP_TO_NEXT_EDGE, C.FLAG_EST_LEARN_GRID_OFFSET,
            C.FLAG_EST_ACCEL_PREDICTION, C.FLAG_EST_LEARN_PITCH_ERRORS) == (0x04, 0x08, 0x10, 0x20)
    assert C.FLAGS_ESTIMATOR == 0x3C and C.FLAGS_KNOWN == 0x3F


@pytest.mark.parametrize("text, bits", [
    ("paper", 0),
    ("best", 0x3C),
    ("BEST", 0x3C),
    ("learn_grid_offset+learn_pitch_errors", 0x28),
    ("EST_CLAMP_TO_NEXT_EDGE", 0x04),
    (" accel_prediction + est_learn_pitch_errors ", 0x30),
    ("0x3c", 0x3C),
    ("0x10", 0x10),
    ("0x0", 0),
])
def test_parse_options(text, bits):
    assert parse_options(text) == bits


@pytest.mark.parametrize("text, why", [
    ("fancy", "unknown estimator option 'fancy'"),
    ("learn_grid_offset+", "unknown estimator option ''"),
    ("0x41", "bits outside the estimator options"),
    ("0x03", "bits outside the estimator options"),
    ("0xzz", "not a hex mask"),
])
def test_parse_options_refuses_with_the_file_and_key(text, why):
    with pytest.raises(InputError) as err:
        parse_options(text, "limits.toml", "variants.x.estimator")
    msg = str(err.value)
    assert why in msg and "limits.toml" in msg and "variants.x.estimator" in msg


def test_labels_name_the_options():
    assert options_label(0) == "paper" and options_label(C.FLAGS_ESTIMATOR) == "best"
    assert options_label(0x28) == "EST_LEARN_GRID_OFFSET+EST_LEARN_PITCH_ERRORS"
    assert parse_options(options_label(0x14)) == 0x14
    assert option_names(0x3E | 1) == list(C.ESTIMATOR_OPTIONS)


def _block(flags: int) -> pb.ParamBlock:
    return dataclasses.replace(golden.golden_blocks()[1][1], flags=flags)


def test_pack_carries_the_option_bits_and_unpack_reads_them_back():
    flags = C.FLAG_COMP_ENABLE | C.FLAG_INTERP_ENABLE | C.FLAGS_ESTIMATOR
    data = pb.pack(_block(flags))
    res = pb.check(data)
    assert res.valid and res.warnings == ()
    back = pb.unpack(data)
    assert back.flags == flags
    assert pb.flag_names(back.flags) == ("COMP_ENABLE|INTERP_ENABLE|EST_CLAMP_TO_NEXT_EDGE|EST_LEARN_GRID_OFFSET|"
                                         "EST_ACCEL_PREDICTION|EST_LEARN_PITCH_ERRORS")
    assert E.EstimatorConfig.from_block(back) == E.EstimatorConfig.from_block(back, **{n: True for n in E.OPTION_FLAGS})


def test_an_option_without_interp_enable_is_valid_but_warned_about():
    data = pb.pack(_block(C.FLAG_COMP_ENABLE | C.FLAG_EST_LEARN_PITCH_ERRORS))
    res = pb.check(data)
    assert res.valid
    assert len(res.warnings) == 1 and "EST_LEARN_PITCH_ERRORS without INTERP_ENABLE" in res.warnings[0]
    # and the estimator it gives is the paper's
    assert E.EstimatorConfig.from_block(pb.unpack(data)).options == 0


def test_unknown_bits_are_named_as_a_number():
    assert pb.flag_names(C.FLAG_COMP_ENABLE | 0x100) == "COMP_ENABLE|0x100"
    with pytest.raises(InputError, match="flags"):
        pb.pack(_block(0x40))


ALONE = {
    "estimator_clamp_to_next_edge.csv": C.FLAG_EST_CLAMP_TO_NEXT_EDGE,
    "estimator_learn_grid_offset.csv": C.FLAG_EST_LEARN_GRID_OFFSET,
    "estimator_accel_prediction.csv": C.FLAG_EST_ACCEL_PREDICTION,
    "estimator_learn_pitch_errors.csv": C.FLAG_EST_LEARN_PITCH_ERRORS,
}


def test_golden_vectors_cover_each_option_alone_and_all_together():
    options = {n: sc.cfg.options for n, sc in G.SCENARIOS.items()}
    for name, bit in ALONE.items():
        assert options[name] == bit and G.SCENARIOS[name].flags == C.FLAG_INTERP_ENABLE | bit
    assert options["estimator_all_240rpm.csv"] == C.FLAGS_ESTIMATOR


@pytest.mark.parametrize("name", sorted(ALONE))
def test_each_option_alone_changes_the_estimate(name):
    # the scenario shows its option acting: the same signals under the paper estimator differ
    sc = G.SCENARIOS[name]
    a, b, h = sc.signals()
    with_option = E.run(sc.cfg, a, b, h)
    paper = E.run(E.EstimatorConfig.from_flags(C.FLAG_INTERP_ENABLE, tick_hz=G.TICK_HZ), a, b, h)
    assert not np.array_equal(with_option.theta_hat.view(np.uint32), paper.theta_hat.view(np.uint32))
