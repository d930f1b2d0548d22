"""The station's pre-flight and the ECU state in its captures, on loopback: a real pymodbus dyno
simulator and a real ISO-TP ECU simulator (python-can-remote) on 127.0.0.1.

A typo in the dyno's address or the wrong serial must stop the cycle before anything is written
to the ECU: the calibration the motor's ECU holds stays, byte for byte.
"""

from __future__ import annotations

import dataclasses
import json
import socket
import threading
import time
from pathlib import Path

from click.testing import CliRunner
import pytest

from cli.main import cli
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import ClientTiming, ecu_state, flash_block, hmac_seed_to_key
from eol_cal.firmware import block as B
from eol_cal.sim.loopback import loopback_station
from test_station_run import files, run_args, wait_stopped  # noqa: F401 - the module's fixtures

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
KEY = hmac_seed_to_key(P.DEV_SECRET)


def calibrated_block(serial: str) -> bytes:
    """A calibrated (compensating) block for ``serial``: what a motor that passed once holds."""
    blk = B.unpack(B.read_block_file(FIXTURES / "block_paper.bin"), "block_paper.bin")
    return B.pack(dataclasses.replace(blk, serial=serial))


def calibrate(st) -> None:
    bus = st.open_bus()
    try:
        flash_block(bus, calibrated_block(st.serial), seed_to_key=KEY)
    finally:
        bus.shutdown()


