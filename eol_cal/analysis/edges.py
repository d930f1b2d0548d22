"""Edges of the digital channels: level changes, quadrature decoding onto the quarter-pitch grid,
chatter removal (steps 1 and 2 of :mod:`eol_cal.analysis.angle`)."""

from __future__ import annotations

import numpy as np

# Gray-code position of the quadrature state (a, b) in forward rotation: 00 -> 10 -> 11 -> 01.
_QUAD_POS = {(0, 0): 0, (1, 0): 1, (1, 1): 2, (0, 1): 3}


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
    levels = np.asarray(levels).astype(np.int64)
    if events is not None:
        ev_t = np.asarray(events[0], dtype=float)
        ev_v = np.asarray(events[1]).astype(np.int64)
        order = np.argsort(ev_t, kind="stable")
        ev_t, ev_v = ev_t[order], ev_v[order]
        previous = np.concatenate(([levels[0]], ev_v[:-1]))
        keep = ev_v != previous
        return ev_t[keep], ev_v[keep]
    idx = np.flatnonzero(levels[1:] != levels[:-1]) + 1
    return 0.5 * (t[idx - 1] + t[idx]), levels[idx]


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

    Parameters
    ----------
    times_a, levels_a, times_b, levels_b : ndarray
        Change times (s) and new levels of channels A and B.
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
    chan = np.concatenate((np.zeros(len(times_a), int), np.ones(len(times_b), int)))
    lev = np.concatenate((levels_a, levels_b))
    order = np.lexsort((chan, times))
    times, chan, lev = times[order], chan[order], lev[order]
    a, b = int(a0), int(b0)
    count = 0
    # Direction of the last few steps: one glitch step must not decide an ambiguous double step.
    recent = [1]
    boundary = np.empty(len(times), dtype=np.int64)
    out_t = np.empty(len(times))
    n_out = 0
    i = 0
    n = len(times)
    while i < n:
        # Edges of A and B in the same instant (same sample) are a double step whose order
        # the samples cannot tell: apply them in the order the recent direction implies.
        j = i + 1
        if j < n and times[j] == times[i] and chan[j] != chan[i]:
            group = [i, j]
            i_next = j + 1
        else:
            group = [i]
            i_next = j
        if len(group) == 2:
            q_old = _QUAD_POS[(a, b)]
            na, nb = a, b
            for g in group:
                if chan[g] == 0:
                    na = int(lev[g])
                else:
                    nb = int(lev[g])
            step = (_QUAD_POS[(na, nb)] - q_old) % 4
            trend = 1 if sum(recent) >= 0 else -1
            d = trend if step == 2 else (1 if step == 1 else -1 if step == 3 else 0)
            first = [g for g in group if (chan[g] == 0) == ((d > 0) == (a == b))]
            group = first + [g for g in group if g not in first]
        for g in group:
            q_old = _QUAD_POS[(a, b)]
            if chan[g] == 0:
                a = int(lev[g])
            else:
                b = int(lev[g])
            step = (_QUAD_POS[(a, b)] - q_old) % 4
            d = 1 if step == 1 else -1
            new = count + d
            # written in the order applied, so a double step's two edges come out in sequence
            out_t[n_out] = times[g]
            boundary[n_out] = max(count, new)
            n_out += 1
            count = new
            recent.append(d)
            if len(recent) > 8:
                recent.pop(0)
        i = i_next
    return out_t, boundary


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
    limit = bounce_frac * float(np.median(gap))
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
