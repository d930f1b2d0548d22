"""The A2L description (firmware contract section 5), read back by independent A2L readers.

pya2ldb (``pya2l``) parses the file written by ``eol-cal block a2l`` into its model; every
characteristic's address, size, data type and unit is compared with the layout as the project's
own block code reads it, and the values a calibration tool would show at those addresses with
those types are compared with :func:`eol_cal.firmware.block.unpack` of a real block image.
a2ltool (the a2lfile crate's command line) checks the same files in strict mode.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from sqlalchemy import event
from sqlalchemy.engine import Engine

from cli.main import cli
from eol_cal.sim.virtual_rig import example_block
from eol_cal.firmware import block as B
from eol_cal.firmware import contract as C
from eol_cal.firmware import gen_header
from eol_cal.firmware.contract import DEFAULT_TABLE_LEN
from eol_cal.firmware.mech_params import FP_FORWARD, FP_MAX, FP_REVERSE, MechParams, make_mech_tables, unused_mech

# pya2l registers a "connect" listener on EVERY SQLAlchemy engine of the process (its SQLite
# pragmas and REGEXP function; on a psycopg connection it raises): the records tests in the same
# pytest process would open their databases through it. It is kept only while pya2l opens its own.


@functools.cache
def _pya2l() -> tuple[Any, Any, Any]:
    """pya2l (pya2ldb, in the test extra), its model and its inspect API, imported at first use (1.9
    CPU s: every test worker paid it at collection) with its listener taken off at once."""
    import pya2l
    from pya2l import model
    from pya2l.api import inspect

    event.remove(Engine, "connect", model.set_sqlite3_pragmas)
    return pya2l, model, inspect


@contextlib.contextmanager
def _pya2l_connects():
    model = _pya2l()[1]
    event.listen(Engine, "connect", model.set_sqlite3_pragmas)
    try:
        yield
    finally:
        event.remove(Engine, "connect", model.set_sqlite3_pragmas)


def _import_a2l(path: Path):
    """pya2l's session of an A2L file, its inspected characteristics by name."""
    pya2l, model, a2l_inspect = _pya2l()
    with _pya2l_connects():
        session = pya2l.import_a2l(str(path), in_memory=True, progress_bar=False, loglevel="ERROR")
        names = [c.name for c in session.query(model.Characteristic).all()]
        return session, {name: a2l_inspect.Characteristic(session, name) for name in names}

ROOT = Path(__file__).resolve().parents[1]

#: the ASAM data type and size each layout type must become (stated here, independently of gen_a2l)
ASAM_TYPE = {"u8": ("UBYTE", 1), "u16": ("UWORD", 2), "u32": ("ULONG", 4), "f32": ("FLOAT32_IEEE", 4)}
NP_TYPE = {"UBYTE": "u1", "UWORD": "u2", "ULONG": "u4", "FLOAT32_IEEE": "f4"}


def _a2ltool() -> str:
    """The a2ltool executable the test extra installs next to this interpreter (else on PATH)."""
    beside = Path(sys.executable).parent / "a2ltool"
    exe = str(beside) if beside.exists() else shutil.which("a2ltool")
    assert exe is not None, "a2ltool (test extra) is not installed"
    return exe


def _write_a2l(tmp_path: Path, bank: int, table_len: int, layout: int = 1) -> Path:
    out = tmp_path / f"bank{bank}_n{table_len}_v{layout}.a2l"
    res = CliRunner().invoke(cli, ["block", "a2l", "--bank", str(bank), "-o", str(out), "--table-len", str(table_len),
                                   "--layout", str(layout)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module", params=[(0, DEFAULT_TABLE_LEN, 1), (1, 1024, 1), (1, 16, 1), (0, DEFAULT_TABLE_LEN, 2),
                                        (1, 16, 2)], ids=lambda p: f"bank{p[0]}-N{p[1]}-v{p[2]}")
def parsed(request, tmp_path_factory):
    bank, n, layout = request.param
    path = _write_a2l(tmp_path_factory.mktemp("a2l"), bank, n, layout)
    session, chars = _import_a2l(path)
    yield bank, n, path, session, chars, layout


