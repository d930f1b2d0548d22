"""Parameter block: layout, pack/unpack, every validity rule, CRC, Intel HEX, generated header."""

from __future__ import annotations

import dataclasses
import io
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from intelhex import IntelHex

from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware import gen_header, golden

ROOT = Path(__file__).resolve().parents[1]


def _block(n: int = 64, **kw) -> B.ParamBlock:
    x = 2 * np.pi * np.arange(n) / n
    args = dict(sequence=5, flags=B.FLAG_COMP_ENABLE, serial="SN-42", calibrated_at=1_700_000_000, poles=6,
                encoder_ppr=64, tick_hz=20000.0, kt=0.04905, hall_angle=(1.0, 3.1, 2.0, 5.2, 0.0, 4.1),
                c6=0.01, phase_c6=0.1, k6=0.002, phase_k6=-0.3, lead_s=8e-4, iqc_limit=5.0,
                table_const=0.2 * np.sin(x), table_per_amp=0.03 * np.cos(x))
    args.update(kw)
    return B.ParamBlock(**args)


# ---- layout -------------------------------------------------------------------------------

CONTRACT_OFFSETS = {  # firmware contract section 2, typed in independently of layout_v1.toml
    "magic": 0, "layout_version": 2, "block_bytes": 4, "sequence": 8, "flags": 12, "serial": 16,
    "calibrated_at": 32, "poles": 36, "encoder_ppr": 38, "tick_hz": 40, "kt": 44, "hall_angle": 48,
    "c6": 72, "phase_c6": 76, "k6": 80, "phase_k6": 84, "lead_s": 88, "iqc_limit": 92,
    "table_len": 96, "reserved": 98, "table_const": 100,
}


@pytest.mark.parametrize("n", [16, 256, 1024])
def test_layout_matches_contract_and_tiles_the_block(n):
    assert set(B.FIELDS) == set(CONTRACT_OFFSETS) | {"table_per_amp", "crc32"}
    for name, off in CONTRACT_OFFSETS.items():
        assert B.field_offset(name, n) == off, name
    assert B.field_offset("table_per_amp", n) == 100 + 4 * n
    assert B.field_offset("crc32", n) == 100 + 8 * n
    # fields tile [0, block_bytes) without gap or overlap; 32-bit fields 4-aligned
    spans = sorted((B.field_offset(f, n), B.field_count(f, n) * B._SIZE[B.FIELDS[f]["type"]], f)
                   for f in B.FIELDS)
    pos = 0
    for off, size, name in spans:
        assert off == pos, name
        if B.FIELDS[name]["type"] in ("u32", "f32"):
            assert off % 4 == 0, name
        pos += size
    assert pos == B.block_bytes(n) == 104 + 8 * n


def test_constants():
    assert (B.MAGIC, B.LAYOUT_VERSION, B.SUPPORTED_LAYOUTS) == (0xEC6A, 1, (1, 2))
    assert B.BANK_WORD_ADDR == (0x328000, 0x330000)
    assert (B.BANK_WORDS, B.BANK_BYTES) == (0x8000, 65536)
    assert (B.FLAG_COMP_ENABLE, B.FLAG_INTERP_ENABLE) == (1, 2)


# ---- CRC ----------------------------------------------------------------------------------

def test_crc32_check_value_and_zlib():
    assert B.crc32(b"123456789") == 0xCBF43926
    rng = np.random.default_rng(3)
    for size in (0, 1, 7, 1000):
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        assert B.crc32(data) == zlib.crc32(data) & 0xFFFFFFFF


# ---- pack / unpack --------------------------------------------------------------------------

