"""The capture windows of a joined capture (``eol-cal acquire``: one window per profile segment).

A dyno capture is several capture windows joined in one file: metadata ``segment_starts`` gives
each window's first sample time (s), written rounded to the microsecond. The shaft turned an
unknown angle between two windows and the encoder count is not carried across the gap, so any
angle must be reconstructed per window; every analysis of a capture splits it here first.
"""

from __future__ import annotations

import numpy as np

from eol_cal.capture.data import Capture
from eol_cal.firmware.estimator import quadrature_phase

#: a step in ``t`` longer than this many median sample periods starts a new window, unless the
#: encoder shows that the angle is bridged across it (:func:`_bridged`)
GAP_PERIODS = 1.5
#: a gap is bridged only when it is shorter than this fraction of the encoder's quadrature-edge
#: interval around it (so at most one edge can fall inside) and the quadrature state moved by at
#: most one step across it
BRIDGE_EDGE_FRACTION = 0.5
#: samples on each side of a gap in which the edge interval is measured
_BRIDGE_CONTEXT = 2000


def _bridged(capture: Capture, i: int) -> bool:
    """Whether the angle can be carried across the gap between samples ``i`` and ``i + 1``.

    A dropped sample or two inside a running capture is not a join: when the gap is much shorter
    than the quadrature edges' spacing and the encoder state moved at most one count, the edge
    (if any) inside it is placed at the gap's middle, an error of a fraction of one count.
    Without both encoder channels nothing can be told, and the gap is a join.
    """
    if not (capture.has("enc_a") and capture.has("enc_b")):
        return False
    lo, hi = max(0, i - _BRIDGE_CONTEXT), min(len(capture.t), i + 1 + _BRIDGE_CONTEXT)
    a, b = (np.asarray(capture[ch][lo:hi]).astype(np.int64) & 1 for ch in ("enc_a", "enc_b"))
    pos = np.asarray(quadrature_phase(a, b))  # numpy in, numpy out: the array type for the checker
    k = i - lo
    step = (int(pos[k + 1]) - int(pos[k])) % 4
    if step == 2:
        return False
    t = np.asarray(capture.t[lo:hi], dtype=float)
    changes = np.flatnonzero(np.diff(pos) != 0)
    changes = changes[changes != k]
    if len(changes) < 3:
        return False
    edge_dt = float(np.median(np.diff(t[changes])))
    return float(t[k + 1] - t[k]) < BRIDGE_EDGE_FRACTION * edge_dt


def window_spans(capture: Capture) -> list[tuple[int, int]]:
    """Half-open sample ranges of a capture's windows.

    From metadata ``segment_starts`` (s) when present, matched within half a sample period
    because the starts are written rounded (µs) and a start rounded up would otherwise put the
    previous window's last sample into the next window. Without it, a window begins after every
    step in ``t`` longer than :data:`GAP_PERIODS` median sample periods that the encoder cannot
    bridge (a dropped sample is bridged; :func:`_bridged`).

    Parameters
    ----------
    capture : Capture
        Any capture; a continuous one gives one span.

    Returns
    -------
    list of (start, stop)
        Non-empty, in time order, covering every sample.
    """
    t = np.asarray(capture.t, dtype=float)
    n = len(t)
    if n < 3:
        return [(0, n)] if n else []
    dt = np.diff(t)
    starts_meta = [float(s) for s in str(capture.metadata.get("segment_starts", "")).split(",") if s.strip()]
    if starts_meta:
        half = 0.5 * float(dt.min())
        idx = {int(np.searchsorted(t, s - half)) for s in starts_meta} | {0}
    else:
        # no step can exceed GAP_PERIODS medians while none exceeds GAP_PERIODS times the
        # shortest: the median (a partial sort, most of this function's time) only when one may
        gaps = (np.flatnonzero(dt > GAP_PERIODS * float(np.median(dt)))
                if dt.max() > GAP_PERIODS * dt.min() else np.zeros(0, np.int64))
        idx = {0} | {int(i) + 1 for i in gaps if not _bridged(capture, int(i))}
    edges = sorted(i for i in idx if i < n) + [n]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def split_windows(capture: Capture) -> list[Capture]:
    """A capture as one capture per window (:func:`window_spans`).

    A continuous capture comes back as itself (same object). Otherwise metadata is copied with
    ``segment_starts`` dropped and ``segments`` = 1, truth is copied, events are cut to each
    window's time span, and ``source`` gets ``#k`` appended (k from 1).

    Parameters
    ----------
    capture : Capture
        Any capture.

    Returns
    -------
    list of Capture
        The windows, in time order; the windows of one capture belong to one motor.
    """
    spans = window_spans(capture)
    if len(spans) <= 1:
        return [capture]
    t = capture.t
    meta = {k: v for k, v in capture.metadata.items() if k != "segment_starts"}
    meta["segments"] = 1
    out = []
    for k, (a, b) in enumerate(spans, start=1):
        events = {}
        for name, (times, levels) in capture.events.items():
            keep = (times >= t[a]) & (times <= t[b - 1])
            events[name] = (times[keep], levels[keep])
        out.append(Capture(t[a:b], {name: v[a:b] for name, v in capture.channels.items()}, dict(meta),
                           dict(capture.truth), events, source=f"{capture.source}#{k}"))
    return out