def _mech_example(encoder_ppr: int) -> MechParams:
    """A layout-2 extension with a distinct value in every field (so a misplaced one shows)."""
    rng = np.random.default_rng(7)
    m = unused_mech(encoder_ppr)
    tc, tp = make_mech_tables((0.01, 0.002, 0.001), (0.3, 1.1, -2.0), (1e-5, 0.0, 2e-6), (0.5, 0.0, 1.0), 0.049)
    return m.replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=1.25, mech_c=(0.01, 0.002, 0.001),
                     mech_phase_c=(0.3, 1.1, -2.0), mech_k=(1e-5, 0.0, 2e-6), mech_phase_k=(0.5, 0.0, 1.0),
                     mech_table_const=tc, mech_table_per_amp=tp,
                     fingerprint=rng.normal(0.0, 0.005, 2 * encoder_ppr))


def _size(ch) -> int:
    dims = [d for d in (ch.matrixDim.x, ch.matrixDim.y, ch.matrixDim.z) if d is not None]
    return ch.fnc_element_size * math.prod(dims)


def test_a_characteristic_per_field_and_per_named_flag_bit(parsed):
    _, _, _, _, chars, layout = parsed
    fields = [f["name"] for f in B.LAYOUTS[layout]["field"]]
    bits = [f"flags.{name}" for name in C.FLAGS]
    assert sorted(chars) == sorted(fields + bits)


def test_every_characteristic_has_the_layouts_address_size_type_and_unit(parsed):
    bank, n, _, _, chars, layout = parsed
    base = 2 * B.BANK_WORD_ADDR[bank]  # the contract's byte address of the bank
    for f in B.LAYOUTS[layout]["field"]:
        name = f["name"]
        ch = chars[name]
        asam, elem = ASAM_TYPE[f["type"]]
        count = B.field_count(name, n, layout)
        assert ch.address == base + B.field_offset(name, n, layout), name
        assert ch.fnc_asam_dtype == asam, name
        assert ch.fnc_element_size == elem, name
        assert _size(ch) == elem * count, name
        if name == "serial":
            assert ch.type == "ASCII" and ch.matrixDim.x == count
        elif f.get("count", 1) == 1:
            assert ch.type == "VALUE" and ch.matrixDim.x is None, name
        else:
            assert ch.type == "VAL_BLK" and ch.matrixDim.x == count, name
        if name not in ("serial", "flags"):
            assert ch.compuMethod.conversionType == "IDENTICAL", name
            assert ch.compuMethod.unit == f.get("unit", ""), name
        assert (ch.physUnit or "") == f.get("unit", ""), name
        assert ch.readOnly == (f["role"] != "field" or name == "layout_version"), name
    assert chars["hall_angle"].matrixDim.x == 6
    assert chars["table_const"].matrixDim.x == chars["table_per_amp"].matrixDim.x == n


def test_the_characteristics_tile_the_block(parsed):
    bank, n, _, _, chars, layout = parsed
    spans = sorted((chars[f["name"]].address, _size(chars[f["name"]])) for f in B.LAYOUTS[layout]["field"])
    start = 2 * B.BANK_WORD_ADDR[bank]
    for addr, size in spans:
        assert addr == start
        start += size
    assert start - 2 * B.BANK_WORD_ADDR[bank] == B.block_bytes(n, layout) == {1: 104, 2: 3248}[layout] + 8 * n


def test_flags_name_the_contracts_bits(parsed):
    _, _, _, _, chars, _ = parsed
    flags = chars["flags"]
    verb = flags.compuMethod.tab_verb
    assert flags.compuMethod.conversionType == "TAB_VERB"
    table = dict(zip(verb.in_values, verb.text_values, strict=True))
    assert len(table) == 2 ** len(C.FLAGS)
    for name, flag in C.FLAGS.items():
        assert table[float(1 << flag.bit)] == name
        bit = chars[f"flags.{name}"]
        assert bit.bitMask == 1 << flag.bit and bit.address == flags.address
        assert bit.compuMethod.tab_verb.text_values == ["off", "on"]
    assert table[float(C.FLAGS_KNOWN)] == "|".join(C.FLAGS)


def test_memory_segments_byte_order_and_version(parsed):
    _, n, path, session, _, layout = parsed
    model = _pya2l()[1]
    segs = sorted(session.query(model.MemorySegment).all(), key=lambda s: s.address)
    assert [(s.name, s.address, s.size, s.prgType, s.memoryType) for s in segs] == [
        (f"BANK{b}", 2 * w, B.BANK_BYTES, "DATA", "FLASH") for b, w in enumerate(B.BANK_WORD_ADDR)]
    assert [2 * w for w in B.BANK_WORD_ADDR] == [0x650000, 0x660000]
    assert session.query(model.ModCommon).one().byte_order.byteOrder == "MSB_LAST"
    version = session.query(model.Asap2Version).one()
    assert (version.versionNo, version.upgradeNo) == (1, 71)
    assert f"table_len = {n}" in path.read_text("ascii").split("*/")[0]
    assert f"layout version {layout}," in path.read_text("ascii").split("*/")[0]


