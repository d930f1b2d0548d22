"""The CLI: across processes over python-can-remote, and exit codes on the virtual bus."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.ecu import protocol as P
from eol_cal.ecu.sim_ecu import Faults
from eol_cal.sim.virtual_rig import example_block, virtual_rig
from eol_cal.firmware import block as B


@pytest.fixture
def files(tmp_path):
    key = tmp_path / "key.hex"
    key.write_text(P.DEV_SECRET.hex() + "\n")
    block = tmp_path / "block.bin"
    block.write_bytes(example_block(seed=4))
    return tmp_path, key, block


def _start_sim(flash, serial="SIM-0001"):
    proc = subprocess.Popen([sys.executable, "-m", "cli.main", "ecu-sim", "--flash-file", str(flash),
                             "--listen", "127.0.0.1:0", "--serial", serial],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = proc.stdout.readline().strip()
    assert url.startswith("ws://127.0.0.1:"), proc.stderr.read() if proc.poll() is not None else url
    return proc, url


def _stop(proc):
    proc.terminate()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


@pytest.mark.slow
def test_flash_across_processes_and_restart_sees_the_flash(files):
    tmp, key, block = files
    flash = tmp / "ecu.bin"
    runner = CliRunner()
    proc, url = _start_sim(flash)
    try:
        bus = ["-i", "remote", "-c", url]
        res = runner.invoke(cli, ["flash", str(block), *bus, "--key-file", str(key), "--json"])
        assert res.exit_code == 0, res.output
        report = json.loads(res.output)
        assert report["verified"] and report["active_after"]["sequence"] == 1 and report["bank"] == 0
        res = runner.invoke(cli, ["flash", str(tmp / "missing.bin"), *bus, "--key-file", str(key)])
        assert res.exit_code == 2 and "cannot read" in res.output
        bad = tmp / "bad.bin"
        raw = bytearray(block.read_bytes())
        raw[0] = 0
        bad.write_bytes(bytes(raw))
        res = runner.invoke(cli, ["flash", str(bad), *bus, "--key-file", str(key)])
        assert res.exit_code == 2 and "magic" in res.output
        res = runner.invoke(cli, ["flash", str(block), *bus])
        assert res.exit_code == 2 and "--key-file" in res.output
    finally:
        _stop(proc)
    proc, url = _start_sim(flash)  # a restart on the same flash file
    try:
        bus = ["-i", "remote", "-c", url]
        res = runner.invoke(cli, ["ecu", "info", *bus, "--json"])
        assert res.exit_code == 0, res.output
        info = json.loads(res.output)
        assert info["active"]["sequence"] == 1 and info["block"]["valid"] and info["block"]["serial"] == "SIM-0001"
        out = tmp / "back.bin"
        res = runner.invoke(cli, ["ecu", "read-block", *bus, "-o", str(out)])
        assert res.exit_code == 0, res.output
        assert out.read_bytes() == block.read_bytes()  # example block already has sequence 1
    finally:
        _stop(proc)


def test_exit_codes_on_the_virtual_bus(files):
    tmp, key, block = files
    runner = CliRunner()
    with virtual_rig(tmp / "f.bin") as rig:
        bus = ["-i", "virtual", "-c", rig.channel]
        res = runner.invoke(cli, ["flash", str(block), *bus, "--key-file", str(key), "--dry-run"])
        assert res.exit_code == 0 and "dry run" in res.output and rig.sim.active.sequence == 0
        res = runner.invoke(cli, ["flash", str(block), *bus, "--key-file", str(key), "--no-verify"])
        assert res.exit_code == 0 and "NOT read back" in res.output
        rig.sim.faults = Faults(corrupt_byte=next(i for i in range(500, 2000) if block.read_bytes()[i] & 1))
        res = runner.invoke(cli, ["flash", str(block), *bus, "--key-file", str(key)])
        assert res.exit_code == 1 and "differs from the block" in res.output
        assert rig.sim.active.sequence == 1
        rig.sim.faults = Faults()
        other = tmp / "other.bin"
        other.write_bytes(example_block(serial="OTHER-7"))
        res = runner.invoke(cli, ["flash", str(other), *bus, "--key-file", str(key)])
        assert res.exit_code == 2 and "force" in res.output and "previous block stays active" in res.output
        hexfile = tmp / "other.hex"
        hexfile.write_text(B.to_intel_hex(other.read_bytes(), 1))
        res = runner.invoke(cli, ["flash", str(hexfile), *bus, "--key-file", str(key), "--force", "--json"])
        assert res.exit_code == 0, res.output
        assert json.loads(res.output)["sequence"] == 2
        ini = tmp / "can.ini"
        ini.write_text(f"[default]\ninterface = virtual\nchannel = {rig.channel}\n")
        res = runner.invoke(cli, ["ecu", "info", "--can-config", str(ini), "--json"])
        assert res.exit_code == 0 and json.loads(res.output)["active"]["sequence"] == 2, res.output
    res = runner.invoke(cli, ["ecu", "info", "--can-config", str(tmp / "nope.ini")])
    assert res.exit_code == 2 and "file not found" in res.output
    res = runner.invoke(cli, ["flash", str(block), "-i", "udp_multicast", "-c", "x", "--key-file", str(key)])
    assert res.exit_code == 2 and "udp_multicast" in res.output
    res = runner.invoke(cli, ["ecu-sim", "--flash-file", str(tmp / "x.bin"), "--listen", "nonsense"])
    assert res.exit_code == 2 and "HOST:PORT" in res.output


def test_the_project_fixture_block_flashes_and_reads_back(tmp_path):
    """fixtures/block_paper.bin (made by the project's block tooling) goes in and comes back equal."""
    from pathlib import Path

    from eol_cal.ecu.sim_ecu import SimConfig

    fixture = Path(__file__).resolve().parent.parent / "fixtures" / "block_paper.bin"
    key = tmp_path / "key.hex"
    key.write_text(P.DEV_SECRET.hex())
    runner = CliRunner()
    with virtual_rig(tmp_path / "f.bin", config=SimConfig(serial="EPS-0001")) as rig:
        bus = ["-i", "virtual", "-c", rig.channel]
        res = runner.invoke(cli, ["flash", str(fixture), *bus, "--key-file", str(key)])
        assert res.exit_code == 0, res.output
        out = tmp_path / "back.bin"
        res = runner.invoke(cli, ["ecu", "read-block", *bus, "-o", str(out)])
        assert res.exit_code == 0, res.output
    assert B.unpack(out.read_bytes()) == B.unpack(fixture.read_bytes())  # sequence 1 on a fresh ECU
