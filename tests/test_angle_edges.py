"""Quadrature decoding, vectorised (eol_cal.analysis.edges.quadrature_boundaries), against the edge
walk it replaced: one edge at a time, a double step (A and B in one instant) taken in the order
the last eight steps imply. Same times, same boundaries, on thousands of random edge sequences
with many simultaneous edges."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.analysis.edges import quadrature_boundaries

_QUAD_POS = {(0, 0): 0, (1, 0): 1, (1, 1): 2, (0, 1): 3}


def _walk(times_a, levels_a, times_b, levels_b, a0, b0):
    """The edge walk, edge by edge (the implementation before the vectorised one)."""
    times = np.concatenate((times_a, times_b))
    chan = np.concatenate((np.zeros(len(times_a), int), np.ones(len(times_b), int)))
    lev = np.concatenate((levels_a, levels_b))
    order = np.lexsort((chan, times))
    times, chan, lev = times[order], chan[order], lev[order]
    a, b, count, recent = int(a0), int(b0), 0, [1]
    out_t, boundary = [], []
    i, n = 0, len(times)
    while i < n:
        j = i + 1
        group = [i, j] if j < n and times[j] == times[i] and chan[j] != chan[i] else [i]
        i_next = i + len(group)
        if len(group) == 2:
            q_old = _QUAD_POS[(a, b)]
            na, nb = a, b
            for g in group:
                na, nb = (int(lev[g]), nb) if chan[g] == 0 else (na, int(lev[g]))
            step = (_QUAD_POS[(na, nb)] - q_old) % 4
            trend = 1 if sum(recent) >= 0 else -1
            d = trend if step == 2 else (1 if step == 1 else -1 if step == 3 else 0)
            first = [g for g in group if (chan[g] == 0) == ((d > 0) == (a == b))]
            group = first + [g for g in group if g not in first]
        for g in group:
            q_old = _QUAD_POS[(a, b)]
            a, b = (int(lev[g]), b) if chan[g] == 0 else (a, int(lev[g]))
            d = 1 if (_QUAD_POS[(a, b)] - q_old) % 4 == 1 else -1
            out_t.append(times[g])
            boundary.append(max(count, count + d))
            count += d
            recent = (recent + [d])[-8:]
        i = i_next
    return np.array(out_t, float), np.array(boundary, np.int64)


def test_vectorised_decoding_is_the_edge_walk():
    rng = np.random.default_rng(0)
    ties = 0
    for _ in range(2000):
        a0, b0 = (int(x) for x in rng.integers(0, 2, 2))
        na, nb = rng.integers(0, 40, 2)
        grid = int(rng.integers(1, 4))  # a coarse time grid: many edges of A and B in one instant
        ta = np.sort(rng.integers(0, 30 * grid, na)) / grid
        tb = np.sort(rng.integers(0, 30 * grid, nb)) / grid
        la, lb = (a0 + 1 + np.arange(na)) % 2, (b0 + 1 + np.arange(nb)) % 2  # each change toggles its line
        ties += bool(set(ta) & set(tb))
        got = quadrature_boundaries(ta, la, tb, lb, a0, b0)
        ref = _walk(ta, la, tb, lb, a0, b0)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
    assert ties > 1000


def test_levels_other_than_0_and_1_are_refused():
    with pytest.raises(ValueError, match="0 or 1"):
        quadrature_boundaries(np.array([1.0]), np.array([2]), np.array([2.0]), np.array([1]), 0, 0)


def test_edge_knots_as_np_unique_and_the_means():
    """angle.edge_knots: sorted edges with no shared instant are their own knots, the values np.unique
    and the means of one give, bit for bit; shared instants are merged at their mean angle."""
    import numpy as np

    from eol_cal.analysis.angle import edge_knots

    rng = np.random.default_rng(7)
    t = np.cumsum(rng.exponential(1e-4, 4000))
    rel = np.cumsum(rng.choice([-1.0, 1.0], 4000)) * (4 * np.pi / 2048)
    for te in (t, np.repeat(t[:50], 2)):
        u, inv = np.unique(te, return_inverse=True)
        r = rel[:len(te)]
        want = (u, np.bincount(inv, weights=r) / np.bincount(inv))
        got = edge_knots(te, r)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert np.array_equal(np.signbit(got[1]), np.signbit(want[1]))


def test_level_changes_of_small_integer_levels_are_the_int64_ones():
    # a capture's int8 channels are compared as they are: the same changes, the new levels int64
    from eol_cal.analysis.edges import level_changes

    rng = np.random.default_rng(3)
    for _ in range(30):
        n = int(rng.integers(2, 3000))
        t = np.cumsum(rng.uniform(1e-4, 2e-4, n))
        lev = rng.integers(0, 7, n) * (rng.uniform(size=n) < 0.9)
        ref = level_changes(t, lev.astype(np.int64))
        for dtype in (np.int8, np.uint8, np.int32, float):
            got = level_changes(t, lev.astype(dtype))
            assert got[1].dtype == np.int64
            assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
        bits = lev.astype(bool)
        got = level_changes(t, bits)
        ref = level_changes(t, bits.astype(np.int64))
        assert got[1].dtype == np.int64 and np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
