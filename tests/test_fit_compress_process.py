"""The compression in a second process (issue 37 item 4, ``compress_process``): the same summaries
and fits bit for bit as in this process, its errors raised here naming the capture, no JAX in it,
a fallback to this process when it dies, and nothing left behind at exit."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from eol_cal.analysis import fit
from eol_cal.analysis.fit import batch, compress_process
from eol_cal.analysis.fit.compression import Summaries, compress_many, summarise_segments
from eol_cal.analysis.fit.synth import synthetic_segments

pytestmark = pytest.mark.skipif(not hasattr(os, "memfd_create"), reason="the compression process is Linux's")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _motors(n: int, seed: int = 21) -> list[fit.SteadySegments]:
    rng = np.random.default_rng(seed)
    return [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0))[0] for _ in range(n)]


def _same_summaries(a: Summaries, b: Summaries) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in Summaries.__dataclass_fields__)


def _same(a: fit.MotorFit, b: fit.MotorFit) -> bool:
    return (a.harmonics == b.harmonics and a.delay_s == b.delay_s and np.array_equal(a.coef, b.coef)
            and np.array_equal(a.t_avg, b.t_avg) and np.array_equal(a.cov6, b.cov6) and a.rms == b.rms)


def _started(proc: compress_process.CompressProcess) -> compress_process.CompressProcess:
    """``proc`` once its imports are done (until then its callers summarise here)."""
    deadline = time.monotonic() + 60.0
    while not proc.ready():
        assert time.monotonic() < deadline and not proc.broken, "the compression process did not start"
        time.sleep(0.01)
    return proc


@pytest.fixture(scope="module")
def child():
    proc = _started(compress_process.CompressProcess())
    yield proc
    proc.close()


def test_the_childs_summaries_are_this_process_s_bit_for_bit(child):
    """Every field of compress_many's results, with and without a current channel, across a buffer
    grown between calls."""
    spec = fit.FitSpec()
    small, large = _motors(2), _motors(6, seed=22)
    rng = np.random.default_rng(3)
    with_current = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0))[0]
                    for _ in range(2)]
    for m in with_current:
        m.kt_iq = [0.01 * np.sin(th) + 1.0 for th in m.theta]
    for motors in (small, large, with_current):
        here = compress_many(motors, spec, 4)
        there = compress_many(motors, spec, 4, child.summarise)
        for a, b in zip(here, there, strict=True):
            assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in a.__dataclass_fields__)
    assert not child.broken


def test_fits_through_the_process_equal_the_threads(monkeypatch):
    """fit_many with the process (its worker thread's blocks compressed there) and without: the same
    fits bit for bit; the threshold's default keeps a small batch in this process."""
    motors = _motors(40)
    spec = fit.FitSpec()
    threads = fit.fit_many(motors, spec, mode="vmap", chunk=8, threads=1, process=False)
    _started(compress_process.compress_process())
    used: list[int] = []
    real = compress_process.compress_process

    def counted():
        used.append(1)
        return real()

    monkeypatch.setattr(batch, "compress_process", counted)
    through = fit.fit_many(motors, spec, mode="vmap", chunk=8, threads=1, process=True)
    assert used and all(_same(a, b) for a, b in zip(threads, through, strict=True))
    fit.fit_many(motors, spec, mode="vmap", chunk=8, threads=1)  # 40 < PROCESS_MIN_MOTORS: not asked
    assert len(used) == 1
    monkeypatch.setattr(batch, "running", lambda: None)  # none running: started from PROCESS_START_MOTORS
    monkeypatch.setattr(batch, "PROCESS_MIN_MOTORS", 8)
    fit.fit_many(motors, spec, mode="vmap", chunk=8, threads=1)
    assert len(used) == 1
    monkeypatch.setattr(batch, "PROCESS_START_MOTORS", 40)
    fit.fit_many(motors, spec, mode="vmap", chunk=8, threads=1)
    assert len(used) == 2


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_an_error_in_the_child_is_raised_here_and_names_the_capture(child):
    """A capture whose compression fails (a NaN angle: no Cholesky factor) fails in the child with
    the error this process would raise; fit_many names the capture whichever thread compressed it,
    and the child goes on serving."""
    spec = fit.FitSpec()
    motors = _motors(8)
    bad = motors[5]
    bad.theta[1] = bad.theta[1].copy()
    bad.theta[1][10] = np.nan
    todo = [(bad.theta[s], bad.t[s], bad.torque[s], None, bad.pole_pairs) for s in range(bad.n_segments)]
    with pytest.raises(np.linalg.LinAlgError) as here:
        summarise_segments(todo, spec)
    with pytest.raises(np.linalg.LinAlgError) as there:
        child.summarise(todo, spec)
    assert str(there.value) == str(here.value)
    good = [(motors[0].theta[0], motors[0].t[0], motors[0].torque[0], None, motors[0].pole_pairs)]
    assert _same_summaries(child.summarise(good, spec), summarise_segments(good, spec)) and not child.broken
    sources = [f"serial-{i}" for i in range(len(motors))]
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(batch, "COMPRESS_BLOCK", 2)
    try:
        with pytest.raises(np.linalg.LinAlgError) as caught:
            fit.fit_many(motors, spec, mode="vmap", chunk=4, threads=1, process=True, sources=sources)
    finally:
        monkeypatch.undo()
    assert "in the compression of capture serial-5" in getattr(caught.value, "__notes__", [])


def test_a_starting_child_leaves_the_work_to_this_process():
    """Until the child has started, its callers summarise here rather than wait for it."""
    spec = fit.FitSpec()
    m = _motors(1)[0]
    todo = [(m.theta[s], m.t[s], m.torque[s], None, m.pole_pairs) for s in range(m.n_segments)]
    proc = compress_process.CompressProcess()
    try:
        here = proc.summarise(todo, spec)
        # summarised before the child said it had started (its imports take ~0.1 s of CPU): not waited for
        assert not proc._ready
        assert _same_summaries(here, summarise_segments(todo, spec))
    finally:
        proc.close()


def test_the_child_outlives_a_ctrl_c(child):
    """SIGINT (Ctrl-C reaches the terminal's process group) leaves the child serving."""
    spec = fit.FitSpec()
    m = _motors(1)[0]
    todo = [(m.theta[s], m.t[s], m.torque[s], None, m.pole_pairs) for s in range(m.n_segments)]
    os.kill(child.pid, signal.SIGINT)
    time.sleep(0.2)
    assert _same_summaries(child.summarise(todo, spec), summarise_segments(todo, spec)) and not child.broken


def test_a_dead_child_leaves_the_work_to_this_process():
    """The child killed: its block is summarised here, and every later one."""
    spec = fit.FitSpec()
    m = _motors(1)[0]
    todo = [(m.theta[s], m.t[s], m.torque[s], None, m.pole_pairs) for s in range(m.n_segments)]
    proc = _started(compress_process.CompressProcess())
    try:
        proc.summarise(todo, spec)
        proc._proc.kill()
        proc._proc.wait()
        assert _same_summaries(proc.summarise(todo, spec), summarise_segments(todo, spec))
        assert proc.broken
    finally:
        proc.close()


@pytest.mark.slow  # a parent process of its own with its child (CONTRIBUTING.md, "Fast or slow")
def test_the_child_imports_no_jax_and_ends_with_its_parent(tmp_path):
    """A process that fits through the child: no JAX library mapped in the child, and when the
    parent ends, no child left (its buffers are memfds: no name under /dev/shm to leak, their memory
    the kernel's to free once both processes have closed them)."""
    script = textwrap.dedent("""
        import numpy as np
        from eol_cal.analysis.fit import FitSpec, compress_process, fit_many
        from eol_cal.analysis.fit.synth import synthetic_segments
        rng = np.random.default_rng(1)
        motors = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0))[0]
                  for _ in range(40)]
        fit_many(motors, FitSpec(), mode="vmap", chunk=8, threads=1, process=True)
        pid = compress_process.running().pid
        maps = open(f"/proc/{pid}/maps").read()
        print(pid, "xla" in maps or "jaxlib" in maps)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env=dict(os.environ, PYTHONPATH=ROOT))
    assert res.returncode == 0, res.stderr
    pid, jax_mapped = res.stdout.split()
    assert jax_mapped == "False"
    assert not os.path.exists(f"/proc/{pid}")  # the parent waited for it at exit
    assert "leaked" not in res.stderr
