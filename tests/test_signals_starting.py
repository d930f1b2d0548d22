"""Signals (issue 36, class 8): exit 2 from the first instruction to the last. SIGTERM or SIGHUP
while ``eol-cal run`` is starting (imports, option parsing, settings) ended it by the signal
(exit 143/129); and no flash step starts after a signal, wherever its exception went.

Real parts: the CLI as a child process (the program's own entry, ``cli.main`` as ``__main__``), a
TCP listener on 127.0.0.1 that never answers as the dyno (the run stays in its start), the ECU
simulator on a python-can virtual bus.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from eol_cal.infra import interrupts
from eol_cal.ecu.client import flash_block, hmac_seed_to_key
from eol_cal.ecu import protocol as P
from eol_cal.errors import Interrupted
from eol_cal.sim.fuzz.scenarios import station_files

from eol_cal.sim.virtual_rig import example_block, virtual_rig

ROOT = Path(__file__).resolve().parents[1]
# the child says "go" once the interpreter and the cli package are up, then runs the program as
# `eol-cal` does; what follows "go" is eol-cal's start (cli.main's imports, the options, the settings)
CHILD = ("import os, runpy, sys, cli; os.write(1, b'go\\n'); sys.argv = ['eol-cal', *sys.argv[1:]]; "
         "runpy.run_module('cli.main', run_name='__main__')")


@pytest.fixture
def silent_dyno():
    """A TCP port on 127.0.0.1 that takes connections and never answers (a dyno that hangs)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(16)
        yield f"127.0.0.1:{s.getsockname()[1]}"


@pytest.mark.slow  # child processes, a second each
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
@pytest.mark.parametrize("after_s", [0.02, 0.1, 0.25, 0.5])
def test_a_signal_while_run_starts_is_exit_2(tmp_path, silent_dyno, sig, after_s):
    for name, data in station_files().items():
        (tmp_path / name).write_bytes(data)
    station = (tmp_path / "station.toml").read_text().replace('"127.0.0.1:1"', f'"{silent_dyno}"')
    (tmp_path / "station.toml").write_text(station)
    env = {k: v for k, v in os.environ.items() if not k.startswith("EOL_CAL_") or k == "EOL_CAL_JAX_CACHE"}
    env["PYTHONPATH"] = str(ROOT)
    child = subprocess.Popen([sys.executable, "-c", CHILD, "run", "--station", str(tmp_path / "station.toml"),
                              "--serial", "M-1"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert child.stdout is not None and child.stdout.readline() == b"go\n"
    time.sleep(after_s)
    child.send_signal(sig)
    try:
        out, err = child.communicate(timeout=120)  # a hang guard: the watchdog ends a stuck run within 10 s
    finally:
        child.kill()
    assert child.returncode == 2, (child.returncode, err.decode()[-2000:])
    text = err.decode()
    # one line: refused while starting, or the run's own (the dyno sent to its safe state, recorded)
    assert "Traceback" not in text and text.strip().splitlines()[-1].startswith(("error:", "interrupted:")), text[-2000:]


def test_no_erase_or_write_after_a_signal_whose_exception_was_swallowed(tmp_path, monkeypatch):
    monkeypatch.setattr(interrupts, "_unraisable", lambda frame: False)
    interrupts.reset()
    with contextlib.suppress(Interrupted):  # raised here and swallowed, as a finalizer prints and drops it
        interrupts.deliver("SIGTERM", None)
    with virtual_rig(tmp_path / "f.bin") as rig:
        before = (tmp_path / "f.bin").read_bytes()
        with pytest.raises(Interrupted) as exc:
            flash_block(rig.tester, example_block(seed=5), seed_to_key=hmac_seed_to_key(P.DEV_SECRET))
        after = (tmp_path / "f.bin").read_bytes()
    interrupts.reset()
    assert after == before  # nothing erased, nothing written
    assert "erase" in str(exc.value) or "flash" in str(exc.value)


def test_a_signal_inside_importlib_is_raised_a_moment_later(monkeypatch):
    """Raised inside importlib's own code (between its import lock's acquire and the try that
    releases it) the exception left the lock held: the next import in any thread hung (run
    started, SIGTERM: its spool-flush thread and the cycle stuck for ever)."""
    namespace: dict = {}
    exec(compile("import sys\nframe = sys._getframe()", "<frozen importlib._bootstrap>", "exec"), namespace)
    again = []
    monkeypatch.setattr(interrupts, "_redeliver", again.append)
    interrupts.reset()
    interrupts.deliver("SIGTERM", namespace["frame"])  # no exception here
    assert again == [signal.SIGTERM] and interrupts.received() == "SIGTERM"
    with pytest.raises(Interrupted):
        interrupts.deliver("SIGTERM", sys._getframe())  # anywhere else: at once
    interrupts.reset()


def test_a_signal_while_a_class_is_made_is_raised_after_it(monkeypatch):
    """Raised inside a ``__set_name__`` (a dataclass's field while ``run`` imported the executor's
    ``StepEvent``), Python 3.11 turned the exception into ``RuntimeError("Error calling __set_name__
    ...")``: the run ended with exit 1 and a traceback instead of exit 2 (CI, 2026-11-30)."""
    again = []
    monkeypatch.setattr(interrupts, "_redeliver", again.append)
    interrupts.reset()

    class Signalled:
        def __set_name__(self, owner, name):
            interrupts.deliver("SIGHUP", sys._getframe())  # the handler's frame: inside __set_name__

    class Made:  # made: nothing raised inside its __set_name__
        field = Signalled()

    assert Made.__name__ == "Made" and again == [signal.SIGHUP] and interrupts.received() == "SIGHUP"
    interrupts.reset()
