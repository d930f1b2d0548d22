"""The frame's own uncertainty (issue 34, item 4): with one capture window the firmware frame offset's
standard error comes from its segments' scatter, not 0 (phase_k6's interval covered 80 % of plant
motors without it)."""

from __future__ import annotations

import cmath
import math
from types import SimpleNamespace

import numpy as np
import pytest

from eol_cal.analysis.fit.fp_angle import frame_sd


def _input(window_offsets, segment_offsets, n=1000):
    """A motor input as frame_sd reads it: per window (and per segment of each) its frame part."""
    parts = [(n * len(segs) * cmath.exp(1j * o), n * len(segs)) for o, segs in zip(window_offsets, segment_offsets, strict=True)]
    seg_parts = [[(n * cmath.exp(1j * s), n) for s in segs] for segs in segment_offsets]
    total = sum(p for p, _ in parts)
    return SimpleNamespace(frame_parts=parts, frame_segment_parts=seg_parts, window_frac=None,
                           frame_offset_rad=cmath.phase(total))


def test_one_window_takes_its_segments_scatter():
    segs = np.radians([0.10, 0.05, 0.08, -0.03, -0.07, -0.09, 0.04, -0.02])
    mi = _input([float(np.angle(np.exp(1j * segs).mean()))], [list(segs)])
    d = segs - mi.frame_offset_rad
    want = math.sqrt(float((d * d).mean()) * 8 / 7 / 8)  # standard error of the mean of 8 equal parts
    assert frame_sd(mi) == pytest.approx(want, rel=1e-3)
    assert math.degrees(frame_sd(mi)) > 0.02  # the 0 it was
    # one segment: nothing to scatter
    assert frame_sd(_input([0.001], [[0.001]])) == 0.0


def test_several_windows_keep_the_windows_scatter():
    mi = _input([0.001, -0.001], [[0.01, -0.01], [0.02, -0.02]])
    assert frame_sd(mi) == pytest.approx(0.001, rel=1e-3)
