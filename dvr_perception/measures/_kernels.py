"""numba twins of the measures' per-pixel loops (numpy computes the same when numba is missing).

:func:`group_stats` gives, bit for bit, what the numpy reference
:func:`dvr_perception.measures._layer_sets._group_stats` gives: the sums run over the pixels
in order, as ``numpy.bincount`` does.  :func:`correlate_columns` and :func:`correlate_rows`
give, bit for bit, what ``scipy.ndimage.correlate1d(..., axis=0 or 1, mode="nearest")``
gives with a symmetric or antisymmetric kernel (scipy's symmetric loop, the same order of
sums), vectorised along the rows and parallel over them.  Every kernel releases the
interpreter lock (``nogil``): :func:`~dvr_perception.measures.combined.all_measures` runs
transparency in a worker thread meanwhile.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = [
    "correlate_columns",
    "correlate_rows",
    "group_stats",
    "label_regions",
    "layer_bits",
    "neighbour_sets",
    "premultiplied_excess",
    "seen_on",
    "visibility_core",
]


@njit(cache=True, nogil=True)
def group_stats(values, group, n):
    """Per-group pixel count, mean and two-pass population std of ``values`` (flat arrays).

    Each group's sums run over its pixels in order; a run of pixels of one group is added
    in a register and stored once (the same additions in the same order).
    """
    count = np.zeros(n, np.int64)
    total = np.zeros(n)
    size = values.size
    i = 0
    while i < size:
        g = group[i]
        acc = total[g]
        j = i
        while j < size and group[j] == g:
            acc += values[j]
            j += 1
        total[g] = acc
        count[g] += j - i
        i = j
    mean = np.empty(n)
    for g in range(n):
        mean[g] = total[g] / max(count[g], 1)
    sq = np.zeros(n)
    i = 0
    while i < size:
        g = group[i]
        m = mean[g]
        acc = sq[g]
        j = i
        while j < size and group[j] == g:
            d = values[j] - m
            acc += d * d
            j += 1
        sq[g] = acc
        i = j
    std = np.empty(n)
    for g in range(n):
        std[g] = np.sqrt(sq[g] / max(count[g], 1))
    return count, mean, std


@njit(cache=True, nogil=True)
def premultiplied_excess(rgba, slack):
    """Count the pixels of an (N, 4) RGBA array whose colour exceeds their opacity.

    Returns ``(over, covered)``: the pixels whose brightest colour exceeds their opacity
    by more than ``slack``, and those with opacity above ``slack`` (read in float64).
    """
    over = 0
    covered = 0
    for i in range(rgba.shape[0]):
        alpha = float(rgba[i, 3])
        brightest = max(max(float(rgba[i, 0]), float(rgba[i, 1])), float(rgba[i, 2]))
        if brightest > alpha + slack:
            over += 1
        if alpha > slack:
            covered += 1
    return over, covered


@njit(cache=True, nogil=True)
def layer_bits(visible, assigned, threshold, limits, out):
    """Layer-set bitmask of every pixel: bit ``s`` where structure ``s`` is a layer there.

    ``visible`` and ``assigned`` are (K, N) (float32 or float64, read in float64), ``limits``
    (K,) float64 and ``out`` (N,) uint32: bit ``s`` of ``out[r]`` is set where
    ``visible[s, r] > threshold`` or ``assigned[s, r] > limits[s]``, the comparisons of
    :func:`~.regions.layer_footprints` and of the transparency measure's occlusion-free
    footprints, without their (K, N) boolean stacks.
    """
    k = visible.shape[0]
    for r in range(out.size):
        b = 0
        for s in range(k):
            if float(visible[s, r]) > threshold or float(assigned[s, r]) > limits[s]:
                b |= 1 << s
        out[r] = b


@njit(cache=True, nogil=True)
def seen_on(visible, assigned, scale, layers, pix, cap, fraction):
    """Whether ``layers`` together are seen on the flat pixels ``pix`` (D3, D7).

    ``visible`` and ``assigned`` are (K, N) (read in float64), ``scale`` (K,): on each pixel
    the layers' visible opacities and carried opacities ``min(assigned, cap) * scale`` are
    summed in the order of ``layers`` (as numpy sums a (layers, pixels) array over its
    first axis); seen where the visible sum exceeds ``fraction`` times the carried one, or
    nothing is carried.
    """
    out = np.empty(pix.size, np.bool_)
    for i in range(pix.size):
        p = pix[i]
        vis = 0.0
        carry = 0.0
        for layer in layers:
            vis += float(visible[layer, p])
            carry += min(float(assigned[layer, p]), cap) * scale[layer]
        out[i] = vis > fraction * carry or carry <= 0.0
    return out


@njit(cache=True, nogil=True)
def neighbour_sets(layer_set, k):
    """Per layer ``i``, the union (a bitmask) of the layer sets found next to its pixels.

    ``layer_set`` is an (H, W) bitmask image; ``seen[i]`` ORs the sets of every pixel within
    the 8-neighbourhood (the pixel itself included) of a pixel holding layer ``i``: bit ``j``
    of ``seen[i]`` says that layers ``i`` and ``j`` are adjacent (or overlap).  0 for a layer
    no pixel holds.
    """
    h, w = layer_set.shape
    seen = np.zeros(k, np.int64)
    for y in range(h):
        for x in range(w):
            b = np.int64(layer_set[y, x])
            if b == 0:
                continue
            near = np.int64(0)
            for yy in range(max(y - 1, 0), min(y + 2, h)):
                for xx in range(max(x - 1, 0), min(x + 2, w)):
                    near |= np.int64(layer_set[yy, xx])
            for i in range(k):
                if (b >> i) & 1:
                    seen[i] |= near
    return seen


@njit(cache=True)
def _root(parent, p):
    """Root of ``p`` in the union-find forest, compressing the path on the way."""
    r = p
    while parent[r] != r:
        r = parent[r]
    while parent[p] != r:
        q = parent[p]
        parent[p] = r
        p = q
    return r


@njit(cache=True)
def _union(parent, p, q):
    """Join the components of ``p`` and ``q``: the larger root points to the smaller."""
    a = _root(parent, p)
    b = _root(parent, q)
    if a < b:
        parent[b] = a
    elif b < a:
        parent[a] = b


@njit(cache=True, nogil=True)
def label_regions(image):
    """Label the connected components of equal value (8-connectivity) by first pixel.

    ``image`` is (H, W) integer.  Returns ``(region_id, first, area)``: (H, W) int32 ids
    ``0..n-1`` in row-major order of each component's first pixel (what
    ``skimage.measure.label(image, background=<absent value>, connectivity=2)`` gives, minus
    1), the flat index of each component's first pixel and its pixel count.

    Union-find over the neighbours already visited (up-left, up, up-right, left), where each
    pixel points to a smaller index, so every root is its component's first pixel and one
    pass in row-major order numbers the components.  Of the visited neighbours only those
    not already joined need a union: the pixel above touches the other three, and the
    left one touches the upper left one.
    """
    h, w = image.shape
    n = h * w
    flat = image.reshape(n)
    parent = np.arange(n)
    for y in range(h):
        for x in range(w):
            p = y * w + x
            v = flat[p]
            if y > 0 and flat[p - w] == v:
                parent[p] = _root(parent, p - w)
                continue
            if x > 0 and flat[p - 1] == v:
                parent[p] = _root(parent, p - 1)
            elif y > 0 and x > 0 and flat[p - w - 1] == v:
                parent[p] = _root(parent, p - w - 1)
            if y > 0 and x < w - 1 and flat[p - w + 1] == v:
                _union(parent, p, p - w + 1)
    region_id = np.empty(n, np.int32)
    first = np.empty(n, np.int64)
    area = np.zeros(n, np.int64)
    count = 0
    for p in range(n):
        if parent[p] == p:
            region_id[p] = count
            first[count] = p
            count += 1
        else:  # a smaller index in the same component, numbered already
            region_id[p] = region_id[parent[p]]
        area[region_id[p]] += 1
    return region_id.reshape(h, w), first[:count].copy(), area[:count].copy()


#: Fixed number of ray chunks of :func:`visibility_core`: its sums do not depend on the
#: number of threads.
_CHUNKS = 64


@njit(cache=True, nogil=True, parallel=True)
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
            if not (has_bits and bits[r] != 0) and _blank(visible, assigned, r):
                # nothing on this ray: target and deviation 0, every sum adds 0, no histogram
                for s in range(k):
                    target[s, r] = 0.0
                deviation[r] = 0.0
                nonempty[r] = False
                continue
            total = 0.0
            asum = 0.0
            for s in range(k):
                a = max(float(assigned[s, r]), 0.0)
                if thickness:
                    ws = a
                elif a == 0.0:  # imp * -expm1(-0 / scale) is 0: an absent structure
                    ws = 0.0
                else:
                    ws = imp[s] * -np.expm1(-a / scale)
                w[ch, s] = ws
                total += ws
                asum += float(assigned[s, r])
            full = asum > 0.0
            nonempty[r] = full
            dev = 0.0
            for s in range(k):
                c = 0.0
                if total > 0.0:
                    c = min(max(w[ch, s] / total, 0.0), 1.0)
                t = c * float(a_imp[r])
                v = float(visible[s, r])
                target[s, r] = t
                dev += abs(t - v)
                part[ch, 0, s] += v
                part[ch, 1, s] += t
                part[ch, 2, s] += float(assigned[s, r])
                if full:
                    part[ch, 3, s] += v
                    part[ch, 4, s] += t
                if has_bits:
                    on = (bits[r] >> np.uint64(s)) & np.uint64(1)
                    here = on != 0
                else:
                    here = float(assigned[s, r]) > 0.0 or v > 0.0
                if here:
                    r_part[ch, s] += 1
                    h_part[ch, 0, s, _bin(min(max(v, 0.0), 1.0), edges)] += 1
                    h_part[ch, 1, s, _bin(min(max(t, 0.0), 1.0), edges)] += 1
            deviation[r] = dev if full else 0.0
            if full:
                e_part[ch] += dev
                n_part[ch] += 1
    # the chunks' partial sums added in chunk order by plain loops: in a parallel function
    # numba turns ``e_part.sum()`` into a reduction split over the threads, whose rounding
    # changed with their number (E_v of the 512 x 512 x 452 CT one ulp apart at 1 and 2)
    e_sum = 0.0
    n_sum = 0
    sums = np.zeros((5, k))
    hist = np.zeros((2, k, nbins), np.int64)
    rays = np.zeros(k, np.int64)
    for ch in range(_CHUNKS):
        e_sum += e_part[ch]
        n_sum += n_part[ch]
        for s in range(k):
            for q in range(5):
                sums[q, s] += part[ch, q, s]
            for b in range(nbins):
                hist[0, s, b] += h_part[ch, 0, s, b]
                hist[1, s, b] += h_part[ch, 1, s, b]
            rays[s] += r_part[ch, s]
    return target, deviation, nonempty, e_sum, n_sum, sums, hist, rays


@njit(cache=True, inline="always")
def _blank(visible, assigned, r):
    """Whether every structure's visible and assigned opacity on ray ``r`` is 0."""
    for s in range(visible.shape[0]):  # noqa: SIM110 - a loop numba compiles, no generator
        if visible[s, r] != 0.0 or assigned[s, r] != 0.0:
            return False
    return True


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


