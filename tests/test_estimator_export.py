"""The firmware estimator's scan kept between processes (eol_cal.numerics.exported): read back instead
of traced, bit for bit the traced program's figures, and every damaged or foreign entry passed over."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from eol_cal.firmware import estimator as est
from eol_cal.numerics import exported
from eol_cal.firmware.kinematics import draw_sensor_errors, encoder_hall_signals

TICK_HZ = 20000.0


@pytest.fixture
def signals():
    err = draw_sensor_errors(np.random.default_rng(4), 64)
    t = np.arange(2500) / TICK_HZ
    return encoder_hall_signals(np.mod(0.4 + 4 * math.pi * t, 2 * math.pi), 6, 64, err)  # 120 rpm


@pytest.fixture
def export_dir(tmp_path, monkeypatch):
    """A fresh cache directory for this test, and a process that has read or traced nothing yet."""
    monkeypatch.setattr(exported, "_DIR", tmp_path)
    monkeypatch.setattr(exported, "_KEPT", {})
    return tmp_path


def _new_process() -> None:
    """What a new process has: no program in memory (neither read nor traced)."""
    exported._KEPT.clear()
    est._scan_chunk.cache_clear()


def _run(signals) -> est.EstimatorOut:
    a, b, h = signals
    return est.run_jax_chunked(est.EstimatorConfig.paper(), a, b, h, chunk=1024)


def _traced(signals, monkeypatch) -> est.EstimatorOut:
    with monkeypatch.context() as m:
        m.setattr(exported, "_DIR", None)
        return _run(signals)


def _same(x: est.EstimatorOut, y: est.EstimatorOut) -> None:
    for a, b in zip(x, y, strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_a_second_process_reads_the_scan_instead_of_tracing_it_bit_for_bit(signals, export_dir, monkeypatch):
    plain = _traced(signals, monkeypatch)
    _new_process()
    first = _run(signals)  # traced, exported, and the program read back used (what the next process compiles)
    assert [p.name.split("-")[1] for p in export_dir.glob("est-*.jaxexport")] == ["scan"]
    traced = est._scan_chunk(est._program_config(est.EstimatorConfig.paper()))
    assert len(exported._KEPT) == 1 and next(iter(exported._KEPT.values())) is not traced
    _new_process()
    second = _run(signals)  # read back
    assert est._scan_chunk.cache_info().misses == 0  # nothing traced
    _same(first, plain)
    _same(second, plain)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "flipped", "foreign", "empty"])
def test_a_damaged_or_foreign_entry_is_passed_over_and_written_again(signals, export_dir, monkeypatch, damage):
    plain = _traced(signals, monkeypatch)
    _new_process()
    _run(signals)
    scan = next(export_dir.glob("est-scan-*.jaxexport"))
    good = scan.read_bytes()
    if damage == "garbage":
        scan.write_bytes(b"\x00garbage" * 100)
    elif damage == "truncated":
        scan.write_bytes(good[: len(good) // 2])
    elif damage == "flipped":  # one bit of the program: the digest no longer matches
        scan.write_bytes(good[:-100] + bytes([good[-100] ^ 1]) + good[-99:])
    elif damage == "foreign":  # another program's intact entry under this name: the scan of 2 lanes
        a, b, h = signals
        est.run_jax_batch(est.EstimatorConfig.paper(), [(a, b, h), (a, b, h)], chunk=1024)
        other = next(p for p in export_dir.glob("est-scan-*.jaxexport") if p != scan)
        shutil.copyfile(other, scan)
    else:
        scan.write_bytes(b"")
    _new_process()
    _same(_run(signals), plain)
    assert est._scan_chunk.cache_info().misses == 1  # traced again
    _new_process()  # written again: the next process reads it
    _same(_run(signals), plain)
    assert est._scan_chunk.cache_info().misses == 0


def test_an_entry_is_read_only_for_its_own_key_and_arguments(tmp_path):
    import jax
    import jax.numpy as jnp

    fn = jax.jit(lambda x: x * 2)
    args = (np.arange(4, dtype=np.int32),)
    key = exported.key_text("t-1", "double")
    assert exported.save(tmp_path, "t", key, fn, args)
    assert exported.load(tmp_path, "t", key, args) is not None
    np.testing.assert_array_equal(exported.load(tmp_path, "t", key, args)(*args), [0, 2, 4, 6])
    # another shape or dtype than the entry's: not read (the key should differ too; this is the second guard)
    assert exported.load(tmp_path, "t", key, (np.arange(5, dtype=np.int32),)) is None
    assert exported.load(tmp_path, "t", key, (jnp.arange(4, dtype=jnp.float32),)) is None
    # the entry of one key copied under another's name
    other = exported.key_text("t-1", "triple")
    shutil.copyfile(exported.entry_path(tmp_path, "t", key), exported.entry_path(tmp_path, "t", other))
    assert exported.load(tmp_path, "t", other, args) is None
    # the envelope alone
    blob = exported.pack(key, b"payload")
    assert exported.unpack(blob, key) == b"payload"
    assert exported.unpack(blob, other) is None
    assert exported.unpack(blob[:-1] + b"X", key) is None
    assert exported.unpack(b"not an entry" + blob, key) is None
    assert exported.load(None, "t", key, args) is None


def test_an_oversized_entry_is_not_read(tmp_path, monkeypatch):
    import jax

    args = (np.arange(4, dtype=np.int32),)
    key = exported.key_text("t-1", "double")
    assert exported.save(tmp_path, "t", key, jax.jit(lambda x: x * 2), args)
    monkeypatch.setattr(exported, "MAX_ENTRY_BYTES", 100)
    assert exported.load(tmp_path, "t", key, args) is None


def test_a_fifo_under_an_entrys_name_is_passed_over_unread(tmp_path):
    """An open() of a FIFO waits for a writer: the entry is read through the bounded reader,
    which refuses anything but a regular file."""
    import os
    import threading

    args = (np.arange(4, dtype=np.int32),)
    key = exported.key_text("t-1", "double")
    os.mkfifo(exported.entry_path(tmp_path, "t", key))
    got: dict = {}
    reader = threading.Thread(target=lambda: got.update(fn=exported.load(tmp_path, "t", key, args)), daemon=True)
    reader.start()
    reader.join(60.0)  # milliseconds when refused; a hang guard, not a timing check
    assert not reader.is_alive() and got == {"fn": None}


def test_the_fit_cache_switch_sets_the_estimator_directory_too(tmp_path, monkeypatch):
    import jax

    from eol_cal.analysis.fit.cache import enable_compile_cache

    monkeypatch.setattr(exported, "_DIR", None)
    monkeypatch.setattr(jax.config, "update", lambda *a: None)  # the suite's own compilation cache stays
    assert enable_compile_cache(tmp_path / "c") == tmp_path / "c"
    assert exported.cache_dir() == tmp_path / "c"
    assert enable_compile_cache(None) is None and exported.cache_dir() is None
