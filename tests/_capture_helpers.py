"""Small captures for the capture tests (the analytic model, short and coarse to stay fast)."""

from __future__ import annotations

import dataclasses

import numpy as np

from eol_cal.capture.data import Capture
from eol_cal.capture.synthetic import synthetic_capture


def small_capture(**kwargs) -> Capture:
    """0.5 s at 60 rpm and 5 kHz: 1.5 electrical revolutions, 9 hall changes, 31 A rising edges."""
    opts = dict(rpm=60.0, seconds=0.5, fs=5000.0, serial="T-0001", seed=7)
    opts.update(kwargs)
    return synthetic_capture(**opts)


def with_channel(capture: Capture, name: str, values: np.ndarray | None) -> Capture:
    """A copy with one channel replaced (``None`` removes it); recorded events are dropped."""
    channels = dict(capture.channels)
    if values is None:
        channels.pop(name)
    else:
        channels[name] = values
    return dataclasses.replace(capture, channels=channels, events={})


def with_metadata(capture: Capture, **changes) -> Capture:
    """A copy with metadata keys changed (value ``None`` removes the key)."""
    meta = dict(capture.metadata)
    for key, value in changes.items():
        if value is None:
            meta.pop(key, None)
        else:
            meta[key] = value
    return dataclasses.replace(capture, metadata=meta)


def assert_same_capture(a: Capture, b: Capture, events: bool = True) -> None:
    """Same time base, channels (values and dtype kind), metadata, truth and (optionally) events."""
    assert np.array_equal(a.t, b.t)
    assert list(a.channels) == list(b.channels)
    for name in a.channels:
        assert np.array_equal(a.channels[name], b.channels[name]), name
        assert a.channels[name].dtype.kind == b.channels[name].dtype.kind, name
    assert a.metadata == b.metadata
    assert {k: type(v) for k, v in a.metadata.items()} == {k: type(v) for k, v in b.metadata.items()}
    assert a.truth == b.truth
    assert {k: type(v) for k, v in a.truth.items()} == {k: type(v) for k, v in b.truth.items()}
    if events:
        assert set(a.events) == set(b.events)
        for name in a.events:
            assert np.array_equal(a.events[name][0], b.events[name][0]), name
            assert np.array_equal(a.events[name][1], b.events[name][1]), name
