"""The joint fit's segment compressions shared with the model check's speed bands (issue 37 item 2:
the bands are fitted on the joint fit's own segments and compressed them again, ~1.3 ms of a
refit's serial). Within :func:`shared_compression` a segment is compressed once, bit for bit the
same figures, and only for the same arrays and the same columns; a fit's whole result is the
same with and without it."""

from __future__ import annotations

import contextlib
import dataclasses
import json

import numpy as np

from eol_cal.analysis.fit import FitSpec
from eol_cal.analysis.fit import compression
from eol_cal.analysis.fit.compression import compress, shared_compression
from eol_cal.analysis.fit.synth import synthetic_segments


def _counting(monkeypatch):
    """The segments compressed from now on (each compression measures its span once: ``mech_span``)."""
    calls = []
    real = compression.mech_span

    def counted(*args, **kw):
        calls.append(args[0])
        return real(*args, **kw)

    monkeypatch.setattr(compression, "mech_span", counted)
    return calls


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))


def test_a_segment_is_compressed_once_within_the_scope_and_the_figures_are_the_same(monkeypatch):
    seg, _ = synthetic_segments(np.random.default_rng(7))
    spec = FitSpec()
    alone = compress(seg, spec)
    calls = _counting(monkeypatch)
    with shared_compression():
        first = compress(seg, spec)
        again = compress(seg, dataclasses.replace(spec, delay_s=2e-4, lack_of_fit=False))  # the bands' spec
        band = compress(dataclasses.replace(seg, theta=seg.theta[1:3], t=seg.t[1:3], torque=seg.torque[1:3],
                                            i_qo=seg.i_qo[1:3], omega_e=seg.omega_e[1:3]), spec)
        assert len(calls) == seg.n_segments  # nothing compressed twice
        other = compress(seg, dataclasses.replace(spec, drift_degree=3))  # other columns: compressed anew
        assert len(calls) == 2 * seg.n_segments
        moved = compress(dataclasses.replace(seg, theta=[th + 0.0 for th in seg.theta]), spec)  # other arrays
        assert len(calls) == 3 * seg.n_segments
    assert _same(first, alone) and _same(again, alone) and _same(moved, alone)
    assert np.array_equal(band.R, alone.R[1:3]) and np.array_equal(band.z, alone.z[1:3])
    assert not np.array_equal(other.z, np.zeros_like(other.z)) and other.R.shape[1] == alone.R.shape[1] + 1
    compress(seg, spec)
    assert len(calls) == 4 * seg.n_segments  # out of the scope: none kept


def test_a_fit_with_the_model_check_is_the_same_with_and_without_shared_compressions(monkeypatch):
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.analysis.fit.motors import FitOptions, fit_inputs
    from eol_cal.capture.synthetic import synthetic_capture

    caps = [synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=j, theta_r0=0.7 * j, serial="S1")
            for j, (rpm, iq) in enumerate([(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0)])]
    opts = FitOptions(mech=False, capture_metrics=False, batch="loop")

    def result() -> str:
        inputs = motor_inputs(caps, opts.motor, estimator_options=opts.estimator_options, mechanics=opts.mechanics)
        (r,) = fit_inputs(inputs, opts, "test").results
        assert r.model_check is not None and r.model_check["status"] != "not checked", r.model_check
        return json.dumps(r.to_json(), sort_keys=True, default=str)

    calls = _counting(monkeypatch)
    shared = result()
    n_shared = len(calls)
    monkeypatch.setattr(compression, "shared_compression", contextlib.nullcontext)
    assert result() == shared
    assert 0 < n_shared < len(calls) - n_shared  # the bands' segments were compressed once, not twice
