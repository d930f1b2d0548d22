"""Processes that share a cache directory trace and compile a kept program once between them
(eol_cal.numerics.exported.one_at_a_time): the second waits for the first and reads its program and
executable; a lock path that is no regular file leaves the work unlocked, never stuck."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from eol_cal.numerics import exported

pytest.importorskip("jax")

#: one process asking for the program kept in argv[2]. "first": its trace waits, inside the build,
#: until the second process is about to ask (file argv[3]/ready), so both want it at the same time;
#: prints how many times it built the program and how many XLA compiles it ran, and the outputs
STEP = r"""
import json, pathlib, sys, time
import numpy as np
import jax, jax.numpy as jnp
from eol_cal.numerics import exported
from eol_cal.numerics.xla import start_xla

start_xla()
jax.config.update("jax_enable_compilation_cache", False)
role, directory, flags = sys.argv[1], sys.argv[2], pathlib.Path(sys.argv[3])
exported.set_cache_dir(directory)
compiles, built = [], []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, secs, **_: compiles.append(secs) if event == "/jax/core/compile/backend_compile_duration" else None)

def build():
    built.append(1)
    if role == "first":
        (flags / "building").write_text("")
        deadline = time.monotonic() + 120
        while not (flags / "ready").exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(1.0)  # the second process reaches the lock meanwhile
    return jax.jit(lambda a: (jnp.linalg.cholesky(a @ a.T + 4.0 * jnp.eye(4, dtype=a.dtype)), jnp.cos(a).sum()))

args = (np.arange(16, dtype=np.float32).reshape(4, 4) / 10.0,)
if role == "second":
    (flags / "ready").write_text("")
fn = exported.kept("t", "t-lock-1", "cholesky", build, args)
out = fn(*args)
print(json.dumps({"built": len(built), "compiles": len(compiles), "out": [np.asarray(o).tolist() for o in out]}))
"""


def _start(role: str, directory, flags) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", STEP, role, str(directory), str(flags)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONHASHSEED": "0"})


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.slow  # two processes, each importing JAX (CONTRIBUTING.md, "Fast or slow")
def test_two_processes_asking_at_once_trace_and_compile_once(tmp_path):
    kept, flags = tmp_path / "kept", tmp_path / "flags"
    kept.mkdir()
    flags.mkdir()
    first = _start("first", kept, flags)
    deadline = time.monotonic() + 300
    while not (flags / "building").exists():  # the first one is tracing: it holds the program's lock
        assert first.poll() is None and time.monotonic() < deadline, "the first process never started its trace"
        time.sleep(0.01)
    second = _start("second", kept, flags)
    a, b = _result(first), _result(second)
    # the second waited for the first's program and executable instead of tracing and compiling its own
    assert b["built"] == 0 and b["compiles"] == 0, b
    assert a["built"] == 1 and a["compiles"] >= 1
    assert a["out"] == b["out"]
    assert len(list(kept.glob("t-*.jaxexport"))) == 1 and len(list(kept.glob("t-*.xlaexec"))) == 1


def test_a_lock_path_that_is_no_regular_file_leaves_the_work_unlocked(tmp_path):
    fifo = tmp_path / "p.lock"
    os.mkfifo(fifo)
    with exported.one_at_a_time(fifo) as held:  # an open() of a FIFO would wait for a writer
        assert held is False
    (tmp_path / "d.lock").mkdir()
    with exported.one_at_a_time(tmp_path / "d.lock") as held:
        assert held is False
    with exported.one_at_a_time(tmp_path / "missing" / "x.lock") as held:
        assert held is False
    with exported.one_at_a_time(tmp_path / "ok.lock") as held:
        assert held is True
        with exported.one_at_a_time(tmp_path / "other.lock") as other:  # another program's: not waited for
            assert other is True
