"""Ctrl-C and SIGTERM during ``eol-cal acquire``: one line, exit 2, the dyno left stopped and
disabled, no capture file (real processes: the acquire command, the dyno simulator in this one)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from eol_cal.dyno import sim_dyno as ds
from eol_cal.dyno.sim_capture import synthetic_source

pytestmark = pytest.mark.slow  # process-level or multi-second: not in the fast loop


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_acquire_signalled_mid_profile(tmp_path, sig):
    sim = ds.DynoSim(synthetic_source, serial="A-1")
    out = tmp_path / "cap.mf4"
    with ds.DynoSimThread(sim, "127.0.0.1", 0) as dyno:
        proc = subprocess.Popen([sys.executable, "-m", "cli.main", "acquire", "--dyno", f"127.0.0.1:{dyno.port}",
                                 "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # the drive turns: the profile has started (however long the process takes to start; it
        # ending first is the failure)
        while not sim.enabled and proc.poll() is None:
            time.sleep(0.02)
        assert sim.enabled, proc.communicate()[1]
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=10)
        errors = [line for line in err.splitlines() if line.startswith("error:")]
        assert proc.returncode == 2 and "Traceback" not in err, err
        assert errors == [f"error: interrupted by {sig.name} during the dyno profile; speed set to 0 and drive disabled"]
        end = time.monotonic() + 60  # a hang guard: the ramp down takes a fraction of a second
        while sim.speed != 0.0 and time.monotonic() < end:
            time.sleep(0.02)
        assert not sim.enabled and sim.speed == 0.0
    assert not out.exists()
