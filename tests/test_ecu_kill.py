"""A dead ECU link and SIGINT/SIGTERM at each flashing step, with real processes.

The ECU simulator runs as ``eol-cal ecu-sim`` (python-can-remote on 127.0.0.1) and kills itself
(SIGKILL) when the request of a step arrives; ``eol-cal flash`` runs as its own process. The
invariants: the flash ends within the documented bound with exit 2 and one error line naming
the step, the old block's bank is untouched, and the ECU boots the old block, or the new one
only once it was complete and checked (its CRC written after the read-back).
"""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import ClientTiming, EcuError, flash_block, hmac_seed_to_key
from eol_cal.ecu.flash import NorFlash, select_active
from eol_cal.ecu.sim_ecu import Faults
from eol_cal.sim.virtual_rig import FAST_CLIENT, example_block, virtual_rig

pytestmark = pytest.mark.slow  # process-level or multi-second: not in the fast loop

KEY = hmac_seed_to_key(P.DEV_SECRET)
OLD = example_block(seed=1)
NEW = example_block(seed=2)
BOUND_S = ClientTiming().dead_link_bound_s
# a process's start-up and imports, and the slack a CPU hog (load 8 on 2 cores, four trials side by
# side) adds to every wait, s: these tests guard against hangs (the code before waited for ever);
# bench/bench_faults_ecu.py measures the bound itself
START_S = 30.0


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A flash image whose bank 0 holds OLD (sequence 1), the key file and the NEW block file."""
    d = tmp_path_factory.mktemp("kill")
    with virtual_rig(d / "base.bin") as rig:
        flash_block(rig.tester, OLD, seed_to_key=KEY, timing=FAST_CLIENT)
    (d / "key.hex").write_text(P.DEV_SECRET.hex())
    (d / "new.bin").write_bytes(NEW)
    return d


def _cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli.main", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _sim(flash, *fault: str) -> tuple[subprocess.Popen, str]:
    proc = _cli("ecu-sim", "--flash-file", str(flash), "--listen", "127.0.0.1:0", "--s3-s", "1", *fault)
    url = proc.stdout.readline().strip()
    assert url.startswith("ws://127.0.0.1:"), proc.stderr.read()
    return proc, url


def _end(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _copy(base, tmp):
    path = tmp / "ecu.bin"
    path.write_bytes((base / "base.bin").read_bytes())
    return path


def _booted(path) -> int:
    """The sequence the ECU boots from this flash image (1 old, 2 new)."""
    return select_active(NorFlash(path))[0].sequence


def _one_error_line(stderr: str) -> str:
    errors = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in stderr, stderr
    return errors[0]


# (step the ECU dies at, sequence it boots afterwards): before the CRC is written the old block,
# afterwards the new one, which was read back before its CRC went out.
KILL_CASES = [("session", 1), ("security", 1), ("erase", 1), ("download", 1), ("transfer", 1),
              ("read_memory", 1), ("transfer_exit", 2), ("check", 2), ("reset", 2)]


def _kill_trial(base, tmp, step: str) -> tuple[int, float, str, int]:
    path = _copy(base, tmp)
    sim, url = _sim(path, "--die-at", step)
    try:
        t0 = time.monotonic()
        flash = _cli("flash", str(base / "new.bin"), "-i", "remote", "-c", url, "--key-file", str(base / "key.hex"))
        _, err = flash.communicate(timeout=BOUND_S + START_S + 5)
        elapsed = time.monotonic() - t0
        assert sim.wait(5) == -signal.SIGKILL  # the ECU really died at that step
    finally:
        _end(sim)
    return flash.returncode, elapsed, err, _booted(path)


def test_ecu_killed_at_each_step(base, tmp_path_factory):
    """Each step at once (the trials run side by side, each on its own flash image)."""
    old_bank = NorFlash(base / "base.bin").bank(0)
    dirs = [tmp_path_factory.mktemp(step) for step, _ in KILL_CASES]
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda c: _kill_trial(base, c[1], c[0][0]), zip(KILL_CASES, dirs, strict=True)))
    for (step, boots), d, (rc, elapsed, err, booted) in zip(KILL_CASES, dirs, results, strict=True):
        line = _one_error_line(err)
        assert rc == 2 and elapsed < BOUND_S + START_S, (step, elapsed, err)
        assert "CAN link lost" in line, line
        assert NorFlash(d / "ecu.bin").bank(0) == old_bank, f"{step}: the old block's bank was touched"
        assert booted == boots, (step, line)
        assert ("previous block stays active" in line) == (boots == 1), line


# The tester's progress line while the ECU serves that (slowed) step.
SIGNAL_CASES = [("session", "sessions"), ("security", "security access"), ("erase", "erase"),
                ("transfer", "download"), ("transfer_exit", "transfer exit (37)"),
                ("check", "check routine (31 0202)"), ("reset", "reset")]


def _signal_trial(base, tmp, step: str, shown: str, sig: signal.Signals) -> tuple[int, float, str, int]:
    path = _copy(base, tmp)
    sim, url = _sim(path, "--slow", f"{step}:1.0")
    try:
        flash = _cli("flash", str(base / "new.bin"), "-i", "remote", "-c", url, "--key-file", str(base / "key.hex"))
        lines = []
        for line in flash.stderr:
            lines.append(line)
            if line.strip() == shown:
                break
        time.sleep(0.3)
        t0 = time.monotonic()
        flash.send_signal(sig)
        _, err = flash.communicate(timeout=BOUND_S + START_S + 5)
        elapsed = time.monotonic() - t0
        time.sleep(1.5)  # the slowed request ends on the ECU (a reset boots the new block)
    finally:
        _end(sim)
    return flash.returncode, elapsed, "".join(lines) + err, _booted(path)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_at_each_step(base, tmp_path_factory, sig):
    """Each step at once (the trials run side by side): exit 2, one line, within the bound."""
    def trial(case):
        return _signal_trial(base, tmp_path_factory.mktemp(case[0]), *case, sig)

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(trial, SIGNAL_CASES))
    for (step, shown), (rc, elapsed, err, booted) in zip(SIGNAL_CASES, results, strict=True):
        line = _one_error_line(err)
        assert rc == 2 and elapsed < BOUND_S + START_S, (step, elapsed, err)
        assert f"interrupted by {sig.name} during flash ({shown})" in line, line
        # Interrupted before the reset the tester erases what it wrote: the old block boots,
        # and the message says which block boots.
        assert booted == (2 if step == "reset" else 1), line
        assert ("previous block stays active" in line) == (booted == 1), line


def test_silent_ecu_ends_within_the_bound():
    """An ECU that stops answering after its 0x78 for the erase (the bus stays up: a real CAN bus)."""
    timing = dataclasses.replace(FAST_CLIENT, s3_s=1.0)
    with virtual_rig(faults=Faults(power_loss_step="erase")) as rig:
        t0 = time.monotonic()
        with pytest.raises(EcuError, match=r"erase: no response .*previous block stays active"):
            flash_block(rig.tester, NEW, seed_to_key=KEY, timing=timing)
        assert time.monotonic() - t0 < timing.dead_link_bound_s + START_S
