"""A signal at any moment (issue 23, class 2): inside a garbage-collector callback (JAX's
``_xla_gc_callback`` printed "Exception ignored" and the run went on to flash and exit 0), and
while the main thread is stuck in a system call that C code repeats (SQLite reading a FIFO:
SIGTERM was not answered at all). Real processes, real signals; the bounds are generous (a
loaded machine), and only a hang or a lost signal could exceed them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script(tmp_path: Path, body: str) -> subprocess.Popen:
    path = tmp_path / "child.py"
    path.write_text(textwrap.dedent(body))
    return subprocess.Popen([sys.executable, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=tmp_path)


def _wait_ready(proc: subprocess.Popen) -> None:
    assert proc.stdout.readline().strip() == "ready", proc.stderr.read()


@pytest.mark.parametrize(("sig", "exit_s"), [(signal.SIGTERM, 0.0), (signal.SIGINT, 0.0), (signal.SIGTERM, 0.5)])
def test_a_signal_inside_a_gc_callback_is_not_lost(tmp_path, sig, exit_s):
    """``exit_s``: a slow exit (a loaded machine's teardown; an atexit handler here). The signal is
    sent again 0.05 s after the callback (``REDELIVER_S``); the command had raised it already and was
    ending with exit 2, its handlers put back, and the second SIGTERM met the default handler and
    killed the process (-15)."""
    proc = _script(tmp_path, """
        import atexit, gc, time
        from cli.common import handle_errors
        from eol_cal.infra import interrupts

        def slow_callback(phase, info):  # as JAX's: Python code the collector runs
            if phase == "start":
                time.sleep(0.2)

        @handle_errors
        def command():
            gc.callbacks.append(slow_callback)
            print("ready", flush=True)
            for _ in range(300):  # a minute of "fit"; almost all of it inside the callback
                gc.collect()
                interrupts.raise_if_received("the next step")  # a step that writes checks first
            print("flashed", flush=True)

        atexit.register(time.sleep, EXIT_S)
        command()
    """.replace("EXIT_S", repr(exit_s)))
    _wait_ready(proc)
    time.sleep(0.5)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, (proc.returncode, out, err)
    assert "flashed" not in out and "Exception ignored" not in err, err
    assert f"interrupted by {sig.name}" in err, err


@pytest.mark.parametrize("where", ["weakref", "generator"])
def test_a_signal_dropped_where_no_finalizer_was_seen_is_sent_again(tmp_path, where):
    """Code Python runs where it drops exceptions but that is neither a ``__del__`` nor a gc
    callback (a weakref callback, a generator the collector closes): the signal is not printed
    as "Exception ignored" and lost; it comes again and stops the command before its next step."""
    proc = _script(tmp_path, f"""
        import gc, time, weakref
        from cli.common import handle_errors
        from eol_cal.infra import interrupts

        class Thing:
            pass

        def slow(ref):  # a weakref callback: its exception is dropped
            time.sleep(0.2)

        def slow_generator():
            try:
                yield 1
            finally:  # run by the collector when the generator dies
                time.sleep(0.2)

        @handle_errors
        def command():
            print("ready", flush=True)
            keep = []
            for _ in range(300):
                if "{where}" == "weakref":
                    t = Thing()
                    keep.append(weakref.ref(t, slow))
                    del t
                else:
                    g = slow_generator()
                    next(g)
                    del g
                interrupts.raise_if_received("the next step")
            print("flashed", flush=True)

        command()
    """)
    _wait_ready(proc)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, (out, err)
    assert "flashed" not in out and "Exception ignored" not in err and "Traceback" not in err, err
    assert "interrupted by SIGTERM" in err, err


def test_a_main_thread_stuck_in_a_system_call_is_ended_by_the_watchdog(tmp_path):
    fifo = tmp_path / "records.sqlite"
    os.mkfifo(fifo)
    marker = tmp_path / "safe"
    proc = _script(tmp_path, f"""
        import sqlite3
        from cli.common import handle_errors
        from eol_cal.infra import interrupts

        interrupts.WATCHDOG_GRACE_S = 2.0

        @handle_errors
        def command():
            with interrupts.emergency(lambda: open({str(marker)!r}, "w").write("dyno safe")):
                print("ready", flush=True)
                # read-only: open() of a FIFO blocks until a writer comes; SQLite repeats it on EINTR
                sqlite3.connect("file:{fifo}?mode=ro", uri=True).execute("select 1")

        command()
    """)
    _wait_ready(proc)
    time.sleep(0.5)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)  # without the watchdog: never
    assert proc.returncode == 2, err
    assert "interrupted by SIGTERM" in err and "did not answer" in err, err
    assert marker.read_text() == "dyno safe"
    assert time.monotonic() - t0 >= 2.0  # the handler had its grace period first


@pytest.mark.slow  # a process run past the watchdog's grace: 7.5 s
def test_a_command_that_answers_in_time_is_not_touched_by_the_watchdog(tmp_path):
    proc = _script(tmp_path, """
        import time
        from cli.common import handle_errors
        from eol_cal.infra import interrupts

        # the grace is for the handler to start (a loaded machine, niced: over 1 s was seen);
        # the clean-up after it is longer still, and must not count
        interrupts.WATCHDOG_GRACE_S = 5.0

        @handle_errors
        def command():
            with interrupts.emergency(lambda: print("EMERGENCY", flush=True)):
                try:
                    print("ready", flush=True)  # inside the try: a signal right after it is cleaned up
                    time.sleep(60)
                finally:
                    time.sleep(7.0)  # a long clean-up (the dyno's safe state) after the handler ran
                    print("cleaned up", flush=True)

        command()
    """)
    _wait_ready(proc)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "cleaned up" in out and "EMERGENCY" not in out, (out, err)