def test_a_tool_reading_with_the_a2l_sees_the_blocks_values(parsed):
    """What CANape would display: each characteristic read from a bank image at its address,
    with its type, the byte order and bit mask, equals the block's decoded fields."""
    bank, n, _, session, chars, layout = parsed
    # bit 0 set, bit 1 clear: the bit characteristics must tell them apart
    blk = dataclasses.replace(B.unpack(example_block(serial="EPS-A2L-7", table_len=n, sequence=5)),
                              flags=C.FLAG_COMP_ENABLE)
    if layout == 2:
        blk = dataclasses.replace(blk, layout_version=2, mech=_mech_example(blk.encoder_ppr))
    data = B.pack(blk)
    model = _pya2l()[1]
    seg = {s.name: s for s in session.query(model.MemorySegment).all()}[f"BANK{bank}"]
    image = data + b"\xff" * (seg.size - len(data))
    order = {"MSB_LAST": "<", "MSB_FIRST": ">"}[session.query(model.ModCommon).one().byte_order.byteOrder]
    expected = B.unpack(data).to_dict() | {"reserved": 0, "crc32": B.crc32(data[:-4])}
    if layout == 2:
        mech = expected.pop("mech")
        fp = np.zeros(2 * FP_MAX)
        fp[:len(mech["fingerprint"])] = mech["fingerprint"]
        expected |= mech | {"fingerprint": fp, "mech_table_len": 128, "reserved2": 0}
    for name, ch in chars.items():
        off = ch.address - seg.address
        raw = image[off:off + _size(ch)]
        if ch.type == "ASCII":
            assert raw.rstrip(b"\0").decode("ascii") == expected[name] == "EPS-A2L-7"
            continue
        values = np.frombuffer(raw, dtype=order + NP_TYPE[ch.fnc_asam_dtype])
        if ch.bitMask:
            shift = (ch.bitMask & -ch.bitMask).bit_length() - 1
            flag = name.split(".", 1)[1]
            assert (int(values[0]) & ch.bitMask) >> shift == bool(expected["flags"] & (1 << C.FLAGS[flag].bit)), name
        elif ch.type == "VAL_BLK":
            np.testing.assert_array_equal(values, np.asarray(expected[name], dtype=values.dtype), err_msg=name)
        else:
            assert values[0] == expected[name], name


