"""``--verbose`` / ``--log-file`` on the commands that talk to the ECU or the dyno, and one line
with exit 2 when a CAN bus cannot be opened."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.sim.virtual_rig import example_block
from tests.test_ecu_cli import _start_sim, _stop

PROFILE = """
name = "short"
[[segment]]
speed_rpm = 60.0
iq = 30.0
seconds = 0.4
"""
#: a log line starts with a UTC timestamp to the millisecond
STAMP = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z ", re.M)


def _files(tmp_path: Path) -> tuple[Path, Path]:
    key = tmp_path / "key.hex"
    key.write_text(P.DEV_SECRET.hex() + "\n")
    block = tmp_path / "block.bin"
    block.write_bytes(example_block(seed=4))
    return key, block


def _sent_service_ids(log: str) -> set[int]:
    """First byte of every UDS request payload udsoncan's Connection logger wrote."""
    return {int(m.group(1), 16) for m in re.finditer(r"Connection DEBUG Sending \d+ bytes : \[([0-9a-f]{2})", log)}


@pytest.mark.slow
def test_flash_log_file_holds_the_uds_exchanges(tmp_path: Path):
    key, block = _files(tmp_path)
    log = tmp_path / "flash.log"
    proc, url = _start_sim(tmp_path / "ecu.bin")
    try:
        res = CliRunner().invoke(cli, ["flash", str(block), "-i", "remote", "-c", url, "--key-file", str(key),
                                       "--log-file", str(log)])
    finally:
        _stop(proc)
    assert res.exit_code == 0, res.output
    text = log.read_text()
    assert STAMP.search(text)
    assert {0x10, 0x27, 0x22, 0x31, 0x34, 0x36, 0x37} <= _sent_service_ids(text), text[:2000]
    # positive responses come back as SID + 0x40
    assert re.search(r"Connection DEBUG Received \d+ bytes : \[74", text)
    assert "UdsClient" in text


@pytest.mark.slow
def test_ecu_info_verbose_writes_to_stderr_only(tmp_path: Path):
    proc, url = _start_sim(tmp_path / "ecu.bin")
    try:
        res = CliRunner().invoke(cli, ["ecu", "info", "-i", "remote", "-c", url, "--verbose", "--json"])
    finally:
        _stop(proc)
    assert res.exit_code == 0, res.output
    assert 0x22 in _sent_service_ids(res.stderr)
    assert '"serial"' in res.stdout and "Sending" not in res.stdout


def test_acquire_log_file_holds_the_modbus_exchanges(tmp_path: Path):
    profile = tmp_path / "p.toml"
    profile.write_text(PROFILE)
    log = tmp_path / "acquire.log"
    with DynoSimThread(DynoSim(synthetic_source, serial="M-LOG")) as th:
        res = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{th.port}", "--profile", str(profile),
                                       "-o", str(tmp_path / "c.csv"), "--log-file", str(log)])
        port = th.port
    assert res.exit_code == 0, res.output
    text = log.read_text()
    lines = [ln for ln in text.splitlines() if "eol_cal.modbus" in ln]
    assert lines and all(STAMP.match(ln) for ln in lines)
    assert all(f"127.0.0.1:{port}" in ln for ln in lines)
    assert any(" FC04 addr 0 " in ln for ln in lines)  # identification block read (input registers)
    assert any(" FC16 " in ln for ln in lines)  # set points written
    assert any(re.search(r" FC03 addr 32768 \(0x8000\) count 125 \[[0-9a-f]{4} ", ln) for ln in lines)  # window


def test_acquire_log_file_names_a_refusal(tmp_path: Path):
    profile = tmp_path / "p.toml"
    profile.write_text(PROFILE.replace("60.0", "5000.0"))  # over the simulator's max speed
    log = tmp_path / "acquire.log"
    with DynoSimThread(DynoSim(synthetic_source, serial="M-LOG")) as th:
        res = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{th.port}", "--profile", str(profile),
                                       "-o", str(tmp_path / "c.csv"), "--log-file", str(log), "--retries", "0"])
    assert res.exit_code == 2, res.output
    assert re.search(r"FC16 .* -> exception 3", log.read_text())


def test_unwritable_log_file_is_one_line(tmp_path: Path):
    res = CliRunner().invoke(cli, ["ecu", "info", "-i", "virtual", "-c", "x", "--log-file", str(tmp_path / "no" / "x.log")])
    assert res.exit_code == 2
    assert res.output.count("\n") == 1 and "x.log" in res.output and "Traceback" not in res.output


def test_missing_can_driver_is_one_line_exit_2(tmp_path: Path):
    key, block = _files(tmp_path)
    for args in (["flash", str(block), "-i", "kvaser", "-c", "0", "--key-file", str(key)],
                 ["ecu", "info", "-i", "kvaser", "-c", "0"],
                 ["ecu", "info", "-i", "no_such_interface", "-c", "0"]):
        res = CliRunner().invoke(cli, args)
        assert res.exit_code == 2, (args, res.output)
        assert res.output.count("\n") == 1 and "Traceback" not in res.output, res.output
        assert "interface" in res.output and args[args.index("-i") + 1] in res.output


def test_ctrl_c_before_a_command_runs_is_one_line_exit_2(monkeypatch, capsys):
    import pytest

    import cli.main as main_module

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # e.g. while the command's heavy imports load, before its handlers are set

    monkeypatch.setattr(main_module, "cli", interrupted)
    with pytest.raises(SystemExit) as exit_info:
        main_module.main()
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "interrupted" in err and "Traceback" not in err
