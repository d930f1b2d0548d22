"""``eol-cal ecu restore``: an earlier calibration made active again, on the ECU simulator served
over python-can-remote on 127.0.0.1 (real ISO-TP, UDS, NOR flash semantics in a file)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.ecu import protocol as P
from eol_cal.ecu.flash import NorFlash, select_active
from eol_cal.sim.remote_ecu import serve_remote
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.sim.virtual_rig import example_block
from eol_cal.firmware import block as B


@pytest.fixture
def ecu(tmp_path):
    """Start an ECU simulator on ``tmp_path/NAME.flash``; yields a function returning its bus options."""
    servers = []

    def start(name: str = "ecu") -> list[str]:
        servers.append(serve_remote(tmp_path / f"{name}.flash", config=SimConfig(serial="SIM-0001")))
        return ["-i", "remote", "-c", servers[-1].url]

    yield start
    for server in servers:
        server.close()


@pytest.fixture
def files(tmp_path):
    key = tmp_path / "key.hex"
    key.write_text(P.DEV_SECRET.hex())
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(example_block(seed=1))
    b.write_bytes(example_block(seed=2))
    return {"key": str(key), "a": a, "b": b}


def _invoke(*args: str):
    return CliRunner().invoke(cli, list(args))


def _content(data: bytes) -> dict:
    """A block's fields but the ones a re-flash changes (its sequence and CRC)."""
    d = B.unpack(data, "block").to_dict()
    for name in ("sequence", "crc32"):
        d.pop(name, None)
    return {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in d.items()}


def _active(bus: list[str], tmp_path, name: str = "active.bin") -> bytes:
    out = tmp_path / name
    res = _invoke("ecu", "read-block", *bus, "-o", str(out))
    assert res.exit_code == 0, res.output
    return out.read_bytes()


def test_restore_previous_makes_the_first_calibration_active_with_a_higher_sequence(ecu, files, tmp_path):
    bus = ecu()
    for block in (files["a"], files["b"]):
        res = _invoke("flash", str(block), *bus, "--key-file", files["key"])
        assert res.exit_code == 0, res.output
    assert _content(_active(bus, tmp_path)) == _content(files["b"].read_bytes())
    saved = tmp_path / "saved.bin"
    res = _invoke("ecu", "restore", "--bank", "previous", *bus, "--key-file", files["key"], "--save", str(saved), "--json")
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    assert report["restored_from"] == "ECU bank 0" and report["bank"] == 0 and report["verified"]
    assert report["previous"]["bank"] == 1 and report["previous"]["sequence"] == 2
    active = _active(bus, tmp_path)
    assert _content(active) == _content(files["a"].read_bytes()) != _content(files["b"].read_bytes())
    assert B.unpack(active, "ECU").sequence == 3 == report["active_after"]["sequence"]
    assert saved.read_bytes() == files["a"].read_bytes()  # the block as bank 0 held it (sequence 1)
    # the bank that is active already: nothing is written
    res = _invoke("ecu", "restore", "--bank", "0", *bus, "--key-file", files["key"])
    assert res.exit_code == 0 and "active block already" in res.output
    assert B.unpack(_active(bus, tmp_path), "ECU").sequence == 3
    # and back to B through a file, as a run directory keeps it
    res = _invoke("ecu", "restore", "--from", str(files["b"]), *bus, "--key-file", files["key"])
    assert res.exit_code == 0 and "active now, seq 4" in res.output, res.output
    assert _content(_active(bus, tmp_path)) == _content(files["b"].read_bytes())


def test_an_erased_or_damaged_bank_is_refused_and_nothing_is_written(ecu, files, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)  # where a restore keeps its copy when not told: none may be left by a refusal
    bus = ecu("one")
    res = _invoke("flash", str(files["a"]), *bus, "--key-file", files["key"])
    assert res.exit_code == 0, res.output
    res = _invoke("ecu", "restore", "--bank", "previous", *bus, "--key-file", files["key"])
    assert res.exit_code == 2 and "ECU bank 1" in res.output and "erased bank" in res.output, res.output
    # a bank holding a block whose CRC does not match (a flash cut short after the CRC, a bit flip)
    flash = NorFlash(tmp_path / "two.flash")
    flash.program(0, 0, files["a"].read_bytes())
    damaged = bytearray(example_block(seed=2, sequence=2))
    damaged[B.HEADER_BYTES + 10] ^= 0x01
    flash.program(1, 0, bytes(damaged))
    bus = ecu("two")
    res = _invoke("ecu", "restore", "--bank", "1", *bus, "--key-file", files["key"])
    assert res.exit_code == 2 and "ECU bank 1" in res.output and "CRC" in res.output, res.output
    active, _ = select_active(NorFlash(tmp_path / "two.flash"))
    assert (active.bank, active.sequence) == (0, 1)  # untouched
    res = _invoke("ecu", "restore", "--bank", "2", *bus, "--key-file", files["key"])
    assert res.exit_code == 2 and "bank" in res.output
    res = _invoke("ecu", "restore", *bus, "--key-file", files["key"])
    assert res.exit_code == 2 and "--bank" in res.output
    assert list(work.iterdir()) == []


def test_restore_without_save_keeps_the_block_in_a_file_before_the_bank_is_erased(ecu, files, tmp_path, monkeypatch):
    bus = ecu("keep")
    for block in (files["a"], files["b"]):
        assert _invoke("flash", str(block), *bus, "--key-file", files["key"]).exit_code == 0
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    res = _invoke("ecu", "restore", "--bank", "previous", *bus, "--key-file", files["key"])
    assert res.exit_code == 0, res.output
    kept = list(work.glob("ecu-bank0-*.bin"))
    assert len(kept) == 1 and kept[0].read_bytes() == files["a"].read_bytes()
    assert f"--from {kept[0].name}" in res.output