@pytest.mark.parametrize("n", [16, 64, 1024])
def test_pack_unpack_round_trip(n):
    b = _block(n)
    data = B.pack(b)
    assert len(data) == B.block_bytes(n)
    assert B.check(data).valid
    u = B.unpack(data)
    assert u == b
    assert B.pack(u) == data
    assert u.table_const.dtype == np.float32 and u.table_len == n
    # bytes where the contract puts them, little-endian
    assert struct.unpack_from("<HHII", data, 0) == (0xEC6A, 1, 104 + 8 * n, 5)
    assert data[16:32] == b"SN-42" + b"\0" * 11
    assert struct.unpack_from("<f", data, 100 + 4 * n + 4)[0] == b.table_per_amp[1]
    assert struct.unpack_from("<I", data, 100 + 8 * n)[0] == zlib.crc32(data[:100 + 8 * n])


def test_floats_held_as_binary32_and_equality_sees_changes():
    b = _block()
    assert b.kt == float(np.float32(0.04905)) and b.kt != 0.04905
    assert b != dataclasses.replace(b, sequence=6)
    tc = b.table_const.copy()
    tc[3] = np.nextafter(tc[3], np.float32(1))
    assert b != dataclasses.replace(b, table_const=tc)
    with pytest.raises(ValueError):
        b.table_const[0] = 1.0  # read-only: the block is frozen


def test_sixteen_character_serial_has_no_nul():
    data = B.pack(_block(serial="ABCDEFGHIJKLMNOP"))
    assert data[16:32] == b"ABCDEFGHIJKLMNOP"
    assert B.unpack(data).serial == "ABCDEFGHIJKLMNOP"


@pytest.mark.parametrize("change, field", [
    (dict(sequence=0), "sequence"),
    (dict(sequence=0xFFFFFFFF), "sequence"),
    (dict(flags=0x40), "flags"),
    (dict(serial="X" * 17), "serial"),
    (dict(serial="MOTÖR"), "serial"),
    (dict(serial="A\0B"), "serial"),
    (dict(table_const=np.zeros(8), table_per_amp=np.zeros(8)), "table_len"),
    (dict(table_const=np.zeros(48), table_per_amp=np.zeros(48)), "table_len"),
    (dict(table_const=np.zeros(2048), table_per_amp=np.zeros(2048)), "table_len"),
    (dict(kt=float("nan")), "kt"),
    (dict(lead_s=1e39), "lead_s"),
    (dict(iqc_limit=-1.0), "iqc_limit"),
    (dict(tick_hz=0.0), "tick_hz"),
    (dict(poles=5), "poles"),
    (dict(calibrated_at=-1), "calibrated_at"),
    (dict(layout_version=2), "layout_version"),
])
def test_pack_refuses_what_would_not_be_valid(change, field):
    b = _block(**change)
    with pytest.raises(InputError) as err:
        B.pack(b)
    assert err.value.field == field


def test_construction_refuses_malformed_fields():
    with pytest.raises(InputError, match="table_per_amp"):
        _block(table_per_amp=np.zeros(32))
    with pytest.raises(InputError, match="hall_angle"):
        _block(hall_angle=(0.0,) * 5)
    with pytest.raises(InputError, match="sequence"):
        _block(sequence=1.5)


# ---- validity: every rule ------------------------------------------------------------------

def _patched(data: bytes, fmt: str, off: int, value: int, fix_crc: bool = True) -> bytes:
    buf = bytearray(data)
    struct.pack_into(fmt, buf, off, value)
    return B.with_crc(bytes(buf)) if fix_crc else bytes(buf)


