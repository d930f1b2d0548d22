"""``eol-cal block show|check|hex`` and ``eol-cal golden``: outputs and exit codes."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.firmware import block as B

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "fixtures" / "block_paper.bin"


def _run(*args: str):
    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


def test_show_json_fields_validity_crc():
    res = _run("block", "show", str(PAPER), "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["valid"] is True and doc["status"] == 0 and doc["reasons"] == []
    data = PAPER.read_bytes()
    assert doc["crc32_stored"] == doc["crc32_computed"] == f"0x{B.crc32(data[:-4]):08x}"
    blk = doc["block"]
    assert blk["serial"] == "EPS-0001" and blk["table_len"] == 256 and len(blk["table_const"]) == 256
    assert blk["magic"] == 0xEC6A and blk["block_bytes"] == len(data)


def test_show_human_and_invalid_block(tmp_path):
    res = _run("block", "show", str(PAPER))
    assert res.exit_code == 0 and "valid" in res.output and "EPS-0001" in res.output
    bad = bytearray(PAPER.read_bytes())
    bad[200] ^= 1
    path = tmp_path / "bad.bin"
    path.write_bytes(bytes(bad))
    res = _run("block", "show", str(path), "--json")
    doc = json.loads(res.output)
    assert res.exit_code == 0 and doc["status"] == 1 and "CRC mismatch" in doc["reasons"][0]
    assert doc["block"] is not None  # still decodable: the fields are shown


def test_show_json_of_a_block_holding_nan(tmp_path):
    buf = bytearray(PAPER.read_bytes())
    struct.pack_into("<f", buf, B.field_offset("kt"), float("nan"))
    struct.pack_into("<f", buf, B.field_offset("table_const") + 8, float("-inf"))
    path = tmp_path / "nan.bin"
    path.write_bytes(B.with_crc(bytes(buf)))
    res = _run("block", "show", str(path), "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["valid"] and doc["block"]["kt"] == "nan" and doc["block"]["table_const"][2] == "-inf"


def test_show_undecodable_exits_2(tmp_path):
    path = tmp_path / "erased.bin"
    path.write_bytes(b"\xff" * 4096)
    res = _run("block", "show", str(path))
    assert res.exit_code == 2 and "erased bank" in res.output


def test_check_exit_codes(tmp_path):
    assert _run("block", "check", str(PAPER)).exit_code == 0
    buf = bytearray(PAPER.read_bytes())
    struct.pack_into("<I", buf, 8, 0)
    bad = tmp_path / "seq0.bin"
    bad.write_bytes(B.with_crc(bytes(buf)))
    res = _run("block", "check", str(bad))
    assert res.exit_code == 1 and "sequence" in res.output
    res = _run("block", "check", str(bad), "--json")
    assert res.exit_code == 1 and json.loads(res.output.split("\nerror")[0])["status"] == 2
    assert _run("block", "check", str(tmp_path / "missing.bin")).exit_code == 2


def test_hex_export_round_trip_and_refusal(tmp_path):
    out = tmp_path / "b1.hex"
    res = _run("block", "hex", str(PAPER), "--bank", "1", "-o", str(out))
    assert res.exit_code == 0, res.output
    assert "0x660000" in res.output
    assert B.intel_hex_bank(out.read_text()) == (1, PAPER.read_bytes())
    # a .hex file is accepted wherever a block file is
    assert _run("block", "check", str(out)).exit_code == 0
    # a bank dump exports only the block
    dump = tmp_path / "bank.bin"
    dump.write_bytes(PAPER.read_bytes() + b"\xff" * 1000)
    _run("block", "hex", str(dump), "--bank", "0", "-o", str(tmp_path / "b0.hex"))
    assert B.intel_hex_bank((tmp_path / "b0.hex").read_text()) == (0, PAPER.read_bytes())
    bad = tmp_path / "bad.bin"
    bad.write_bytes(PAPER.read_bytes()[:-1] + b"\0")
    res = _run("block", "hex", str(bad), "--bank", "0", "-o", str(tmp_path / "x.hex"))
    assert res.exit_code == 1 and not (tmp_path / "x.hex").exists()
    assert _run("block", "hex", str(PAPER), "--bank", "2", "-o", str(out)).exit_code == 2


def test_uncompensated_block_for_the_calibration_capture(tmp_path):
    out = tmp_path / "prep.bin"
    res = CliRunner().invoke(cli, ["block", "uncompensated", "--serial", "M-0007", "-o", str(out)])
    assert res.exit_code == 0, res.output
    data = out.read_bytes()
    assert B.check(data).valid
    blk = B.unpack(data, str(out))
    # the field's estimator, no compensation, the contract's nominal hall table
    assert blk.flags == B.FLAG_INTERP_ENABLE | B.FLAGS_ESTIMATOR and blk.serial == "M-0007"  # default best
    assert blk.iqc_limit == 0.0 and not blk.table_const.any() and not blk.table_per_amp.any()
    assert (blk.poles, blk.encoder_ppr) == (6, 64)
    motor = tmp_path / "m8.toml"
    motor.write_text("poles = 8\n")
    res = CliRunner().invoke(cli, ["block", "uncompensated", "--serial", "M-8", "-o", str(out), "--motor", str(motor)])
    assert res.exit_code == 0 and B.unpack(out.read_bytes(), str(out)).poles == 8
    bad = tmp_path / "bad.bin"
    res = CliRunner().invoke(cli, ["block", "uncompensated", "--serial", "M" * 17, "-o", str(bad)])
    assert res.exit_code == 2 and "serial" in res.output and not bad.exists()


def test_one_rule_reads_every_block_file(tmp_path):
    """Intel HEX by content or by name, raw binary otherwise; the same bytes either way."""
    from eol_cal.errors import InputError

    data = PAPER.read_bytes()
    text = B.to_intel_hex(data, 1)
    as_bin_name = tmp_path / "block.bin"
    as_bin_name.write_text(text)                      # HEX content under a binary name
    assert B.read_block_file(as_bin_name) == data
    hexfile = tmp_path / "block.hex"
    hexfile.write_text(text)
    assert B.read_block_file(hexfile) == B.read_block_file(PAPER) == data
    bad = tmp_path / "bad.hex"
    bad.write_bytes(data)                              # binary under a HEX name: refused, not guessed
    with pytest.raises(InputError, match="bad.hex"):
        B.read_block_file(bad)
    with pytest.raises(InputError, match="cannot read"):
        B.read_block_file(tmp_path / "missing.bin")
    for cmd in (("block", "show"), ("block", "check")):   # every command goes through the rule
        assert _run(*cmd, str(as_bin_name)).exit_code == 0
