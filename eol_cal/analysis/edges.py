"""Edges of the digital channels: level changes, quadrature decoding onto the quarter-pitch grid,
chatter removal (steps 1 and 2 of :mod:`eol_cal.analysis.angle`)."""

from __future__ import annotations

import numpy as np

from eol_cal.numerics.median import median


def level_changes(
    t: np.ndarray, levels: np.ndarray, events: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Times and new levels of every change of a digital channel.

    Parameters
    ----------
    t : ndarray
        Sample times (s).
    levels : ndarray
        Channel levels at ``t``.
    events : (ndarray, ndarray), optional
        Exact change events (times (s), new levels). When given they are used instead of the
        samples; entries that repeat the previous level are dropped.

    Returns
    -------
    times : ndarray
        Change times (s); from samples, the midpoint of the two straddling samples (the
        unbiased estimate of a change that is uniformly distributed between them).
    new_levels : ndarray of int
        Level after each change.
    """
    # integer (or boolean) levels compared as they are (a capture's int8): the same changes as in
    # int64 without converting every sample; only the changes' new levels are converted
    levels = np.asarray(levels)
    if levels.dtype.kind not in "iub":
        levels = levels.astype(np.int64)
    if events is not None:
        ev_t = np.asarray(events[0], dtype=float)
        ev_v = np.asarray(events[1]).astype(np.int64)
        order = np.argsort(ev_t, kind="stable")
        ev_t, ev_v = ev_t[order], ev_v[order]
        previous = np.concatenate(([int(levels[0])], ev_v[:-1]))
        keep = ev_v != previous
        return ev_t[keep], ev_v[keep]
    idx = np.flatnonzero(levels[1:] != levels[:-1]) + 1
    return 0.5 * (t[idx - 1] + t[idx]), levels[idx].astype(np.int64)


def boundary_state(old_states: np.ndarray, new_states: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The hall boundary each transition crosses, named by the state that begins there going forward.

    ``new_states`` for a forward transition, ``old_states`` for a reverse one (and for a glitch,
    direction 0, whichever: its angle is not used).
    """
    return np.where(direction >= 0, new_states, old_states)


def quadrature_boundaries(
    times_a: np.ndarray,
    levels_a: np.ndarray,
    times_b: np.ndarray,
    levels_b: np.ndarray,
    a0: int,
    b0: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Decode A/B edges into boundary indices on the quarter-pitch grid.

    Each edge is a quarter-pitch step, forward or back as the Gray code of (A, B) says. Edges of
    A and B in the same instant (the same sample) are a double step whose order the samples
    cannot tell: both are taken in the direction of the last few steps (the sign of the sum of
    the last 8, counting a forward step before the first edge).

    Parameters
    ----------
    times_a, levels_a, times_b, levels_b : ndarray
        Change times (s) and new levels (0/1) of channels A and B.
    a0, b0 : int
        Levels before the first change.

    Returns
    -------
    times : ndarray
        Edge times (s), sorted.
    boundary : ndarray of int
        Index of the cell boundary each edge crosses: the edge between counts c and c+1 is
        boundary c+1 in either direction, so its angle is ``boundary * delta``.
    """
    times = np.concatenate((times_a, times_b))
    chan = np.concatenate((np.zeros(len(times_a), np.int64), np.ones(len(times_b), np.int64)))
    lev = np.concatenate((levels_a, levels_b)).astype(np.int64)
    # two comparisons, not np.isin: its choice of algorithm cost 8x their time a capture
    if not ((lev == 0) | (lev == 1)).all() or {int(a0), int(b0)} - {0, 1}:
        raise ValueError("encoder levels must be 0 or 1")
    order = np.lexsort((chan, times))
    times, chan, lev = times[order], chan[order], lev[order]
    n = len(times)
    k = np.arange(n)
    # each channel's level after every edge: its own last change so far, else its start level
    last_a = np.maximum.accumulate(np.where(chan == 0, k, -1)) if n else k
    last_b = np.maximum.accumulate(np.where(chan == 1, k, -1)) if n else k
    a = np.where(last_a >= 0, lev[np.maximum(last_a, 0)], int(a0))
    b = np.where(last_b >= 0, lev[np.maximum(last_b, 0)], int(b0))
    pos = 2 * b + (a ^ b)  # Gray-code position: 00 -> 10 -> 11 -> 01 is 0, 1, 2, 3
    before = np.concatenate(([2 * int(b0) + (int(a0) ^ int(b0))], pos[:-1]))
    d = np.where((pos - before) % 4 == 1, 1, -1)
    # double steps: an edge of A and one of B at the same time (sorted A first); both go the way
    # of the recent steps, which earlier double steps are part of: settled in order
    double = np.flatnonzero((times[1:] == times[:-1]) & (chan[1:] != chan[:-1]))
    for i in double:
        recent = np.concatenate(([1], d[max(0, i - 8):i]))[-8:]
        d[i] = d[i + 1] = 1 if recent.sum() >= 0 else -1
    count = np.cumsum(d)
    return times.astype(float, copy=False), np.maximum(count, count - d).astype(np.int64)


def debounce_edges(times: np.ndarray, boundary: np.ndarray, bounce_frac: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Collapse chatter: consecutive edges on one boundary in quick succession.

    A run of consecutive edges on the same boundary, each within ``bounce_frac`` times the
    median edge interval of the next, is one crossing when the run is odd (chatter around a
    real edge: kept once, at the run's mean time) and none when it is even (a glitch pulse
    that returned to where it was: dropped). A real reversal inside a cell lasts far longer
    and is kept.

    Parameters
    ----------
    times : ndarray
        Edge times (s), sorted.
    boundary : ndarray of int
        Boundary index of each edge.
    bounce_frac : float
        Threshold as a fraction of the median edge interval; 0 disables.

    Returns
    -------
    times, boundary : ndarray
        The edges with chatter collapsed.
    """
    if bounce_frac <= 0 or len(times) < 3:
        return times, boundary
    gap = np.diff(times)
    limit = bounce_frac * median(gap)
    linked = (np.diff(boundary) == 0) & (gap < limit)
    if not linked.any():
        return times, boundary
    # run id: a new run starts wherever an edge is not linked to its predecessor
    run = np.concatenate(([0], np.cumsum(~linked)))
    counts = np.bincount(run)
    mean_t = np.bincount(run, weights=times) / counts
    first = np.concatenate(([True], ~linked))
    keep = first & (counts[run] % 2 == 1)
    return mean_t[run[keep]], boundary[keep]
