"""numba twins of the measures' per-pixel loops (numpy computes the same when numba is missing).

:func:`group_stats` gives, bit for bit, what the numpy reference
:func:`dvr_perception.measures._layer_sets._group_stats` gives: the sums run over the pixels in
order, as ``numpy.bincount`` does.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["group_stats", "visibility_core"]


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


#: Fixed number of ray chunks of :func:`visibility_core`: its sums do not depend on the
#: number of threads.
_CHUNKS = 64


@njit(cache=True, parallel=True)
def visibility_core(visible, assigned, a_imp, imp, scale, thickness, bits, edges):
    """Per-ray targets and deviations, and the image-wide sums and histograms of visibility.

    ``visible`` and ``assigned`` are (K, N) float64, ``a_imp`` (N,), ``imp`` (K,); ``bits``
    (N,) uint64 presence bitmask, or an empty array for "any assigned or visible opacity";
    ``edges`` the histograms' ``nbins + 1`` bin edges on [0, 1] (``numpy.linspace``).
    Per ray the numbers are those of the numpy code in :mod:`..visibility` (the same
    operations in the same order); the image-wide sums run over :data:`_CHUNKS` fixed
    chunks of rays.  Returns ``target`` (K, N) float32, ``deviation`` (N,) float32,
    ``nonempty`` (N,) bool, ``e_sum`` (sum of the deviation over the non-empty rays),
    ``n_nonempty``, ``sums`` (5, K): visible, target, assigned over all rays, visible and
    target over the non-empty rays, and ``hist`` (2, K, nbins) with ``rays`` (K,).
    """
    k, n = visible.shape
    nbins = edges.size - 1
    target = np.empty((k, n), np.float32)
    deviation = np.empty(n, np.float32)
    nonempty = np.empty(n, np.bool_)
    part = np.zeros((_CHUNKS, 5, k))
    e_part = np.zeros(_CHUNKS)
    n_part = np.zeros(_CHUNKS, np.int64)
    h_part = np.zeros((_CHUNKS, 2, k, nbins), np.int64)
    r_part = np.zeros((_CHUNKS, k), np.int64)
    has_bits = bits.size == n
    w = np.empty((_CHUNKS, k))
    for ch in prange(_CHUNKS):
        for r in range(ch * n // _CHUNKS, (ch + 1) * n // _CHUNKS):
            total = 0.0
            asum = 0.0
            for s in range(k):
                a = max(assigned[s, r], 0.0)
                ws = a if thickness else imp[s] * -np.expm1(-a / scale)
                w[ch, s] = ws
                total += ws
                asum += assigned[s, r]
            full = asum > 0.0
            nonempty[r] = full
            dev = 0.0
            for s in range(k):
                c = 0.0
                if total > 0.0:
                    c = min(max(w[ch, s] / total, 0.0), 1.0)
                t = c * a_imp[r]
                v = visible[s, r]
                target[s, r] = t
                dev += abs(t - v)
                part[ch, 0, s] += v
                part[ch, 1, s] += t
                part[ch, 2, s] += assigned[s, r]
                if full:
                    part[ch, 3, s] += v
                    part[ch, 4, s] += t
                if has_bits:
                    on = (bits[r] >> np.uint64(s)) & np.uint64(1)
                    here = on != 0
                else:
                    here = assigned[s, r] > 0.0 or v > 0.0
                if here:
                    r_part[ch, s] += 1
                    h_part[ch, 0, s, _bin(min(max(v, 0.0), 1.0), edges)] += 1
                    h_part[ch, 1, s, _bin(min(max(t, 0.0), 1.0), edges)] += 1
            deviation[r] = dev if full else 0.0
            if full:
                e_part[ch] += dev
                n_part[ch] += 1
    return (target, deviation, nonempty, e_part.sum(), n_part.sum(), part.sum(axis=0),
            h_part.sum(axis=0), r_part.sum(axis=0))  # fmt: skip


@njit(cache=True, inline="always")
def _bin(x, edges):
    """Bin of ``x`` in [0, 1] among the equal bins of ``edges``, as ``numpy.histogram`` counts.

    numpy's uniform-bin path: ``int(x * nbins)`` (the last edge in the last bin), then one
    down where ``x`` lies below that bin's edge, one up where it reaches the next edge.
    """
    nbins = edges.size - 1
    i = int(x * nbins)
    if i == nbins:
        i -= 1
    if x < edges[i]:
        i -= 1
    elif i != nbins - 1 and x >= edges[i + 1]:
        i += 1
    return i
