"""fit_many's pipeline (issue 37 item 4): the calling thread compresses beside the workers instead
of waiting for them, a chunk's solve runs while the last one's results are unpacked, and a chunk's
segment coefficients are made for all its motors at once. None of it changes a digit: the fits
equal those compressed, solved and unpacked one after another, bit for bit."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from eol_cal.analysis import fit
from eol_cal.analysis.fit import batch
from eol_cal.analysis.fit.motor_fit import segment_coefficients
from eol_cal.analysis.fit.synth import synthetic_segments


def _motors(n: int, seed: int = 11) -> list[fit.SteadySegments]:
    rng = np.random.default_rng(seed)
    return [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0))[0] for _ in range(n)]


def _same(a: fit.MotorFit, b: fit.MotorFit) -> bool:
    return (a.harmonics == b.harmonics and a.delay_s == b.delay_s and np.array_equal(a.coef, b.coef)
            and np.array_equal(a.t_avg, b.t_avg) and np.array_equal(a.cov6, b.cov6) and a.rms == b.rms)


def test_the_calling_thread_compresses_beside_a_worker(monkeypatch):
    """Every block compressed once, some of them by the calling thread (the worker held back), and
    the fits those compressed inline."""
    motors = _motors(24)
    spec = fit.FitSpec()
    inline = fit.fit_many(motors, spec, mode="vmap", chunk=4, threads=0)
    who: list[str] = []
    real = batch.compress_many

    def slow_worker(block, *args):
        who.append(threading.current_thread().name)
        if threading.current_thread() is not threading.main_thread():
            time.sleep(0.05)  # the calling thread takes the next blocks meanwhile
        return real(block, *args)

    monkeypatch.setattr(batch, "compress_many", slow_worker)
    threaded = fit.fit_many(motors, spec, mode="vmap", chunk=4, threads=1)
    assert len(who) == 6  # 24 motors, blocks of 4: each once
    assert 0 < who.count(threading.main_thread().name) < 6
    assert all(_same(a, b) for a, b in zip(inline, threaded, strict=True))


def test_an_error_in_a_block_reaches_the_caller(monkeypatch):
    """Whichever thread compressed the block (a worker's error is handed over in its future), and
    the workers stop taking blocks: fit_many returns with the error instead of hanging."""
    motors = _motors(16)
    real = batch.compress_many

    def failing(block, *args):
        if block[0] is motors[8]:
            raise RuntimeError("block 2 failed")
        return real(block, *args)

    monkeypatch.setattr(batch, "compress_many", failing)
    for threads in (0, 1, 2):
        with pytest.raises(RuntimeError, match="block 2 failed"):
            fit.fit_many(motors, fit.FitSpec(), mode="vmap", chunk=4, threads=threads)


def test_a_chunks_coefficients_are_each_motors_own():
    """The segment coefficients of a chunk's motors made together equal each motor's alone, for
    motors of different segment counts in a padded last chunk."""
    rng = np.random.default_rng(12)
    motors = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=speeds, loads_a=(20.0, 65.0))[0]
              for speeds in ((300.0, 600.0), (300.0, 450.0, 600.0), (300.0, 600.0), (200.0, 400.0, 600.0), (300.0, 600.0))]
    spec = fit.FitSpec()
    fits = fit.fit_many(motors, spec, mode="vmap", chunk=2, threads=0)
    S = max(m.n_segments for m in motors)
    for m, f in zip(motors, fits, strict=True):
        c = fit.compress(m, spec, S)
        n, q = m.n_segments, spec.n_nuis
        t_avg, coef = segment_coefficients(c.R[:n], c.z[:n], f.coef[:, q:], c.ymean[:n], q)
        assert np.array_equal(t_avg, f.t_avg) and np.array_equal(coef, f.coef)


def test_an_error_in_the_unpacking_stops_the_workers(monkeypatch):
    """The workers take no further block once fit_many leaves with an error of its own."""
    motors = _motors(32)
    fit.fit_many(motors[:2], fit.FitSpec(), mode="vmap", chunk=2, threads=0)  # compiled: no compile beside the workers
    calls: list[int] = []
    real = batch.compress_many

    def counted(block, *args):
        calls.append(1)
        time.sleep(0.05)
        return real(block, *args)

    def broken(*args, **kwargs):
        raise ValueError("unpacking failed")

    monkeypatch.setattr(batch, "compress_many", counted)
    monkeypatch.setattr(batch, "unpack", broken)
    with pytest.raises(ValueError, match="unpacking failed"):
        fit.fit_many(motors, fit.FitSpec(), mode="vmap", chunk=2, threads=1)
    assert len(calls) < 16  # of 16 blocks: the first chunks', and the one a worker held