@njit(cache=True, nogil=True, parallel=True)
def correlate_columns(src, weights, signs, out):
    """Correlate each image of ``src`` along its first axis, clamping at the edges.

    ``src`` and ``out`` are (N, H, W) float64, ``weights`` (N, 2 R + 1) the correlation
    weights (image ``n``'s output ``out[n, y] = sum_j src[n, y + j] weights[n, R + j]``, rows
    beyond the edges repeat the edge row: scipy's ``mode="nearest"``) and ``signs`` (N,) +1
    for a symmetric kernel, -1 for an antisymmetric one.  As scipy's ``correlate1d`` sums
    them: the centre term, then ``(src[y - j] +- src[y + j]) * weights[R - j]`` for ``j``
    from ``R`` down to 1, so the results are the same bits.
    """
    n, h, wd = src.shape
    r = (weights.shape[1] - 1) // 2
    for item in prange(n * h):
        m = item // h
        y = item - m * h
        o = out[m, y]
        s = src[m, y]
        w0 = weights[m, r]
        for x in range(wd):
            o[x] = s[x] * w0
        sym = signs[m] > 0
        for q in range(r):
            j = r - q
            a = src[m, max(y - j, 0)]
            b = src[m, min(y + j, h - 1)]
            wj = weights[m, r - j]
            if sym:
                for x in range(wd):
                    o[x] += (a[x] + b[x]) * wj
            else:
                for x in range(wd):
                    o[x] += (a[x] - b[x]) * wj


@njit(cache=True, nogil=True, parallel=True)
def correlate_rows(src, weights, signs, out):
    """:func:`correlate_columns` along the images' second axis (their rows).

    Each row is copied into a buffer extended by ``R`` edge values on both sides (scipy's
    ``mode="nearest"``); the sums run in the same order, so the results are scipy's bits.
    """
    n, h, wd = src.shape
    r = (weights.shape[1] - 1) // 2
    for item in prange(n * h):
        m = item // h
        y = item - m * h
        s = src[m, y]
        o = out[m, y]
        buf = np.empty(wd + 2 * r)
        for i in range(wd + 2 * r):
            buf[i] = s[min(max(i - r, 0), wd - 1)]
        w0 = weights[m, r]
        for x in range(wd):
            o[x] = buf[x + r] * w0
        sym = signs[m] > 0
        for q in range(r):
            j = r - q
            wj = weights[m, r - j]
            lo = buf[r - j : r - j + wd]
            hi = buf[r + j : r + j + wd]
            if sym:
                for x in range(wd):
                    o[x] += (lo[x] + hi[x]) * wj
            else:
                for x in range(wd):
                    o[x] += (lo[x] - hi[x]) * wj