def test_each_validity_rule_is_refused_with_its_status():
    good = B.pack(_block(16))
    H, C = B.STATUS_HEADER_INVALID, B.STATUS_CRC_MISMATCH
    cases = {
        "magic": (_patched(good, "<H", 0, 0x6AEC), H, "magic"),
        "layout": (_patched(good, "<H", 2, 3), H, "layout_version"),
        "table_len small": (_patched(good, "<H", 96, 8), H, "table_len"),
        "table_len large": (_patched(good + bytes(8 * 2048), "<H", 96, 2048), H, "table_len"),
        "table_len not pow2": (_patched(good + bytes(300), "<H", 96, 24), H, "table_len"),
        "block_bytes": (_patched(good, "<I", 4, 104 + 8 * 16 + 2), H, "block_bytes"),
        "sequence 0": (_patched(good, "<I", 8, 0), H, "sequence"),
        "sequence erased": (_patched(good, "<I", 8, 0xFFFFFFFF), H, "sequence"),
        "truncated block": (good[:-1], H, "truncated"),
        "truncated header": (good[:99], H, "truncated"),
        "erased bank": (b"\xff" * B.BANK_BYTES, H, "erased"),
        "crc of edited header": (_patched(good, "<I", 8, 6, fix_crc=False), C, "CRC"),
        "crc field": (good[:-4] + bytes([good[-4] ^ 1]) + good[-3:], C, "CRC"),
    }
    for name, (data, status, word) in cases.items():
        res = B.check(data)
        assert res.status == status and not res.valid, name
        assert any(word in r for r in res.reasons), (name, res.reasons)
    # every bit of the covered bytes is protected by the CRC
    for k in range(0, len(good) - 4, 37):
        flipped = bytearray(good)
        flipped[k] ^= 0x04
        assert B.check(bytes(flipped)).status in (H, C), k


def test_valid_with_erased_tail_and_warnings_only_for_reserved_and_flags():
    good = B.pack(_block(16))
    bank = good + b"\xff" * (B.BANK_BYTES - len(good))
    assert B.check(bank).valid and B.unpack(bank) == _block(16)
    res = B.check(_patched(good, "<H", 98, 1))
    assert res.valid and "reserved" in res.warnings[0]
    res = B.check(_patched(good, "<I", 12, 0x100))
    assert res.valid and "flags" in res.warnings[0]


def test_layout2_extension_warnings_say_when_the_firmware_ignores_the_mechanical_part():
    from eol_cal.firmware.contract import FLAG_MECH_COMP_ENABLE, FLAGS_MECH_NEEDS
    from eol_cal.firmware.mech_params import unused_mech

    base = _block(16)
    plain = dataclasses.replace(base, layout_version=2, mech=unused_mech(base.encoder_ppr))
    good = B.pack(plain)
    assert B.check(good).valid and B.check(good).warnings == ()
    x = B.field_offset("mech_table_len", 16, 2)  # the extension's start
    cases = {
        "mech_table_len": (_patched(good, "<H", x, 64), "mech_table_len is 64, not 128"),
        "fp_len": (_patched(good, "<H", x + 2, 300), "fp_len is 300, more than the 256"),
        "reserved2": (_patched(good, "<H", x + 6, 7), "reserved2 is 0x0007, not 0"),
    }
    for name, (data, text) in cases.items():
        res = B.check(data)
        assert res.valid and any(text in w for w in res.warnings), (name, res.warnings)
    # MECH_COMP_ENABLE with everything it needs but no fingerprint, or fp_len not the encoder's
    enabled = B.pack(dataclasses.replace(plain, flags=plain.flags | FLAGS_MECH_NEEDS | FLAG_MECH_COMP_ENABLE))
    res = B.check(enabled)
    assert res.valid and [w for w in res.warnings if "fp_dirs is 0" in w], res.warnings
    res = B.check(_patched(enabled, "<H", x + 2, base.encoder_ppr - 1))
    assert res.valid and [w for w in res.warnings if f"fp_len {base.encoder_ppr - 1} is not encoder_ppr" in w]
    # a layout-1 block has no extension to read (its bytes there are the CRC and the erased tail)
    assert B.check(B.pack(base) + b"\xff" * 64).warnings == ()


def test_golden_check_cases_agree_with_check():
    for cid, image, status in golden.check_cases(golden.golden_blocks()):
        assert B.check(image).status == status, cid
    assert {s for _, _, s in golden.check_cases(golden.golden_blocks())} == {0, 1, 2}


