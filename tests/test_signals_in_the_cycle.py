"""A signal while ``eol-cal run`` fits (inside JAX) or writes its record (issue 23, class 2): every
time exit 2, the dyno in its safe state, the record kept, and nothing flashed after the signal
(the ECU still boots the block the cycle prepared it with).

Real processes: ``eol-cal run`` and ``eol-cal ecu-sim`` (python-can-remote on 127.0.0.1), the
dyno simulator in this process (tests/test_station_kill.py's fixture)."""

from __future__ import annotations

import signal
import subprocess
import time

import pytest

from test_station_kill import station, station_realtime  # noqa: F401 - the fixtures

from eol_cal.ecu.flash import active_block_from_file
from eol_cal.firmware import block as B
from eol_cal.records.query import query_records
from eol_cal.records.spool import flush_spool


def _wait_for(path_glob, tmp_path, run: subprocess.Popen) -> bool:
    """Until the run has written ``path_glob`` (True), however long that takes; False when it ended first."""
    while run.poll() is None:
        if list((tmp_path / "reports").rglob(path_glob)):
            return True
        time.sleep(0.02)
    return bool(list((tmp_path / "reports").rglob(path_glob)))


# a station process each (15-20 s, the dyno in real time); test_signals_anywhere keeps the signal
# handling in the fast loop
@pytest.mark.slow
@pytest.mark.parametrize("sig, delay_s", [(signal.SIGTERM, 0.1),
                                          (signal.SIGINT, 0.8),
                                          (signal.SIGTERM, 2.0)])
def test_a_signal_during_the_fit_flashes_nothing_after_it(station_realtime, sig, delay_s):  # noqa: F811
    start, tmp_path, dyno = station_realtime
    ecu, run = start()
    assert _wait_for("before.mf4", tmp_path, run), "the calibration capture was never written"
    # The fit (0.1-0.2 s once JAX's cache is warm, seconds on a loaded machine), the flash, then
    # the compensated capture: its lead-in and segments take their physical time (3.7 s) with the
    # dyno in real time, so every delay here lands inside the cycle however fast the machine.
    # (With the dyno faster than real time a whole cycle once ended within 2 s of before.mf4 and
    # the signal came after the run had exited with its verdict.)
    time.sleep(delay_s)
    assert run.poll() is None, f"the run ended (exit {run.returncode}) before the signal was sent"
    run.send_signal(sig)
    _, err = run.communicate(timeout=120)
    assert run.returncode == 2, err
    assert "Traceback" not in err, err
    (rec,) = query_records(tmp_path / "db.sqlite")
    assert not dyno.enabled and dyno.speed == 0.0
    if rec.verdict != "error":
        # the cycle reached its verdict before the signal (the fit, worked on while the dyno
        # turned, can end within delay_s of before.mf4, which is written beside it): the record
        # keeps the verdict, and what was flashed was flashed before the signal
        assert rec.verdict in ("pass", "fail") and rec.error is None, rec
        return
    assert sig.name in rec.error.message, rec.error
    # The step the signal stopped says when it came: a step is only begun after the signals so far
    # were looked at (eol_cal.infra.interrupts). The capture's file, which the test waits for, is written
    # beside the fit and the flash (the flash's CRC waits for it), so on a loaded machine the
    # signal can come during the flash: then its first half went out before the signal, and the
    # ECU boots either block (hog run: the CRC's commit finished, sequence 2 active).
    assert rec.error.step in ("fit", "table", "flash", "acquire compensated", "metrics"), rec.error
    active = B.unpack(active_block_from_file(tmp_path / "ecu.flash"), "active")
    # the flash never began, or the signal came before its CRC (the bank is erased again): the ECU
    # boots the prepared block
    if rec.error.step in ("fit", "table") or (rec.error.step == "flash" and _before_the_crc(rec.error.message)):
        assert active.sequence == 1 and not active.flags & B.FLAG_COMP_ENABLE, ("flashed after the signal", rec.error)


def _before_the_crc(message: str) -> bool:
    """Whether an interrupted flash's message names one of its steps before the block's CRC
    (eol_cal.ecu.sequence: "... during flash (download); ...")."""
    return any(f"during flash ({step})" in message
               for step in ("sessions", "security access", "identification", "erase", "download",
                            "read-back before the CRC (23)", "before the CRC"))


@pytest.mark.slow  # a station process: 8 s
def test_a_signal_while_the_record_is_written_keeps_the_record(station):  # noqa: F811
    start, tmp_path, dyno = station
    ecu, run = start()
    assert _wait_for("after.mf4", tmp_path, run), "the compensated capture was never written"
    time.sleep(0.3)  # the judging, the report, the record
    run.send_signal(signal.SIGTERM)
    _, err = run.communicate(timeout=120)
    assert run.returncode == 2, err
    assert "Traceback" not in err, err
    flush_spool(tmp_path / "db.sqlite", tmp_path / "spool")
    assert len(query_records(tmp_path / "db.sqlite")) == 1
    assert not dyno.enabled and dyno.speed == 0.0
