"""The plant's programs kept between processes (``jax.export`` in the cache directory): a station's
first motor reads them instead of tracing them, and they give what the traced programs give, bit
for bit; a change to the package's code is another key."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("jax")

from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
from eol_cal.numerics import exported
from eol_cal.plant import simulate as S
from eol_cal.plant.ecu_model import true_block
from eol_cal.plant.profile import constant
from eol_cal.plant.variation import draw_motor

FLAGS = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE


def _arrays(mode: str) -> list[np.ndarray]:
    # two motors whose ECUs identify (layout 2: the identifier's branches and loops in the program)
    specs = [draw_motor(s) for s in range(2)]
    blocks = [true_block(s, flags=FLAGS, mech=True) for s in specs] if mode == "compensated" else None
    res = S.simulate(specs, constant(200.0, 0.05, iq=40.0), mode=mode, blocks=blocks, seed=3, pre_roll_s=0.05)
    return [np.asarray(v) for r in res for v in (*r.capture.channels.values(), r.theta_r, r.theta_hat, r.theta_enc)]


def _new_process(monkeypatch) -> None:
    """What a new process has: no plant program in memory, traced or read."""
    monkeypatch.setattr(S, "_COMPILED", {})
    monkeypatch.setattr(exported, "_KEPT", {})


@pytest.mark.slow  # the plant's programs traced, exported and compiled twice over
@pytest.mark.parametrize("mode", ["raw", "compensated"])
def test_a_second_process_reads_the_plants_programs_instead_of_tracing_them_bit_for_bit(mode, tmp_path, monkeypatch):
    monkeypatch.setattr(exported, "_DIR", None)
    _new_process(monkeypatch)
    traced = _arrays(mode)
    monkeypatch.setattr(exported, "_DIR", tmp_path)
    _new_process(monkeypatch)
    first = _arrays(mode)  # traced, exported, and the program read back run
    names = sorted(p.name.rsplit("-", 1)[0] for p in tmp_path.glob("*.jaxexport"))
    assert names == ["plant-chunk", "plant-prime"]
    _new_process(monkeypatch)
    built: list[tuple] = []
    real = S._chunk_fn
    monkeypatch.setattr(S, "_chunk_fn", lambda *a: built.append(a) or real(*a))
    second = _arrays(mode)  # read back: the chunk's program is not traced
    assert built == []
    for got in (first, second):
        assert len(got) == len(traced)
        for a, b in zip(got, traced, strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


def test_the_plants_programs_are_keyed_by_the_packages_code(tmp_path, monkeypatch):
    """Another package source (an edited plant) is another entry, never the old program."""
    monkeypatch.setattr(exported, "_DIR", tmp_path)
    _new_process(monkeypatch)
    args = (np.zeros(3, np.float32),)
    calls: list[str] = []

    def build(tag: str):
        def make():
            calls.append(tag)
            import jax

            return jax.jit(lambda x: x + 1.0)
        return make

    S._kept("plant-test", ("cfg",), build("a"), args)
    _new_process(monkeypatch)
    S._kept("plant-test", ("cfg",), build("b"), args)  # read back: not built
    monkeypatch.setattr(exported, "code_digest", lambda: "another code")
    _new_process(monkeypatch)
    fn = S._kept("plant-test", ("cfg",), build("c"), args)
    assert calls == ["a", "c"] and len(list(tmp_path.glob("plant-test-*.jaxexport"))) == 2
    np.testing.assert_array_equal(np.asarray(fn(*args)), np.ones(3, np.float32))
