"""Safe blocks (issue 16, item 3): blocks the firmware's CRC check calls valid but that must not
drive the motor are refused by `block check`, `block hex`, `table` and `flash` (before any
request reaches the ECU), and a block for another motor type is refused by the ECU's own type,
read from its active block's header before the erase."""

from __future__ import annotations

import dataclasses
import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import EcuError, flash_block, hmac_seed_to_key
from eol_cal.ecu.flash import NorFlash, select_active
from eol_cal.sim.virtual_rig import FAST_CLIENT, example_block, virtual_rig
from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware.block_sanity import MotorType, sanity_problems, type_problems
from eol_cal.domain.motor_params import load_motor

ROOT = Path(__file__).resolve().parents[1]
KEY = hmac_seed_to_key(P.DEV_SECRET)
BASE = B.unpack(example_block(serial="SIM-0001"))
N = BASE.table_len


def patched(**fields) -> bytes:
    """The example block with raw fields overwritten and the CRC made right again: only a
    physical-sanity check can tell."""
    buf = bytearray(B.pack(BASE))
    for name, value in fields.items():
        kind = B.FIELDS[name]["type"]
        fmt = {"u16": "<H", "u32": "<I", "f32": "<f"}[kind]
        struct.pack_into(fmt, buf, B.field_offset(name, N), value)
    data = B.with_crc(bytes(buf))
    assert B.check(data).valid
    return data


UNSAFE = {
    "nan_k6": (dict(k6=float("nan")), "k6"),
    "nan_table": (dict(table_per_amp=float("nan")), "table_per_amp"),
    "inf_iqc_limit": (dict(iqc_limit=float("inf")), "iqc_limit"),
    "negative_iqc_limit": (dict(iqc_limit=-1.0), "iqc_limit"),
    "3e38_iqc_limit": (dict(iqc_limit=3e38), "iqc_limit"),
    "3e38_table": (dict(table_const=3e38), "table_const"),
    "-3e38_table": (dict(table_const=-3e38), "table_const"),
    "poles_0": (dict(poles=0), "poles"),
    "encoder_ppr_0": (dict(encoder_ppr=0), "encoder_ppr"),
    "tick_hz_0": (dict(tick_hz=0.0), "tick_hz"),
    "nan_hall": (dict(hall_angle=float("nan")), "hall_angle"),
}


@pytest.mark.parametrize("name", sorted(UNSAFE))
def test_unsafe_blocks_are_refused_by_check_hex_and_flash(tmp_path, name):
    fields, field = UNSAFE[name]
    path = tmp_path / f"{name}.bin"
    path.write_bytes(patched(**fields))
    runner = CliRunner()
    res = runner.invoke(cli, ["block", "check", str(path), "--json"])
    assert res.exit_code == 1, res.output
    doc = json.loads(res.stdout)
    assert doc["valid"] is True and doc["safe"] is False and any(u.startswith(field) for u in doc["unsafe"])
    assert str(path) in res.stderr and field in res.stderr
    res = runner.invoke(cli, ["block", "hex", str(path), "--bank", "0", "-o", str(tmp_path / "x.hex")])
    assert res.exit_code == 1 and "unsafe" in res.stderr and not (tmp_path / "x.hex").exists()
    # flash refuses before any session: nothing listens on this channel, nothing is needed
    res = runner.invoke(cli, ["flash", str(path), "-i", "virtual", "-c", f"nobody-{name}", "--key-file",
                              str(_key_file(tmp_path))])
    assert res.exit_code == 2, res.output
    assert str(path) in res.stderr and field in res.stderr and "unsafe parameter block" in res.stderr


def _key_file(tmp_path: Path) -> Path:
    key = tmp_path / "key.hex"
    key.write_text(P.DEV_SECRET.hex())
    return key


def test_the_good_block_is_safe_and_the_rules_name_every_problem():
    assert sanity_problems(BASE, 100.0) == []
    assert type_problems(BASE, MotorType.of_motor(load_motor())) == []
    bad = B.unpack(patched(k6=float("nan"), iqc_limit=3e38, poles=0))
    assert [f for f, _ in sanity_problems(bad, 100.0)] == ["iqc_limit", "k6", "poles"]
    # the uncompensated (measurement) block carries iqc_limit 0 and no compensation: it is safe
    from eol_cal.analysis.fit.table import uncompensated_block

    assert sanity_problems(uncompensated_block("X", load_motor()), 100.0) == []


def test_unsafe_block_reaches_no_ecu_request(tmp_path):
    """Checked before security access: the bus stays silent, the banks untouched."""
    with virtual_rig(tmp_path / "f.bin", sniff=True) as rig:
        before = [rig.sim.flash.read(bank, 0, B.BANK_BYTES) for bank in (0, 1)]
        with pytest.raises(InputError, match="iqc_limit"):
            flash_block(rig.tester, patched(iqc_limit=float("inf")), seed_to_key=KEY, timing=FAST_CLIENT)
        time.sleep(0.2)
        assert rig.sniffer.frames == [] and rig.sim.steps_seen == []
        assert [rig.sim.flash.read(bank, 0, B.BANK_BYTES) for bank in (0, 1)] == before


def test_table_refuses_an_iqc_limit_above_the_motor_rating(tmp_path):
    out = tmp_path / "b.bin"
    res = CliRunner().invoke(cli, ["table", str(ROOT / "fixtures" / "fit_paper.json"), "-o", str(out),
                                   "--iqc-limit", "1e30"])
    assert res.exit_code == 2 and "iqc_limit" in res.stderr and "fit_paper.json" in res.stderr, res.output
    assert not out.exists()
    res = CliRunner().invoke(cli, ["table", str(ROOT / "fixtures" / "fit_paper.json"), "-o", str(out),
                                   "--iqc-limit", "10"])
    assert res.exit_code == 0 and B.check(out.read_bytes()).valid


def test_an_8_pole_block_is_refused_by_a_6_pole_ecu_before_the_erase(tmp_path):
    six = example_block(serial="SIM-0001")
    eight = B.pack(dataclasses.replace(BASE, poles=8))
    flash = tmp_path / "f.bin"
    with virtual_rig(flash) as rig:
        flash_block(rig.tester, six, seed_to_key=KEY, timing=FAST_CLIENT)
        rig.sim.steps_seen.clear()
        with pytest.raises(EcuError, match="for 8 poles, the motor has 6") as info:
            flash_block(rig.tester, eight, seed_to_key=KEY, timing=FAST_CLIENT)
        assert "active block in bank 0" in str(info.value) and "previous block stays active" in str(info.value)
        assert "read_memory" in rig.sim.steps_seen and "erase" not in rig.sim.steps_seen, rig.sim.steps_seen
    active, _ = select_active(NorFlash(flash))
    assert active.bank == 0 and active.sequence == 1
    # on an ECU without an active block the station's motor decides
    with virtual_rig(tmp_path / "blank.bin") as rig:
        with pytest.raises(EcuError, match="station's motor"):
            flash_block(rig.tester, eight, seed_to_key=KEY, timing=FAST_CLIENT)
        eight_motor = dataclasses.replace(load_motor(), poles=8)
        report = flash_block(rig.tester, eight, seed_to_key=KEY, timing=FAST_CLIENT, motor=eight_motor)
        assert report.active_after is not None and report.active_after.sequence == 1


def test_motor_type_read_from_a_header():
    head = B.pack(dataclasses.replace(BASE, poles=8, encoder_ppr=128))[:B.HEADER_BYTES]
    assert MotorType.of_header(head) == MotorType(8, 128, float(np.float32(20000.0)))
