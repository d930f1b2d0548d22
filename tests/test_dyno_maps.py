"""Register map files: the shipped maps load, and every bad key is refused naming file, key and reason."""

from __future__ import annotations

from pathlib import Path

import pytest

from eol_cal.dyno.mapfile import load_register_map, shipped_maps
from eol_cal.dyno.registers import ROLES
from eol_cal.errors import InputError

MAPS = Path(__file__).resolve().parents[1] / "eol_cal" / "dyno" / "maps"
DEFAULT = (MAPS / "default.toml").read_text()
VENDOR_B = (MAPS / "vendor-b.toml").read_text()


def test_shipped_maps_load_and_place_every_required_role():
    assert set(shipped_maps()) >= {"default", "vendor-b"}
    for name in shipped_maps():
        m = load_register_map(name)
        assert {r for r, role in ROLES.items() if role.required} <= set(m.entries)
    assert load_register_map(None).name == load_register_map("default").name
    assert load_register_map(MAPS / "vendor-b.toml").word_order == "little"


def _edit(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


@pytest.mark.parametrize(
    ("base", "old", "new", "key", "reason"),
    [
        (DEFAULT, 'word_order = "big"', 'word_order = "middle"', "word_order", "not one of big, little"),
        (DEFAULT, "shared_tables = true", "shared_tables = 1", "shared_tables", "not true or false"),
        (DEFAULT, "max_read_registers = 125", "max_read_registers = 200", "max_read_registers", "outside 1 ... 125"),
        (DEFAULT, "map_version = 1 ", "map_vers = 1 ", "map_vers", "unknown key"),
        (DEFAULT, "[registers.ramp]\naddress = 106", "[registers.rampe]\naddress = 106", "registers.rampe", "unknown key"),
        (DEFAULT, "[registers.ramp]\naddress = 106", "[registers.ramp]\naddress = 105", "registers.ramp.address",
         "overlaps registers.speed_setpoint"),
        (DEFAULT, "[registers.ramp]\naddress = 106", "[registers.ramp]\naddress = 0x8001", "registers.ramp.address",
         "overlaps window"),
        (DEFAULT, "[registers.ramp]\naddress = 106", "[registers.ramp]\naddress = -1", "registers.ramp.address", "outside"),
        (DEFAULT, "[registers.ramp]\naddress = 106", "[registers.ramp]\naddress = \"x\"", "registers.ramp.address",
         "not an integer"),
        (DEFAULT, "[registers.ramp]\naddress = 106\ntype = \"f32\"", "[registers.ramp]\naddress = 106\ntype = \"f64\"",
         "registers.ramp.type", "not one of"),
        (DEFAULT, "[registers.ramp]\naddress = 106\ntype = \"f32\"\ntable = \"holding\"",
         "[registers.ramp]\naddress = 106\ntype = \"f32\"\ntable = \"input\"",
         "registers.ramp.table", "must be a holding register"),
        (DEFAULT, 'unit = "rpm/s"', 'unit = "rad/s"', "registers.ramp.unit", "conversion as scale"),
        (DEFAULT, "[registers.mode]\naddress = 100\ntype = \"u16\"\ntable = \"holding\"",
         "[registers.mode]\naddress = 100\ntype = \"u16\"\ntable = \"holding\"\ncodes = { off = 0 }",
         "registers.mode.codes.speed", "missing"),
        (DEFAULT, "[registers.mode]\naddress = 100\ntype = \"u16\"\ntable = \"holding\"",
         "[registers.mode]\naddress = 100\ntype = \"u16\"\ntable = \"holding\"\ncodes = { off = 0, speed = 0 }",
         "registers.mode.codes.speed", "also another code"),
        (DEFAULT, "[registers.mode]\naddress = 100\ntype = \"u16\"\ntable = \"holding\"",
         "[registers.mode]\naddress = 100\ntype = \"u16\"\ntable = \"holding\"\nscale = 2", "registers.mode.scale",
         "only for numeric"),
        (DEFAULT, "[registers.mode]\naddress = 100\ntype = \"u16\"", "[registers.mode]\naddress = 100\ntype = \"f32\"",
         "registers.mode.type", "cannot hold codes"),
        (DEFAULT, "[registers.dut_serial]\naddress = 1\ntype = \"str\"", "[registers.dut_serial]\naddress = 1\ntype = \"u16\"",
         "registers.dut_serial.type", "must be str"),
        (DEFAULT, "[registers.tick_hz]\naddress = 15\ntype = \"u32\"", "[registers.tick_hz]\naddress = 15\ntype = \"str\"",
         "registers.tick_hz.type", "only for text"),
        (DEFAULT, "[registers.speed]\naddress = 200\ntype = \"f32\"",
         "[registers.speed]\naddress = 200\ntype = \"f32\"\ninvalid = 0", "registers.speed.invalid", "only for integer"),
        (DEFAULT, "[registers.heartbeat]\naddress = 213", "[registers.heartbeat_]\naddress = 213", "registers.heartbeat_",
         "unknown key"),
        (DEFAULT, "torque = 1\n", "", "channels.torque", "missing"),
        (DEFAULT, "iq_ref = 2\n", "iq_ref = 1\n", "channels.iq_ref", "also channels.torque"),
        (DEFAULT, "torque = 1\n", "torque = 16\n", "channels.torque", "also window.digital_id"),
        (DEFAULT, "ic = 10\n", "ic = 10\nic2 = 11\n", "channels.ic2", "unknown key"),
        (DEFAULT, "digital_bits = { enc_a = 0, enc_b = 1, hall = 2 }", "digital_bits = { enc_a = 0, enc_b = 1, hall = 1 }",
         "window.digital_bits.hall", "overlaps"),
        (DEFAULT, 'analog_type = "f32"', 'analog_type = "i16"', "window.analog_type", "not one of f32"),
        (VENDOR_B, "scale = 0.1                 # 0.1 rpm", "scale = 0                   # 0.1 rpm", "registers.speed.scale",
         "must not be 0"),
        (VENDOR_B, "invalid = -2147483648", "invalid = 4294967295", "registers.torque.invalid", "outside"),
        (VENDOR_B, "over_speed = 3,", "over_speed = 4,", "registers.faults.bits.torque_sensor", "also another flag"),
        (VENDOR_B, "codes = { off = 0, on = 0x000F }", "codes = { off = 0, on = 0x000F, maybe = 2 }",
         "registers.enable.codes.maybe", "unknown code"),
        # holding and input are apart
        (VENDOR_B, "[registers.mode]\naddress = 0\n", "[registers.mode]\naddress = 0x0100\n", None, None),
    ],
)
def test_bad_keys_are_named(tmp_path: Path, base: str, old: str, new: str, key: str | None, reason: str | None):
    path = tmp_path / "rig.toml"
    path.write_text(_edit(base, old, new))
    if key is None:
        load_register_map(path)
        return
    with pytest.raises(InputError) as err:
        load_register_map(path)
    assert err.value.file == str(path)
    assert err.value.field == key, str(err.value)
    assert reason in err.value.reason, str(err.value)


def test_shared_tables_make_holding_and_input_one_space(tmp_path: Path):
    path = tmp_path / "rig.toml"
    path.write_text(_edit(VENDOR_B, "shared_tables = false", "shared_tables = true"))
    with pytest.raises(InputError, match="overlaps"):
        load_register_map(path)


def test_missing_role_map_version_and_names():
    from eol_cal.dyno.mapfile import parse_register_map
    import tomllib

    doc = tomllib.loads(DEFAULT)
    del doc["registers"]["speed_setpoint"]
    with pytest.raises(InputError) as err:
        parse_register_map(doc, "x.toml")
    assert err.value.field == "registers.speed_setpoint" and "missing" in err.value.reason
    doc = tomllib.loads(DEFAULT)
    del doc["map_version"]
    with pytest.raises(InputError, match="map_version"):
        parse_register_map(doc, "x.toml")
    doc = tomllib.loads(DEFAULT)
    del doc["registers"]["sim_fault"], doc["registers"]["sim_fault_arg"], doc["registers"]["map_version"], doc["map_version"]
    m = parse_register_map(doc, "x.toml")  # the optional roles
    assert m.map_version is None and "sim_fault" not in m
    for bad in ("vendor-z", "no/such/map.toml"):
        with pytest.raises(InputError):
            load_register_map(bad)


@pytest.mark.parametrize("byte_order", ["big", "little"])
@pytest.mark.parametrize("word_order", ["big", "little"])
def test_one_value_is_coded_as_the_array_codec_codes_it(byte_order: str, word_order: str):
    """regcodec.value_words / words_value (a status poll's registers) against to_words / from_words
    (a capture's samples): the same words and the same values, bit for bit, every type and order."""
    import math
    import struct

    import numpy as np

    from eol_cal.dyno import regcodec as rc

    rng = np.random.default_rng(7)
    for type_ in rc.TYPE_REGS:
        if type_ == "f32":
            values = [0.0, -0.0, 1.0, -1.5, 3.4028234663852886e38, 1e39, -1e39, 1e-45, 1e-46, math.inf, -math.inf,
                      math.nan, 0.1, *rng.normal(0.0, 1e3, 200), *(rng.normal(0.0, 1.0, 50) * 10.0 ** rng.integers(-40, 40, 50))]
        else:
            lo, hi = rc.RANGES[type_]
            values = [lo, hi, 0, 1, -1 if lo < 0 else 2, *(int(v) for v in rng.integers(lo, hi, 200, endpoint=True))]
        for v in values:
            with np.errstate(over="ignore"):
                want = [int(w) for w in rc.to_words(np.asarray([v]), type_, byte_order, word_order)]
                words = rc.value_words(v, type_, byte_order, word_order)  # beyond binary32: numpy's cast
            assert words == want, (type_, v)
            back, array_back = rc.words_value(words, type_, byte_order, word_order), \
                rc.from_words(np.asarray(words), type_, byte_order, word_order)[0]
            if type_ == "f32":
                assert isinstance(back, float)
                same_bits = struct.pack(">f", back) == struct.pack(">f", float(array_back))
                assert same_bits or (math.isnan(back) and math.isnan(array_back))
            else:
                assert isinstance(back, int) and back == int(array_back) == v
    # every 16-bit word read back as the array codec reads it (a dyno's registers are any words)
    for type_ in rc.TYPE_REGS:
        n = rc.TYPE_REGS[type_]
        for words in rng.integers(0, 0x10000, (300, n)).tolist():
            back, array_back = rc.words_value(words, type_, byte_order, word_order), \
                rc.from_words(np.asarray(words), type_, byte_order, word_order)[0]
            if type_ == "f32":
                assert (math.isnan(back) and math.isnan(array_back)) or back == float(array_back)
            else:
                assert back == int(array_back)
