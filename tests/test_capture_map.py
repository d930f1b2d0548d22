"""Channel maps and unit conversion: the foreign DAQ fixture, map errors, pint conversions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _capture_helpers import small_capture

from eol_cal.capture import load_channel_map, read_capture, write_capture
from eol_cal.capture.units import to_canonical
from eol_cal.errors import InputError

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
FOREIGN = FIXTURES / "daq_export_foreign.csv"
FOREIGN_MAP = FIXTURES / "daq_export_foreign.map.toml"


def test_foreign_fixture_through_its_map():
    c = read_capture(FOREIGN, FOREIGN_MAP)
    assert list(c.channels) == ["torque", "enc_a", "enc_b", "hall", "iq_ref", "speed", "temp"]
    assert c.metadata == {"serial": "M-0001", "poles": 6, "encoder_ppr": 64, "station": "EOL-2"}
    assert c.truth == {}
    # time in ms -> s, 10 kHz
    assert c.t[1] == pytest.approx(1e-4, rel=1e-12) and c.sample_rate == pytest.approx(10000.0)
    # torque in N*cm -> N*m: about kt*i_qo = 3.19 N*m
    assert 3.0 < c["torque"].mean() < 3.3
    # speed in 1/min -> rpm (revolutions, not radians), temperature degF -> degC
    assert np.allclose(c["speed"], 60.0)
    assert np.allclose(c["temp"], (68.0 + 0.5 * np.sin(np.pi * c.t) - 32.0) * 5 / 9, atol=1e-3)
    # hall from three bit lines follows the contract's forward sequence 5 1 3 2 6 4
    states = c["hall"][np.r_[True, np.diff(c["hall"]) != 0]]
    assert states[:7].tolist() == [5, 1, 3, 2, 6, 4, 5]


def test_foreign_map_reproduces_the_model():
    """The foreign export is the analytic model at 10 kHz: its map must give the model back."""
    from eol_cal.capture.synthetic import synthetic_capture

    ref = synthetic_capture(rpm=60.0, i_qo=65.0, seconds=1.0, fs=10000.0, serial="M-0001", seed=2)
    c = read_capture(FOREIGN, FOREIGN_MAP)
    assert np.allclose(c.t, ref.t, rtol=0, atol=1e-12)
    assert np.allclose(c["torque"], ref["torque"], rtol=0, atol=0.5e-6 + 1e-12)
    for name in ("enc_a", "enc_b", "hall"):
        assert np.array_equal(c[name], ref[name])


def test_map_with_mdf4_and_bits_on_own_time_bases(tmp_path):
    """A foreign MDF4: hall on three event lines with their own times, torque in N*cm."""
    from asammdf import MDF, Signal

    ref = small_capture()
    mdf = MDF(version="4.10")
    mdf.append([Signal(ref["torque"] * 100.0, ref.t, name="Moment", unit="N*cm"), Signal(ref["enc_a"], ref.t, name="A")])
    for bit, line in enumerate(("HU", "HV", "HW")):
        level = (ref["hall"] >> bit) & 1
        change = np.r_[True, level[1:] != level[:-1]]
        mdf.append([Signal(level[change].astype(np.uint8), ref.t[change], name=line)])
    mdf.save(tmp_path / "f.mf4", overwrite=True)
    mdf.close()
    (tmp_path / "f.toml").write_text(
        '[channels]\ntorque = { name = "Moment" }\nenc_a = { name = "A" }\nhall = { bits = ["HU", "HV", "HW"] }\n'
        '[metadata]\nserial = "F-1"\npoles = 6\nencoder_ppr = 64\niq_ref = 65\n'
    )
    c = read_capture(tmp_path / "f.mf4", tmp_path / "f.toml")
    assert np.array_equal(c.t, ref.t)
    assert np.allclose(c["torque"], ref["torque"], rtol=1e-15)
    assert np.array_equal(c["hall"], ref["hall"])
    # the hall events combine the three lines' change times
    times, levels = c.events["hall"]
    expect_t, expect_l = ref.t[1:][np.diff(ref["hall"]) != 0], ref["hall"][1:][np.diff(ref["hall"]) != 0]
    assert np.array_equal(times, expect_t) and np.array_equal(levels, expect_l)
    assert c.metadata["iq_ref"] == 65.0 and isinstance(c.metadata["iq_ref"], float)


def _map(tmp_path, text):
    path = tmp_path / "m.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "text, field, reason",
    [
        ('[channels]\ntorque = { name = "Nope" }\n', "torque", "source channel 'Nope' not found in"),
        ('[channels]\nhall = { bits = ["DI2", "DIX", "DI4"] }\n', "hall", "source channel 'DIX' not found in"),
    ],
)
def test_map_naming_absent_channel(tmp_path, text, field, reason):
    path = _map(tmp_path, text)
    with pytest.raises(InputError) as info:
        read_capture(FOREIGN, path)
    assert info.value.file == str(path) and info.value.field == field
    assert reason in info.value.reason and str(FOREIGN) in info.value.reason


@pytest.mark.parametrize(
    "text, field, reason",
    [
        ('[channels]\nTorque = { name = "x" }\n', "Torque", "not a canonical channel"),
        ('[channels]\ntorque = { name = "x", scale = 2 }\n', "torque", "unknown keys ['scale']"),
        ('[channels]\nenc_a = { bits = ["a", "b", "c"] }\n', "enc_a", "only for hall"),
        ('[channels]\nhall = { bits = ["a", "b"] }\n', "hall", "three source channel names"),
        ('[channels]\ntorque = { name = "x", unit = "parsec" }\n', "torque", "cannot be converted"),
        ('[channels]\ntorque = { name = "x", unit = "zorks" }\n', "torque", "unknown unit 'zorks'"),
        ('[channels]\ntorque = { name = "x" }\niq_ref = { name = "x" }\n', "iq_ref", "already feeds 'torque'"),
        ('[metadata]\n"truth.k6" = 0.1\n', "truth.k6", "written by simulators only"),
        ('[metadata]\npoles = "six"\n', "poles", "must be an integer"),
        ('[channel]\n', "channel", "unknown table"),
        ("[channels\n", None, "not valid TOML"),
    ],
)
def test_bad_map_files(tmp_path, text, field, reason):
    path = _map(tmp_path, text)
    with pytest.raises(InputError) as info:
        load_channel_map(path)
    assert info.value.file == str(path) and info.value.field == field
    assert reason in info.value.reason


def test_map_and_header_units_must_agree(tmp_path):
    path = _map(tmp_path, '[channels]\nt = { name = "Zeit", unit = "s" }\n')
    with pytest.raises(InputError, match="file states unit 'ms' but map") as info:
        read_capture(FOREIGN, path)
    assert info.value.file == str(FOREIGN) and info.value.field == "t (source channel 'Zeit')"


def test_hall_bit_line_not_binary(tmp_path):
    text = FOREIGN.read_text().splitlines()
    header = text[1].split(",")
    row = text[50].split(",")
    row[header.index("DI3")] = "2"
    text[50] = ",".join(row)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(text) + "\n")
    with pytest.raises(InputError, match="a bit line takes 0 or 1") as info:
        read_capture(bad, FOREIGN_MAP)
    assert info.value.field == "hall (bit line 'DI3')" and info.value.file == str(bad)


def test_canonical_column_and_map_output_collide(tmp_path):
    c = small_capture()
    write_capture(c, tmp_path / "c.csv")
    text = (tmp_path / "c.csv").read_text().replace("speed [rpm]", "moment [N*m]")
    (tmp_path / "c.csv").write_text(text)
    path = _map(tmp_path, '[channels]\ntorque = { name = "moment" }\n')
    with pytest.raises(InputError, match="also produced by the map") as info:
        read_capture(tmp_path / "c.csv", path)
    assert info.value.field == "torque"


@pytest.mark.parametrize(
    "channel, unit, value, expect",
    [
        ("torque", "N*cm", 250.0, 2.5),
        ("torque", "Nm", 2.5, 2.5),
        ("torque", "kN*m", 0.001, 1.0),
        ("iq_ref", "mA", 65000.0, 65.0),
        ("speed", "rpm", 60.0, 60.0),
        ("speed", "rad/s", 2 * np.pi, 60.0),
        ("speed", "1/min", 60.0, 60.0),
        ("speed", "Hz", 1.0, 60.0),
        ("temp", "degF", 212.0, 100.0),
        ("temp", "K", 273.15, 0.0),
        ("t", "ms", 1500.0, 1.5),
        ("t", "s", 1.5, 1.5),
    ],
)
def test_unit_conversions(channel, unit, value, expect):
    out = to_canonical(channel, np.array([value]), unit, "f.csv")
    assert out[0] == pytest.approx(expect, rel=1e-12, abs=1e-9)


@pytest.mark.parametrize(
    "channel, unit, reason",
    [
        ("torque", "A", "cannot be converted to 'N*m'"),
        ("temp", "N", "cannot be converted to 'degC'"),
        ("t", "m", "cannot be converted to 's'"),
        ("torque", "blorf", "unknown unit 'blorf'"),
        ("hall", "V", "given for a digital channel"),
        ("vbat", "V", "not a canonical channel"),
    ],
)
def test_unit_refusals(channel, unit, reason):
    with pytest.raises(InputError) as info:
        to_canonical(channel, np.array([1.0]), unit, "f.csv")
    assert info.value.file == "f.csv" and info.value.field == channel and reason in info.value.reason
