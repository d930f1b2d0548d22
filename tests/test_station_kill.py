"""``eol-cal run`` when the ECU dies or the run is signalled: it ends within the bound, exit 2,
and the record (database) and the report are written all the same (issue 16, deliverable 1).

Real processes: ``eol-cal run`` and ``eol-cal ecu-sim`` (python-can-remote on 127.0.0.1), the
dyno simulator (pymodbus on 127.0.0.1, synthetic captures) in this process.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from eol_cal.dyno import sim_dyno as ds
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import ClientTiming
from eol_cal.ecu.flash import NorFlash, active_block_from_file, select_active
from eol_cal.records.query import query_records

pytestmark = pytest.mark.slow  # process-level or multi-second: not in the fast loop

BOUND_S = ClientTiming().dead_link_bound_s
# process start, imports, the JAX warm-up the run waits for on its way out, and the slack a CPU hog
# (load 8 on 2 cores) adds, s: a hang guard (bench/bench_faults_ecu.py measures the times)
START_S = 30.0
LIMITS = """
default_variant = "TEST"
[variant.TEST]
max_k6 = 0.0025
max_pp_before_pct = 25.0
max_pp_after_pct = 2.0
min_improvement_pct = 50.0
min_r2 = 0.3
max_rms_nm = 0.1
max_ci_k6_rel = 0.05
max_ci_phase_k6_deg = 3.0
max_ci_c6_nm = 0.01
max_hall_deviation_deg = 3.0
"""


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli.main", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.fixture
def station(tmp_path):
    """An ECU simulator process and a dyno simulator; yields a function that starts ``eol-cal run``."""
    yield from _station(tmp_path, realtime=False)


@pytest.fixture
def station_realtime(tmp_path):
    """As :func:`station`, with the dyno simulator in real time (a capture takes its physical
    time), so the steps after a capture have a window a signal can be aimed at on any machine."""
    yield from _station(tmp_path, realtime=True)


def _station(tmp_path: Path, realtime: bool):
    (tmp_path / "limits.toml").write_text(LIMITS)
    (tmp_path / "key.hex").write_text(P.DEV_SECRET.hex())
    flash = tmp_path / "ecu.flash"
    procs = []

    def start(*ecu_fault: str) -> tuple[subprocess.Popen, subprocess.Popen]:
        # the contract's S3 (5 s): `eol-cal run` keeps its session with TesterPresent every 2 s, so
        # an ECU with a shorter S3 drops it in any pause longer than that S3 (a loaded machine's
        # wait for the calibration capture's file before the CRC did, with S3 at 1 s)
        ecu = _cli("ecu-sim", "--flash-file", str(flash), "--listen", "127.0.0.1:0", "--serial", "K-1",
                   "--s3-s", "5", *ecu_fault)
        procs.append(ecu)
        url = ecu.stdout.readline().strip()
        assert url.startswith("ws://"), ecu.stderr.read()
        run = _cli("run", "--dyno", f"127.0.0.1:{dyno.port}", "-i", "remote", "-c", url,
                   "--limits", str(tmp_path / "limits.toml"), "--db", str(tmp_path / "db.sqlite"),
                   "--serial", "K-1", "--key-file", str(tmp_path / "key.hex"),
                   "--report-dir", str(tmp_path / "reports"), "--spool-dir", str(tmp_path / "spool"), "--json",
                   "--log-file", str(tmp_path / "run.log"),
                   # the analytic source's torque path is a rigid coupling: the bench file that is its own
                   "--bench", "none")
        procs.append(run)
        return ecu, run

    sim = ds.DynoSim(synthetic_source, serial="K-1", realtime=realtime)
    with ds.DynoSimThread(sim, "127.0.0.1", 0) as dyno:
        try:
            yield start, tmp_path, sim
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait(5)


def _wait_for_erase(tmp_path, run: subprocess.Popen) -> None:
    """Until the run's exchange log shows its first erase request (the prepare flash's), however
    long a loaded machine takes to get there; the run ending first fails the test."""
    log = tmp_path / "run.log"
    while not (log.exists() and "(EraseMemory)" in log.read_text(errors="replace")):
        assert run.poll() is None, f"the run ended (exit {run.returncode}) before its first erase"
        time.sleep(0.05)


def _recorded(tmp_path, step: str, message: str) -> dict:
    recs = [r.to_json() for r in query_records(tmp_path / "db.sqlite")]
    assert [r["verdict"] for r in recs] == ["error"]
    rec = recs[0]
    # killed before anything was written: a refusal; from the prepare step on: the motor's run
    assert rec["kind"] == ("refusal" if step == "pre-flight" else "production")
    assert rec["error"]["step"] == step and message in rec["error"]["message"], rec["error"]
    assert list((tmp_path / "reports").rglob("report.json")), "no report written"
    return rec


# (the ECU dies at, the cycle's step then, what the ECU boots afterwards per the record): the
# pre-flight's seed/key are the first two security requests, the prepare flash's the next two;
# before the prepare block's CRC nothing was written; at its check routine the uncompensated
# block is complete and checked.
PREPARE_KILLS = [("security", "pre-flight", {"block": "unchanged", "sequence": None, "bank": None}),
                 ("security:3", "prepare ECU", {"block": "unchanged", "sequence": None, "bank": None}),
                 ("erase", "prepare ECU", {"block": "unchanged", "sequence": None, "bank": None}),
                 ("check", "prepare ECU", {"block": "uncompensated", "sequence": 1, "bank": 0})]


@pytest.mark.parametrize("step,cycle_step,boots", PREPARE_KILLS, ids=[s for s, _, _ in PREPARE_KILLS])
def test_run_when_the_ecu_dies_during_the_prepare_flash(station, step, cycle_step, boots):
    start, tmp_path, dyno = station
    ecu, run = start("--die-at", step)
    t0 = time.monotonic()
    _, err = run.communicate(timeout=BOUND_S + START_S + 10)
    assert run.returncode == 2 and time.monotonic() - t0 < BOUND_S + START_S, err
    assert ecu.wait(5) == -signal.SIGKILL
    rec = _recorded(tmp_path, cycle_step, "CAN link lost")
    active = active_block_from_file(tmp_path / "ecu.flash")
    assert rec["ecu_active"] == boots
    if boots["sequence"] is not None:  # the prepare block is complete: archived as it went into the bank
        (prep,) = rec["blocks"]
        assert Path(prep["path"]).read_bytes() == active and not prep["confirmed"]
    assert not dyno.enabled and dyno.speed == 0.0
    assert (active is None) == (boots["sequence"] is None)


def test_run_when_the_ecu_dies_after_the_calibrated_block_is_complete(station):
    """Killed at the calibrated flash's transfer exit: the block is complete and checked, the
    record says the ECU boots it at its next reset."""
    start, tmp_path, dyno = station
    ecu, run = start("--die-at", "transfer_exit:2")
    _, err = run.communicate(timeout=120)
    assert run.returncode == 2, err
    rec = _recorded(tmp_path, "flash", "CAN link lost")
    assert "boots it at its next reset" in rec["error"]["message"]
    assert rec["ecu_active"] == {"block": "calibrated", "sequence": 2, "bank": 1}
    assert select_active(NorFlash(tmp_path / "ecu.flash"))[0].sequence == 2  # what the record says


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_run_signalled_during_the_flash(station, sig):
    start, tmp_path, dyno = station
    ecu, run = start("--slow", "erase:3")
    _wait_for_erase(tmp_path, run)  # the prepare flash has sent its erase
    time.sleep(1.0)  # inside the slowed erase
    t0 = time.monotonic()
    run.send_signal(sig)
    _, err = run.communicate(timeout=BOUND_S + START_S + 10)
    assert run.returncode == 2 and time.monotonic() - t0 < START_S, err
    assert "Traceback" not in err
    _recorded(tmp_path, "prepare ECU", sig.name)
    assert not dyno.enabled and dyno.speed == 0.0


def test_run_signalled_twice_still_records(station):
    """SIGTERM, then SIGINT while the run is recording its error: the record waits for neither."""
    start, tmp_path, dyno = station
    ecu, run = start("--slow", "erase:3")
    _wait_for_erase(tmp_path, run)
    time.sleep(1.0)
    run.send_signal(signal.SIGTERM)
    time.sleep(0.05)  # the run is now commanding the safe state and writing its report
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=BOUND_S + START_S + 10)
    assert run.returncode == 2 and "Traceback" not in err, err
    _recorded(tmp_path, "prepare ECU", "SIGTERM")
