"""Compiled executables kept beside the exported programs (eol_cal.numerics.exported.executable): a
new process runs the executable it reads, without lowering, and gets what the traced program gives
bit for bit, LAPACK's kernels included; only a fresh compile is written (a copy of one that JAX's
compilation cache answered lacks its kernels), and a damaged file is passed over.

Each step is a process of its own: what a process has set up (LAPACK's routines linked in by a
lowering, JAX's compilation cache) is what these checks are about."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("jax")

#: one step: a program with a Cholesky factor (LAPACK) kept in directory argv[2]; JAX's compilation
#: cache in argv[3] ("off": none); prints what ran it and its outputs
STEP = r"""
import json, sys
import numpy as np
import jax, jax.numpy as jnp
from eol_cal.numerics import exported
from eol_cal.numerics.xla import start_xla

start_xla()
mode, directory, compile_cache = sys.argv[1:4]
if compile_cache == "off":
    jax.config.update("jax_enable_compilation_cache", False)
else:
    jax.config.update("jax_compilation_cache_dir", compile_cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
exported.set_cache_dir(None if mode == "traced" else directory)

def build():
    return jax.jit(lambda a, b: (jnp.linalg.cholesky(a @ a.T + 4.0 * jnp.eye(4, dtype=a.dtype)), jnp.sin(b).sum()))

args = (np.arange(16, dtype=np.float32).reshape(4, 4) / 10.0, np.arange(5, dtype=np.float32))
fn = exported.kept("t", "t-exec-1", "cholesky", build, args)
out = fn(*args)
print(json.dumps({"ran": type(fn).__name__, "out": [np.asarray(o).tolist() for o in out]}))
"""


def _step(mode: str, directory, compile_cache) -> dict:
    res = subprocess.run([sys.executable, "-c", STEP, mode, str(directory), str(compile_cache)],
                         capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONHASHSEED": "0"})
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # four processes, each importing JAX and compiling (CONTRIBUTING.md, "Fast or slow")
def test_a_new_process_runs_the_executable_it_reads_bit_for_bit_and_only_a_fresh_compile_is_written(tmp_path):
    plain = _step("traced", tmp_path / "unused", "off")["out"]
    kept, cc = tmp_path / "kept", tmp_path / "xla"
    first = _step("kept", kept, cc)  # traced, exported, compiled fresh: the executable written
    [exe] = kept.glob("t-*.xlaexec")
    assert len(list(kept.glob("t-*.jaxexport"))) == 1
    second = _step("kept", kept, cc)  # read: no lowering, LAPACK linked in before it runs
    assert second["ran"] == "Compiled"
    assert first["out"] == plain and second["out"] == plain

    # a damaged executable is passed over and compiled again; JAX's compilation cache answers that
    # compile, and a copy of its executable would lack its kernels: not written (the damaged file stays)
    good = exe.read_bytes()
    damaged = good[:-100] + bytes([good[-100] ^ 1]) + good[-99:]
    exe.write_bytes(damaged)
    assert _step("kept", kept, cc)["out"] == plain
    assert exe.read_bytes() == damaged