def test_a2ltool_strict_check_finds_no_problem(parsed):
    _, _, path, _, _, _ = parsed
    res = subprocess.run([_a2ltool(), str(path), "--strict", "--check"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "No problems found" in res.stdout + res.stderr, res.stdout + res.stderr


def test_a2ltool_strict_refuses_a_broken_file(tmp_path):
    """The strict reader is not a rubber stamp: a dangling RECORD_LAYOUT reference fails it."""
    good = _write_a2l(tmp_path, 0, 16).read_text("ascii")
    bad = tmp_path / "bad.a2l"
    bad.write_text(good.replace("RL_FLOAT32_IEEE 0 CM_Hz", "RL_MISSING 0 CM_Hz"), "ascii")
    res = subprocess.run([_a2ltool(), str(bad), "--strict", "--check"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode != 0 and "RL_MISSING" in res.stdout + res.stderr


def test_checked_in_a2l_is_generated_and_describes_bank0_default_table(tmp_path):
    path = ROOT / "firmware_params" / "eol_param_block.a2l"
    path2 = ROOT / "firmware_params" / "eol_param_block_v2.a2l"
    for layout, checked_in in ((1, path), (2, path2)):
        out = _write_a2l(tmp_path, 0, DEFAULT_TABLE_LEN, layout)
        assert checked_in.read_text("ascii") == out.read_text("ascii"), "stale A2L: run python -m eol_cal.firmware.gen_header"
    assert gen_header.main(["--check", "--out", str(ROOT / "firmware_params" / "eol_param_block.h"),
                            "--a2l-out", str(path), "--a2l-v2-out", str(path2)]) == 0


def test_cli_refuses_bad_bank_and_table_len(tmp_path):
    out = tmp_path / "x.a2l"
    for args, value in ((["--bank", "2"], "2"), (["--bank", "0", "--table-len", "300"], "300"),
                        (["--bank", "1", "--table-len", "2048"], "2048"), (["--bank", "0", "--table-len", "0"], "0")):
        res = CliRunner().invoke(cli, ["block", "a2l", "-o", str(out), *args])
        assert res.exit_code == 2, res.output
        assert value in res.output
        assert not out.exists()


@pytest.mark.slow
def test_a_bit_the_contract_adds_appears_without_touching_the_generator(tmp_path, monkeypatch):
    """gen_a2l reads the flag names from contract.FLAGS: a new bit there is a new characteristic
    and a new name in the flags word's verbal table, and the file still reads back."""
    monkeypatch.setitem(C.FLAGS, "TEST_BIT_31", C.Flag(31, "a bit this test adds"))
    path = _write_a2l(tmp_path, 1, 16)
    session, chars = _import_a2l(path)
    bit = chars["flags.TEST_BIT_31"]
    assert bit.bitMask == 1 << 31 and bit.address == 2 * B.BANK_WORD_ADDR[1] + B.field_offset("flags")
    verb = chars["flags"].compuMethod.tab_verb
    assert len(verb.in_values) == 2 ** len(C.FLAGS)
    verbs = dict(zip(verb.in_values, verb.text_values, strict=True))
    assert verbs[float(1 << 31 | C.FLAG_COMP_ENABLE)] == "COMP_ENABLE|TEST_BIT_31"
    res = subprocess.run([_a2ltool(), str(path), "--strict", "--check"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr


def test_pya2l_leaves_no_listener_on_other_engines(parsed):
    """Our own engines (the records' SQLite and PostgreSQL) never run pya2l's connect hook."""
    assert not event.contains(Engine, "connect", _pya2l()[1].set_sqlite3_pragmas)


def _contract_bounds(layout: int, table_len: int, motor) -> dict[str, tuple[float, float]]:
    """The contract's bounds table (docs/firmware-contract.md, "Bounds of each field"), read from
    the page itself, for a layout, a table length and a motor (its symbols evaluated)."""
    text = (ROOT / "docs" / "firmware-contract.md").read_text("utf-8")
    section = text.split("### Bounds of each field", 1)[1].split("\n### ", 1)[0]
    names = {"N": table_len, "P": motor.poles, "N_enc": motor.N_enc, "i_max": motor.i_max, "pi": math.pi}

    def value(cell: str) -> float:
        if "(layout 2: " in cell:
            one, two = cell.split("(layout 2: ")
            cell = two.rstrip(")") if layout == 2 else one
        return float(eval(cell.strip(), {"__builtins__": {}}, names))  # our own page's table, no builtins

    out = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0].startswith("`"):
            out[cells[0].strip("`")] = (value(cells[1]), value(cells[2]))
    return out


def test_every_characteristics_limits_are_the_contracts_bounds(parsed):
    """Each field's LOWER/UPPER LIMIT as an independent reader sees it equals the bounds table of
    the contract (the paper's motor, for which the files are written), both layouts."""
    from eol_cal.domain.motor_params import load_motor

    _, n, _, _, chars, layout = parsed
    bounds = _contract_bounds(layout, n, load_motor())
    fields = B.FIELDS_BY_VERSION[layout]
    assert set(fields) <= set(bounds), sorted(set(fields) - set(bounds))
    for name in fields:
        lo, hi = bounds[name]
        ch = chars[name]
        assert (ch.lowerLimit, ch.upperLimit) == pytest.approx((lo, hi), rel=1e-15, abs=0), name


def test_texts_and_read_only_fields_are_the_layouts(parsed):
    """The layout's own version and size in the texts; the version is not a tool's to change."""
    _, n, _, _, chars, layout = parsed
    assert chars["layout_version"].longIdentifier == f"layout version of this block ({layout})"
    assert chars["layout_version"].readOnly
    assert ("3248 + 8*N" if layout == 2 else "104 + 8*N") in chars["block_bytes"].longIdentifier
    assert chars["block_bytes"].lowerLimit == B.block_bytes(n, layout)
    for name, f in B.FIELDS_BY_VERSION[layout].items():
        assert chars[name].readOnly == (f["role"] != "field" or name == "layout_version"), name