@pytest.mark.parametrize("data, field", [
    (b"", "block_bytes"),
    (b"\xff" * 200, "magic"),
])
def test_unpack_names_file_and_field(data, field):
    with pytest.raises(InputError) as err:
        B.unpack(data, "bank0.bin")
    assert err.value.file == "bank0.bin" and err.value.field == field


def test_unpack_refusals_after_magic():
    good = B.pack(_block(16))
    for fmt, off, value, field in (("<H", 2, 7, "layout_version"), ("<H", 96, 12, "table_len"),
                                   ("<H", 96, 32, "block_bytes")):
        with pytest.raises(InputError) as err:
            B.unpack(_patched(good, fmt, off, value, fix_crc=False), "f.bin")
        assert err.value.field == field
    bad_serial = bytearray(good)
    bad_serial[16] = 0xC3
    with pytest.raises(InputError) as err:
        B.unpack(bytes(bad_serial), "f.bin")
    assert err.value.field == "serial"


# ---- Intel HEX --------------------------------------------------------------------------------

@pytest.mark.parametrize("bank", [0, 1])
def test_intel_hex_round_trip_at_bank_address(bank):
    data = B.pack(_block(256))
    text = B.to_intel_hex(data, bank)
    ih = IntelHex()
    ih.loadhex(io.StringIO(text))
    start = 2 * B.BANK_WORD_ADDR[bank]
    assert ih.minaddr() == start and ih.maxaddr() == start + len(data) - 1
    assert ih.tobinstr(start=start, size=len(data)) == data
    assert B.intel_hex_bank(text) == (bank, data)
    assert B.from_intel_hex(text, bank) == data
    with pytest.raises(InputError):
        B.from_intel_hex(text, 1 - bank)


def test_intel_hex_refusals():
    with pytest.raises(InputError, match="bank"):
        B.to_intel_hex(b"\0\0", 2)
    with pytest.raises(InputError):
        B.to_intel_hex(b"\0" * (B.BANK_BYTES + 2), 0)
    with pytest.raises(InputError):
        B.to_intel_hex(b"\0" * 3, 0)
    with pytest.raises(InputError):
        B.intel_hex_bank(":zz\n")


# ---- generated and checked-in artefacts ----------------------------------------------------------

def test_checked_in_header_is_generated_from_layout():
    path = ROOT / "firmware_params" / "eol_param_block.h"
    assert path.read_text("utf-8") == gen_header.render_header(), \
        "stale header: run python -m eol_cal.firmware.gen_header"
    assert gen_header.main(["--check", "--out", str(path),
                            "--a2l-out", str(ROOT / "firmware_params" / "eol_param_block.a2l")]) == 0


def test_header_check_detects_staleness(tmp_path):
    out, a2l = tmp_path / "h.h", tmp_path / "b.a2l"
    paths = ["--out", str(out), "--a2l-out", str(a2l)]
    assert gen_header.main(paths) == 0
    assert gen_header.main(["--check", *paths]) == 0
    out.write_text(out.read_text().replace("UINT32_C(100)", "UINT32_C(102)", 1))
    assert gen_header.main(["--check", *paths]) == 1
    assert gen_header.main(paths) == 0
    # the A2L is checked too: a field one byte off is stale
    a2l.write_text(a2l.read_text().replace("VALUE 0x650028", "VALUE 0x650029", 1))
    assert gen_header.main(["--check", *paths]) == 1


def test_paper_fixture_is_current():
    data = (ROOT / "fixtures" / "block_paper.bin").read_bytes()
    assert B.check(data).valid
    assert data == B.pack(golden.paper_block())
    b = B.unpack(data)
    assert (b.poles, b.encoder_ppr, b.table_len) == (6, 64, 256)
    assert b.hall_angle == tuple(float(np.float32(math.radians(a))) for a in (60, 180, 120, 300, 0, 240))
