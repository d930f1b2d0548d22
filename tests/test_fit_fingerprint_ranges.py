"""The fingerprint's stretches of every window judged together (``fp_angle.every_fingerprint_range``)
against the loop it replaced, segment by segment: the same ranges, on random windows with load
steps, reversals, speed changes and segments at either end of their window; with the samples
next to each segment judged in rounds of growing spans (from 1 sample on: many rounds) and in one
(a span beyond every window)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from eol_cal.analysis.fit import fp_angle
from eol_cal.analysis.fit.fp_angle import EXTEND_TOL, every_fingerprint_range, fingerprint_ranges
from eol_cal.analysis.steady import IQ_TOL_A, IQ_TOL_REL


def _one_window(mi, ci):
    """The loop before: each segment's stops over its whole window, its nearest stop either side."""
    w = np.asarray(mi.angles[ci].omega_r, dtype=float)
    iq = np.asarray(mi.captures[ci].iq_ref(), dtype=float)
    out = []
    for k, info in enumerate(mi.info):
        if mi.capture_of_segment[k] != ci:
            continue
        ws = float(np.median(w[info.start:info.stop]))
        bad = ~((np.sign(w) == np.sign(ws)) & (np.abs(w - ws) <= EXTEND_TOL * abs(ws)))
        bad |= np.abs(iq - info.i_qo) > max(IQ_TOL_A, IQ_TOL_REL * abs(info.i_qo))
        before, after = np.flatnonzero(bad[:info.start]), np.flatnonzero(bad[info.stop:])
        a = int(before[-1]) + 1 if len(before) else 0
        b = info.stop + int(after[0]) if len(after) else len(w)
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _motor(rng):
    """Windows of piecewise speed and load (random levels, signs and lengths) and segments inside."""
    angles, captures, info, owner = [], [], [], []
    for ci in range(int(rng.integers(1, 5))):
        n = int(rng.integers(50, 3000))
        cuts = np.sort(rng.choice(np.arange(1, n), size=int(rng.integers(0, 6)), replace=False))
        levels = rng.choice([-200.0, -100.0, 100.0, 105.0, 200.0], size=len(cuts) + 1)
        loads = rng.choice([0.0, 20.0, 20.2, 65.0], size=len(cuts) + 1)
        w = np.repeat(levels, np.diff(np.concatenate(([0], cuts, [n])))) * (1 + rng.normal(0, 0.03, n))
        iq = np.repeat(loads, np.diff(np.concatenate(([0], cuts, [n]))))
        angles.append(SimpleNamespace(omega_r=w))
        captures.append(SimpleNamespace(iq_ref=lambda iq=iq: iq))
        starts = np.sort(rng.choice(np.arange(0, n - 1), size=int(rng.integers(1, 4)), replace=False))
        for j, a in enumerate(starts):
            stop = int(starts[j + 1]) if j + 1 < len(starts) else n
            b = int(rng.integers(a + 1, stop + 1))
            info.append(SimpleNamespace(start=int(a), stop=b, i_qo=float(iq[a])))
            owner.append(ci)
    return SimpleNamespace(angles=angles, captures=captures, info=info, capture_of_segment=owner)


@pytest.mark.parametrize("first_span", [1, 7, fp_angle.FIRST_SPAN, 1 << 20])
@pytest.mark.parametrize("seed", range(4))
def test_every_windows_stretches_in_one_pass_are_the_segment_by_segment_ones(seed, first_span, monkeypatch):
    monkeypatch.setattr(fp_angle, "FIRST_SPAN", first_span)
    rng = np.random.default_rng(seed)
    for _ in range(50):
        mi = _motor(rng)
        want = [_one_window(mi, ci) for ci in range(len(mi.angles))]
        assert every_fingerprint_range(mi) == want
        assert [fingerprint_ranges(mi, ci) for ci in range(len(mi.angles))] == want
