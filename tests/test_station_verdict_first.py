"""The verdict first, the record never lost (issue 24): the station shows the verdict before it
writes the report and the database, and a station killed right after the verdict leaves the
record in the spool, from where the next start (or ``eol-cal records --flush``) writes it in.

Real processes: ``eol-cal station --demo`` (its simulators in its own process) killed with
SIGKILL; the records database is a real SQLite file, held locked by this test so that the kill
lands between the verdict and the database write whatever the machine's load.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.sim.loopback import loopback_station
from eol_cal.records.query import query_records
from test_station_run import files  # noqa: F401 - the module's fixture

ROOT = Path(__file__).resolve().parents[1]
MOTOR_S = 300.0


def _reader(proc: subprocess.Popen, sink: list[str]) -> threading.Thread:
    def run() -> None:
        while True:
            chunk = os.read(proc.stdout.fileno(), 65536)
            if not chunk:
                return
            sink.append(chunk.decode("utf-8", "replace"))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def _wait_for(sink: list[str], pattern: str, timeout: float, proc: subprocess.Popen) -> re.Match:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        m = re.search(pattern, "".join(sink))
        if m:
            return m
        if proc.poll() is not None:
            break
        time.sleep(0.02)
    raise AssertionError(f"{pattern!r} not seen (exit {proc.poll()}):\n{''.join(sink)[-3000:]}")


@pytest.mark.slow  # a station process killed and run again: 21 s
def test_a_station_killed_right_after_the_verdict_loses_no_record(tmp_path):
    out = tmp_path / "session"
    out.mkdir()
    db = out / "results.sqlite"
    lock = sqlite3.connect(db, isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")  # the database write waits: the kill comes before it
    env = {k: v for k, v in os.environ.items() if not k.startswith("EOL_CAL_")}
    env.update(PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "cli.main", "station", "--demo", "--out", str(out),
                             "--operator", "dave"], cwd=tmp_path, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    sink: list[str] = []
    try:
        _reader(proc, sink)
        _wait_for(sink, r"Scan serial", 120, proc)
        proc.stdin.write(b"DEMO-0001\n")
        proc.stdin.flush()
        shown = _wait_for(sink, r"DEMO-0001: (PASS|FAIL|ERROR)", MOTOR_S, proc).group(1).lower()
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
        lock.rollback()
        lock.close()
    # killed before the record's line ("record RUN_ID -> database"; a refusal's panel names its run's first 8 digits)
    assert not re.search(r"record [0-9a-f]{32} ->", "".join(sink)) and "-> database" not in "".join(sink)
    (spooled,) = list((out / "spool").glob("*.json"))
    doc = json.loads(spooled.read_text())
    rec = doc["record"]
    assert rec["serial"] == "DEMO-0001" and rec["verdict"] == shown
    # the next start writes it into the database
    flush = subprocess.run([sys.executable, "-m", "cli.main", "records", "--db", str(db), "--flush",
                            "--spool-dir", str(out / "spool"), "--json"], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=120)
    assert flush.returncode == 0, flush.stderr
    (row,) = query_records(db)
    assert (row.run_id, row.serial, row.verdict) == (rec["run_id"], "DEMO-0001", shown)
    assert not list((out / "spool").glob("*.json"))
    # the page, drawn on the report thread or, killed before it was, rebuilt from the record: whole
    page = Path(rec["report_dir"]) / "report.html"
    assert page.read_text().rstrip().endswith("</html>") and not list(page.parent.glob(".report.html.*"))


def test_a_calibration_capture_that_cannot_be_written_stops_the_cycle_before_the_flash(files, tmp_path, monkeypatch):  # noqa: F811
    """The calibration capture is written beside the fit and the download; the flash waits for
    the file before the block's CRC, and a write that failed ends the cycle there: the CRC is
    never written, nothing calibrated counts in the ECU."""
    import eol_cal.capture as capture_io
    from test_station_preflight import run_cycle

    written = capture_io.write_capture

    def write(cap, path, *args, **kw):
        if Path(path).name == "before.mf4":
            raise OSError(28, "No space left on device")
        return written(cap, path, *args, **kw)

    monkeypatch.setattr(capture_io, "write_capture", write)
    with loopback_station("W-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        # the analytic source's torque path is a rigid coupling: the bench file that is its own
        res, _ = run_cycle(files, st, "W-1", tmp_path, "--bench", "none")
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert rec["verdict"] == "error" and rec["error"]["step"] in ("fit", "table", "flash"), rec["reasons"]
    assert "before capture was not written" in rec["reasons"][0] and "No space left" in rec["reasons"][0]
    assert [b["role"] for b in rec["blocks"]] == ["prepare"]  # the calibrated block never went in
    assert "the previous block stays active" in rec["reasons"][0]
    assert rec["ecu_active"]["block"] == "uncompensated"