def closed_port() -> int:
    """A port on 127.0.0.1 that nothing listens on (bound once, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_cycle(files, st, serial: str, tmp_path: Path, *extra: str, dyno: str | None = None):  # noqa: F811
    args = run_args(files, st, serial, tmp_path / "r.sqlite", tmp_path / "reports", *extra)
    if dyno is not None:
        args[args.index("--dyno") + 1] = dyno
    t0 = time.monotonic()
    res = CliRunner().invoke(cli, args)
    return res, time.monotonic() - t0


def assert_nothing_written(rec: dict, flash_before: bytes, flash_after: bytes, *codes: str) -> None:
    assert flash_after == flash_before  # both banks, byte for byte
    assert rec["verdict"] == "error" and rec["error"]["step"] == "pre-flight"
    assert rec["kind"] == "refusal" and rec["refusal_codes"] == list(codes)  # not the motor's result
    assert [p["code"] for p in rec["preflight"]["problems"]] == [c for c in codes for _ in range(1 + (c == "wrong_serial"))]
    assert [s["step"] for s in rec["steps"]] == ["pre-flight", "report"]
    assert rec["blocks"] == [] and rec["captures"] == {}
    assert rec["ecu_active"] == {"block": "unchanged", "sequence": None, "bank": None}


@pytest.mark.slow
def test_a_typo_in_the_dyno_address_costs_no_calibration(files, tmp_path):  # noqa: F811
    from eol_cal.schemas import validator

    with loopback_station("P-0001", 3, tmp_path / "sim", source=synthetic_source) as st:
        calibrate(st)
        before = st.flash_file.read_bytes()
        res, wall = run_cycle(files, st, "P-0001", tmp_path, dyno=f"127.0.0.1:{closed_port()}")
        after = st.flash_file.read_bytes()
        assert not st.dyno.sim.enabled and st.dyno.sim.speed == 0.0
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert_nothing_written(rec, before, after, "dyno_unreachable")
    assert len(rec["reasons"]) == 1 and rec["reasons"][0].startswith("pre-flight: dyno not reachable: dyno 127.0.0.1:")
    assert rec["safe_state"].startswith("not commanded")
    # the ECU was reached and found as it is: the calibrated block, the key accepted
    ecu = rec["preflight"]["ecu"]
    assert ecu["key_accepted"] is True and ecu["state"]["serial"] == "P-0001"
    assert "COMP_ENABLE" in ecu["state"]["flags"] and ecu["state"]["sequence"] == 1
    assert rec["preflight"]["dyno"] is None
    assert wall < 60.0, wall  # a hang guard: the whole command, a dead dyno address included, at load 8
    validator("run-record").validate(rec)
    assert Path(rec["report_dir"], "report.json").exists()


def test_a_serial_that_is_not_the_ecus_is_refused_before_the_ecu_is_touched(files, tmp_path):  # noqa: F811
    with loopback_station("M-0001", 3, tmp_path / "sim", source=synthetic_source) as st:
        calibrate(st)
        before = st.flash_file.read_bytes()
        res, _ = run_cycle(files, st, "M-0007", tmp_path)
        after = st.flash_file.read_bytes()
        wait_stopped(st.dyno.sim)
        assert not st.dyno.sim.enabled and st.dyno.sim.speed == 0.0
        assert st.dyno.sim.capture_seq == 0  # the dyno never captured
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert_nothing_written(rec, before, after, "wrong_serial")
    assert rec["reasons"] == ["pre-flight: ECU serial M-0001 (F18C) is not M-0007",
                              "pre-flight: dyno's motor serial M-0001 (dut_serial) is not M-0007"]
    assert rec["safe_state"].startswith("speed 0, drive disabled")


def test_a_wrong_key_is_found_by_the_pre_flight(files, tmp_path):  # noqa: F811
    wrong = tmp_path / "wrong.hex"
    wrong.write_text("00" * 16)
    with loopback_station("K-2", 3, tmp_path / "sim", source=synthetic_source) as st:
        calibrate(st)
        before = st.flash_file.read_bytes()
        res, _ = run_cycle(files, st, "K-2", tmp_path, "--key-file", str(wrong))
        after = st.flash_file.read_bytes()
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert_nothing_written(rec, before, after, "key_refused")
    (reason,) = rec["reasons"]
    assert reason.startswith("pre-flight: security key not accepted") and "0x35" in reason
    assert rec["preflight"]["ecu"]["key_accepted"] is False


def test_a_dead_ecu_is_found_by_the_pre_flight_within_its_timeouts(files, tmp_path):  # noqa: F811
    with loopback_station("D-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        st.ecu.close()  # the ECU's bus server is gone
        res, wall = run_cycle(files, st, "D-1", tmp_path)
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert rec["error"]["step"] == "pre-flight" and rec["captures"] == {}
    assert any(r.startswith("pre-flight: ECU") for r in rec["reasons"]), rec["reasons"]
    assert rec["kind"] == "refusal" and rec["refusal_codes"] in (["ecu_silent"], ["ecu_bus"])
    assert wall < 30.0, wall


def test_the_ecu_state_read_over_uds(tmp_path):
    with loopback_station("S-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        bus = st.open_bus()
        try:
            blank = ecu_state(bus, timing=ClientTiming())
        finally:
            bus.shutdown()
        calibrate(st)
        bus = st.open_bus()
        try:
            state = ecu_state(bus, timing=ClientTiming())
        finally:
            bus.shutdown()
        active = B.check(_active(st.flash_file))
    assert blank.bank is None and blank.serial == "S-1" and blank.describe() == "no valid block"
    assert state.bank == 0 and state.sequence == 1 and state.serial == "S-1"
    assert state.crc32 == f"{active.crc_stored:08x}"
    assert state.flags == "COMP_ENABLE|INTERP_ENABLE"


def _active(flash_file: Path) -> bytes:
    from eol_cal.ecu.flash import active_block_from_file

    return active_block_from_file(flash_file)


def flash_while_acquiring(st, after_captures: int = 1):
    """A capture source that flashes another block into the ECU (a second tester) after
    ``after_captures`` dyno captures: the ECU state changes during the acquisition."""
    count = {"n": 0}
    done = threading.Event()

    def source(req):
        count["n"] += 1
        if count["n"] == after_captures:
            calibrate(st)
            done.set()
        return synthetic_source(req)

    return source, done


@pytest.mark.slow
def test_the_ecu_state_changing_during_the_calibration_capture_ends_the_cycle(files, tmp_path):  # noqa: F811
    with loopback_station("C-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        st.dyno.sim.source, flashed = flash_while_acquiring(st, after_captures=2)
        res, _ = run_cycle(files, st, "C-1", tmp_path)
        wait_stopped(st.dyno.sim)
        assert not st.dyno.sim.enabled and st.dyno.sim.speed == 0.0
    assert flashed.is_set()
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    (prep,) = rec["blocks"]
    assert rec["error"]["step"] == "acquire" and rec["fit"] is None and prep["role"] == "prepare"
    assert "changed during the before acquisition" in rec["reasons"][0]
    cap = rec["captures"]["before"]  # kept, with both states, for whoever looks into it
    assert cap["ecu_before"]["sequence"] == prep["sequence"] == 1
    assert cap["ecu_before"]["flags"] == prep["flags"]
    assert cap["ecu_after"]["sequence"] == 2 and "COMP_ENABLE" in cap["ecu_after"]["flags"]
    # the same capture is refused by `eol-cal fit`, whatever is allowed
    out = tmp_path / "fit.json"
    res = CliRunner().invoke(cli, ["fit", cap["path"], "-o", str(out), "--allow-untraced", "--allow-compensated"])
    assert res.exit_code == 2 and not out.exists()
    (line,) = res.stderr.strip().splitlines()
    assert cap["path"] in line and "changed during the acquisition" in line


def acquire_args(st, out: Path, *extra: str) -> list[str]:
    return ["acquire", "--dyno", st.dyno_address, "--profile", "eol-default", "-o", str(out), "--json", *extra]


SHORT = """
name = "short"
[[segment]]
speed_rpm = 120.0
iq = 65.0
seconds = 0.5

