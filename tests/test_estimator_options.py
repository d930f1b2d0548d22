"""Contract revision 1.1: the estimator options (block flags bits 2-5) from a written choice to the
block, its check, and the estimator the golden vectors run."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware import contract as C
from eol_cal.firmware import estimator as est
from eol_cal.firmware import estimator_golden as G
from eol_cal.firmware import golden
from eol_cal.firmware.options import option_names, options_label, parse_options


def test_the_option_bits_as_the_contract_states_them():
    assert (C.FLAG_EST_CLAMP_TO_NEXT_EDGE, C.FLAG_EST_LEARN_GRID_OFFSET,
            C.FLAG_EST_ACCEL_PREDICTION, C.FLAG_EST_LEARN_PITCH_ERRORS) == (0x04, 0x08, 0x10, 0x20)
    assert C.FLAGS_ESTIMATOR == 0x3C and C.FLAGS_KNOWN == 0x7F  # bit 6: MECH_COMP_ENABLE (revision 1.2)


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


def _block(flags: int) -> B.ParamBlock:
    return dataclasses.replace(golden.golden_blocks()[1][1], flags=flags)


def test_pack_carries_the_option_bits_and_unpack_reads_them_back():
    flags = C.FLAG_COMP_ENABLE | C.FLAG_INTERP_ENABLE | C.FLAGS_ESTIMATOR
    data = B.pack(_block(flags))
    res = B.check(data)
    assert res.valid and res.warnings == ()
    back = B.unpack(data)
    assert back.flags == flags
    assert B.flag_names(back.flags) == ("COMP_ENABLE|INTERP_ENABLE|EST_CLAMP_TO_NEXT_EDGE|EST_LEARN_GRID_OFFSET|"
                                         "EST_ACCEL_PREDICTION|EST_LEARN_PITCH_ERRORS")
    assert est.EstimatorConfig.from_block(back) == est.EstimatorConfig.from_block(back, **{n: True for n in est.OPTION_FLAGS})


def test_an_option_without_interp_enable_is_valid_but_warned_about():
    data = B.pack(_block(C.FLAG_COMP_ENABLE | C.FLAG_EST_LEARN_PITCH_ERRORS))
    res = B.check(data)
    assert res.valid
    assert len(res.warnings) == 1 and "EST_LEARN_PITCH_ERRORS without INTERP_ENABLE" in res.warnings[0]
    # and the estimator it gives is the paper's
    assert est.EstimatorConfig.from_block(B.unpack(data)).options == 0


def test_unknown_bits_are_named_as_a_number():
    assert B.flag_names(C.FLAG_COMP_ENABLE | 0x100) == "COMP_ENABLE|0x100"
    with pytest.raises(InputError, match="flags"):
        B.pack(_block(0x40))


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


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(ALONE))
def test_each_option_alone_changes_the_estimate(name):
    # the scenario shows its option acting: the same signals under the paper estimator differ
    sc = G.SCENARIOS[name]
    a, b, h = sc.signals()
    with_option = est.run(sc.cfg, a, b, h)
    paper = est.run(est.EstimatorConfig.from_flags(C.FLAG_INTERP_ENABLE, tick_hz=G.TICK_HZ), a, b, h)
    assert not np.array_equal(with_option.theta_hat.view(np.uint32), paper.theta_hat.view(np.uint32))


# --------------------------------------------------------------------------- the CLI and the station
def _cli(*args: str):
    from click.testing import CliRunner

    from cli.main import cli

    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


def test_block_show_names_the_options_and_warns_without_interp(tmp_path):
    import json

    path = tmp_path / "b.bin"
    path.write_bytes(B.pack(_block(C.FLAG_COMP_ENABLE | C.FLAG_EST_LEARN_GRID_OFFSET)))
    res = _cli("block", "show", str(path))
    text = " ".join(res.output.split())
    assert res.exit_code == 0
    assert "COMP_ENABLE|EST_LEARN_GRID_OFFSET" in text and "warning" in text and "without INTERP_ENABLE" in text
    doc = json.loads(_cli("block", "show", str(path), "--json").output)
    assert doc["valid"] and any("EST_LEARN_GRID_OFFSET without INTERP_ENABLE" in w for w in doc["warnings"])
    # with INTERP_ENABLE: no warning
    path.write_bytes(B.pack(_block(C.FLAG_INTERP_ENABLE | C.FLAG_EST_LEARN_GRID_OFFSET)))
    doc = json.loads(_cli("block", "show", str(path), "--json").output)
    assert doc["warnings"] == []


@pytest.mark.parametrize("choice, flags", [(None, C.FLAG_INTERP_ENABLE | C.FLAGS_ESTIMATOR),
                                           ("paper", C.FLAG_INTERP_ENABLE),
                                           ("0x20", C.FLAG_INTERP_ENABLE | C.FLAG_EST_LEARN_PITCH_ERRORS)])
def test_block_uncompensated_carries_the_chosen_options(tmp_path, choice, flags):
    path = tmp_path / "prep.bin"
    extra = [] if choice is None else ["--estimator", choice]
    res = _cli("block", "uncompensated", "--serial", "M-1", "-o", str(path), *extra)
    assert res.exit_code == 0, res.output
    blk = B.unpack(path.read_bytes())
    assert blk.flags == flags and not blk.flags & C.FLAG_COMP_ENABLE


#: the fixture's limits; its last table is variant EPS-PREMIUM, so a line appended belongs to it
LIMITS = (Path(__file__).resolve().parents[1] / "fixtures" / "limits.toml").read_text("utf-8") + "\n"
VARIANT = "EPS-PREMIUM"


@pytest.mark.parametrize("line, label, bits", [("", "best", 0x3C), ('estimator = "paper"', "paper", 0),
                                               ('estimator = "learn_pitch_errors+clamp_to_next_edge"',
                                                "EST_CLAMP_TO_NEXT_EDGE+EST_LEARN_PITCH_ERRORS", 0x24),
                                               ('estimator = "0x3c"', "best", 0x3C)])
def test_limits_estimator_key(line, label, bits):
    from eol_cal.records.limits import LIMIT_KEYS, parse_limits

    lim = parse_limits(LIMITS + line + "\n", "lim.toml")[VARIANT]
    assert lim.estimator == label and lim.estimator_options == bits
    assert "estimator" not in LIMIT_KEYS  # not a pass/fail limit


@pytest.mark.parametrize("value", ['"fancy"', '"0x40"', "12"])
def test_limits_refuse_a_bad_estimator(value):
    from eol_cal.records.limits import parse_limits

    with pytest.raises(InputError) as err:
        parse_limits(LIMITS + f"estimator = {value}\n", "lim.toml")
    assert "lim.toml" in str(err.value) and f"variant.{VARIANT}.estimator" in str(err.value)


def test_station_config_estimator_overrides_the_variant(tmp_path):
    from eol_cal.records.limits import parse_limits
    from eol_cal.station.run import StationConfig

    lim = parse_limits(LIMITS + 'estimator = "paper"\n', "lim.toml")[VARIANT]
    cfg = StationConfig(serial="S", dyno=None, open_bus=lambda: None, seed_to_key=lambda s: s, limits=lim,
                        db=tmp_path / "db", report_dir=tmp_path)
    assert cfg.estimator_options == 0
    cfg.estimator = "best"
    assert cfg.estimator_options == C.FLAGS_ESTIMATOR


@pytest.mark.slow
def test_the_prepared_block_selects_the_same_estimator_in_the_rig():
    """The rig's plant runs what the ECU's active block selects: a prepared block with ``best``
    gives another angle estimate than one with ``paper`` (same motor, same noise)."""
    from eol_cal.analysis.fit.table import uncompensated_block
    from eol_cal.dyno.registers import DutCmdKind
    from eol_cal.dyno.sim_capture import CaptureRequest
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.sim.rig import ActiveCalibration, plant_capture

    motor = load_motor("paper")
    req = CaptureRequest(speed_rpm=120.0, dut_cmd_kind=DutCmdKind.IQ, dut_cmd=40.0, n_samples=2000,
                         rate_hz=20000.0, serial="M-1", seed=None, capture_index=1)
    caps = {}
    for name, bits in (("paper", 0), ("best", C.FLAGS_ESTIMATOR)):
        blk = uncompensated_block("M-1", motor, calibrated_at=0, options=bits)
        caps[name] = plant_capture()(req, ActiveCalibration("estimated", blk))
    assert not np.array_equal(caps["paper"]["iq"], caps["best"]["iq"])
