"""numba twins of the measures' per-pixel loops (numpy computes the same when numba is missing).

:func:`group_stats` gives, bit for bit, what the numpy reference
:func:`dvr_perception.measures._scene._group_stats` gives: the sums run over the pixels in
order, as ``numpy.bincount`` does.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["group_stats"]


@njit(cache=True)
def group_stats(values, group, n):
    """Per-group pixel count, mean and two-pass population std of ``values`` (flat arrays)."""
    count = np.zeros(n, np.int64)
    total = np.zeros(n)
    for i in range(values.size):
        g = group[i]
        count[g] += 1
        total[g] += values[i]
    mean = np.empty(n)
    for g in range(n):
        mean[g] = total[g] / max(count[g], 1)
    sq = np.zeros(n)
    for i in range(values.size):
        g = group[i]
        d = values[i] - mean[g]
        sq[g] += d * d
    std = np.empty(n)
    for g in range(n):
        std[g] = np.sqrt(sq[g] / max(count[g], 1))
    return count, mean, std