[[segment]]
speed_rpm = -120.0
iq = -65.0
seconds = 0.5
"""


@pytest.mark.slow
def test_acquire_records_the_ecu_state_and_fit_refuses_what_it_must(tmp_path):
    profile = tmp_path / "short.toml"
    profile.write_text(SHORT)
    runner = CliRunner()
    with loopback_station("A-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        bus = ["-i", "remote", "-c", st.can_channel]
        # untraced: no CAN options, no record of the ECU state
        plain = tmp_path / "plain.mf4"
        res = runner.invoke(cli, acquire_args(st, plain, "--profile", str(profile)))
        assert res.exit_code == 0, res.output
        assert json.loads(res.stdout)["ecu"] is None
        # traced, under compensation: the ECU holds a calibrated block
        calibrate(st)
        comp = tmp_path / "comp.csv"
        res = runner.invoke(cli, acquire_args(st, comp, "--profile", str(profile), *bus))
        assert res.exit_code == 0, res.output
        ecu = json.loads(res.stdout)["ecu"]
        # the ECU changes during the acquisition
        st.dyno.sim.source, flashed = flash_while_acquiring(st, after_captures=1)
        changed = tmp_path / "changed.mf4"
        res = runner.invoke(cli, acquire_args(st, changed, "--profile", str(profile), *bus))
        assert res.exit_code == 0 and flashed.is_set(), res.output
    assert ecu["ecu_before"] == ecu["ecu_after"] and ecu["ecu_before"]["serial"] == "A-1"
    assert ecu["ecu_before"]["flags"] == "COMP_ENABLE|INTERP_ENABLE" and ecu["ecu_before"]["sequence"] == 1
    out = tmp_path / "fit.json"
    for path, allow, why in ((plain, "--allow-untraced", "no record of the ECU state"),
                             (comp, "--allow-compensated", "taken under compensation")):
        res = runner.invoke(cli, ["fit", str(path), "-o", str(out)])
        assert res.exit_code == 2 and not out.exists(), res.output
        (line,) = res.stderr.strip().splitlines()
        assert str(path) in line and why in line, line
        # the explicit option: a warning, and the fit runs
        res = runner.invoke(cli, ["fit", str(path), "-o", str(out), "--bench", "none", allow])
        assert res.exit_code in (0, 1) and out.exists(), res.output
        assert f"warning: file {path}" in res.stderr and why in res.stderr
        out.unlink()
    res = runner.invoke(cli, ["fit", str(changed), "-o", str(out), "--allow-untraced", "--allow-compensated"])
    assert res.exit_code == 2 and "changed during the acquisition" in res.stderr and "sequence 2" in res.stderr
    # analyze: the compensated capture is measured and its ECU state reported; untraced with a
    # warning; the changed one refused
    res = runner.invoke(cli, ["analyze", str(comp), str(plain), str(changed), "--json"])
    assert res.exit_code == 2
    doc = json.loads(res.stdout)
    by_file = {r["file"].split("#")[0]: r for r in doc["captures"]}
    assert by_file[str(comp)]["ecu"] == ecu and by_file[str(plain)]["ecu"] is None
    assert [e["file"] for e in doc["errors"]] == [str(changed)]
    assert f"warning: file {plain}" in res.stderr and f"warning: file {comp}" not in res.stderr
    from eol_cal.schemas import validator

    validator("analyze").validate(doc)


def test_the_report_shows_what_the_ecu_ran_before_the_run_and_during_each_capture():
    from eol_cal.sim.run_records import make_record

    from eol_cal.capture.ecu_state import EcuState
    from eol_cal.report.motor_page import ecu_states
    from eol_cal.records.record import EcuFound, PreflightResult

    ran = EcuState(0, 1, "0badcafe", "INTERP_ENABLE", "R-1")
    rec = make_record("R-1", error_step="fit")  # ended after the calibration capture
    cap = dataclasses.replace(rec.captures["before"], ecu_before=ran, ecu_after=ran)
    rec = dataclasses.replace(rec, captures={"before": cap}, preflight=PreflightResult(
        None, EcuFound(EcuState(1, 4, "12345678", "COMP_ENABLE|INTERP_ENABLE", "R-1"), True)))
    cols = {c["label"]: c for c in ecu_states(rec)}
    assert cols["before the run"]["crc32"] == "12345678" and cols["before the run"]["flags"] == "COMP_ENABLE|INTERP_ENABLE"
    assert cols["ran during the calibration capture"]["crc32"] == "0badcafe"
    assert "ran during the compensated capture" not in cols
