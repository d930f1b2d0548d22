"""The median of a 1-D array, bit for bit ``np.median``'s, without its generic machinery.

``np.median`` goes through ``_ureduce``, a NaN check and ``np.mean`` of the middle values: on
the refit's few-thousand-sample arrays that costs about as much as the partition itself
(issue 37: ~14 medians a serial). This computes the same partition and the same arithmetic
(the middle value, or the sum of the two middle values over 2, each sum from +0.0 as ``np.mean``'s), so the
result is identical to the last bit (tests/test_numerics_median.py compares them).
"""

from __future__ import annotations

import numpy as np


def median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a 1-D array (any unit; the same unit back).

    Parameters
    ----------
    x : ndarray
        One-dimensional values; NaN anywhere gives NaN, as ``np.median``.

    Returns
    -------
    float
        The middle value (odd length) or the mean of the two middle values (even length); NaN
        for an empty array (``np.median`` warns there: it is left to it).
    """
    a = np.asarray(x, dtype=float)
    n = len(a)
    if n == 0:
        return float(np.median(a))
    h = n // 2
    # the last position partitioned too: a NaN sorts there, and makes the median NaN (np.median's check)
    part = np.partition(a, (h - 1, h, n - 1) if n % 2 == 0 else (h, n - 1))
    if np.isnan(part[-1]):
        return float("nan")
    # np.mean's sum starts from +0.0 (a -0.0 median comes back +0.0): the same additions here
    if n % 2:
        return float(0.0 + part[h])
    return float((0.0 + part[h - 1] + part[h]) / 2.0)
