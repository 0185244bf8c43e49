"""numba kernels of :mod:`dvr_perception.rays.curvature` (numpy computes the same without numba).

The curvature is computed slice by slice (see :func:`dvr_perception.rays.curvature`'s notes),
by one Python thread per y band (the slice kernels are serial and release the GIL):

* :func:`classify_slice` and :func:`boundary_slice` give the structure ids and boundary voxels
  of one z slice, with the x range of the boundary voxels of every row.
* :func:`need_ranges` turns those row ranges into the rows (and x ranges) of the in-plane
  derivative passes that the boundary voxels read.
* :func:`xy_pass` filters one slice along x (orders 0, 1, 2) and then along y (the six
  combinations of total order at most 2), on the needed rows only.
* :func:`z_pass` finishes the nine derivatives along z on the rows of a slice with boundary
  voxels, and :func:`z_points` gives the numerator of the mean curvature and ``|grad f|^2`` at
  those voxels.
* :func:`mark_pages` and :func:`slab_fill` keep a band's ``|H|`` in 8^3 pages as it is
  computed, eight z slices at a time (:mod:`dvr_perception.rays._curvature_pages`).
* :func:`cell_diffs` and :func:`cells_gradient_max` give what bounds ``|grad f|^2`` per cell
  (neighbour differences and the value range) and its exact maximum (the branch and bound of
  the global gradient maximum).

Kernels are passed as their half ``w[r:]`` (``w[r + a]``, ``a = 0..r``); odd orders use
``w[r + a] (s[x + a] - s[x - a])``, so a constant field has exactly zero gradient.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = [
    "boundary_slice",
    "cell_diffs",
    "cells_gradient_max",
    "classify_slice",
    "mark_pages",
    "mask_points",
    "need_ranges",
    "slab_fill",
    "write_curvature",
    "xy_pass",
    "z_pass",
    "z_points",
]


@njit(cache=True, nogil=True)
def classify_slice(data, los, his, inclusive, ks, out):
    """Structure id of every voxel of a 2-D slice; the last matching range wins."""
    ny, nx = data.shape
    nr = los.size
    for y in range(ny):
        for x in range(nx):
            v = np.float64(data[y, x])
            k = -1
            for n in range(nr):
                if v >= los[n] and (v < his[n] or (inclusive[n] and v == his[n])):
                    k = ks[n]
            out[y, x] = k


@njit(cache=True, nogil=True)
def boundary_slice(prev, cur, nxt, has_prev, has_next, y0, x0, out, rowlo, rowhi):
    """Boundary voxels of slice ``cur`` in the window starting at ``(y0, x0)`` of the slice.

    A voxel is a boundary voxel when its id differs from one of its 6 neighbours inside the
    grid (``prev``/``nxt`` are the slices below and above, when ``has_prev``/``has_next``).
    ``out`` (the window's shape) receives the mask, ``rowlo``/``rowhi`` the first and last
    x (slice coordinates) of each window row's boundary voxels (``lo > hi`` when none).
    """
    ny, nx = cur.shape
    wy, wx = out.shape
    for j in range(wy):
        y = y0 + j
        lo = nx
        hi = -1
        for i in range(wx):
            x = x0 + i
            c = cur[y, x]
            b = (
                (x > 0 and cur[y, x - 1] != c)
                or (x + 1 < nx and cur[y, x + 1] != c)
                or (y > 0 and cur[y - 1, x] != c)
                or (y + 1 < ny and cur[y + 1, x] != c)
                or (has_prev and prev[y, x] != c)
                or (has_next and nxt[y, x] != c)
            )
            out[j, i] = b
            if b:
                lo = min(lo, x)
                hi = x
        rowlo[j] = lo
        rowhi[j] = hi


@njit(cache=True, nogil=True)
def need_ranges(rowlo, rowhi, z_first, nzb, rz, ry, ylo, yhi, xlo, xhi):
    """Rows and x ranges of the in-plane passes that the boundary voxels read.

    ``rowlo``/``rowhi`` (``[slice, row]``) hold the x range of the points of slice
    ``z_first + slice`` (block coordinates; rows are block rows).  ``ylo``/``yhi``
    (``[nzb, ny]``) receive the ranges where the y pass is needed (the z pass reads
    ``clamp(z + dz)``, ``|dz| <= rz``), ``xlo``/``xhi`` where the x pass is needed (the y pass
    reads ``clamp(y + dy)``, ``|dy| <= ry``).  Empty ranges have ``lo > hi``.
    """
    nze, ny = rowlo.shape
    big = 1 << 30
    ylo[:, :] = big
    yhi[:, :] = -1
    xlo[:, :] = big
    xhi[:, :] = -1
    for k in range(nze):
        z = z_first + k
        a = max(0, z - rz)
        b = min(nzb - 1, z + rz)
        for y in range(ny):
            lo = rowlo[k, y]
            hi = rowhi[k, y]
            if lo > hi:
                continue
            for zz in range(a, b + 1):
                ylo[zz, y] = min(ylo[zz, y], lo)
                yhi[zz, y] = max(yhi[zz, y], hi)
    for zz in range(nzb):
        for y in range(ny):
            lo = ylo[zz, y]
            hi = yhi[zz, y]
            if lo > hi:
                continue
            for yy in range(max(0, y - ry), min(ny - 1, y + ry) + 1):
                xlo[zz, yy] = min(xlo[zz, yy], lo)
                xhi[zz, yy] = max(xhi[zz, yy], hi)


@njit(inline="always")
def _init(out, a, w):
    """``out[:] = w * a`` (1-D slices of equal length: loops that vectorise)."""
    for i in range(out.size):
        out[i] = w * a[i]


@njit(inline="always")
def _even(out, a, b, w):
    """``out[:] += w * (a + b)``."""
    for i in range(out.size):
        out[i] += w * (a[i] + b[i])


@njit(inline="always")
def _odd(out, a, b, w):
    """``out[:] += w * (a - b)``."""
    for i in range(out.size):
        out[i] += w * (a[i] - b[i])


@njit(cache=True, nogil=True)
def xy_pass(src, xlo, xhi, ylo, yhi, kx0, kx1, kx2, ky0, ky1, ky2, xbuf, out):
    """Filter slice ``src`` along x then y on the needed rows (block coordinates).

    ``xbuf`` ``[3, ny, nx]`` receives the x pass (orders 0, 1, 2) on rows ``y`` with
    ``xlo[y] <= xhi[y]`` over ``x`` in that range; ``out`` ``[6, ny, nx]`` the y pass, in the
    order (oy, ox) = (0,0), (0,1), (0,2), (1,0), (1,1), (2,0), on the rows and ranges of
    ``ylo``/``yhi``.  Indices are clamped to the slice (edge replication).  Every value is
    summed in the same order whatever the ranges, so a brick gives the full result's bits.
    """
    ny, nx = src.shape
    rx = kx0.size - 1
    ry = ky0.size - 1
    pad = np.empty(nx + 2 * rx, np.float32)
    zero = np.float32(0.0)
    for y in range(ny):
        lo = xlo[y]
        hi = xhi[y]
        if lo > hi:
            continue
        # the row with replicated edges: pad[i] = src[y, clamp(lo - rx + i)]
        m = hi - lo + 1
        for i in range(m + 2 * rx):
            pad[i] = src[y, min(max(lo - rx + i, 0), nx - 1)]
        r0 = xbuf[0, y, lo : hi + 1]
        r1 = xbuf[1, y, lo : hi + 1]
        r2 = xbuf[2, y, lo : hi + 1]
        c = pad[rx : rx + m]
        _init(r0, c, kx0[0])
        _init(r1, c, zero)
        _init(r2, c, kx2[0])
        for t in range(1, rx + 1):
            p = pad[rx + t : rx + t + m]
            q = pad[rx - t : rx - t + m]
            _even(r0, p, q, kx0[t])
            _odd(r1, p, q, kx1[t])
            _even(r2, p, q, kx2[t])
    for y in range(ny):
        lo = ylo[y]
        hi = yhi[y]
        if lo > hi:
            continue
        _init(out[0, y, lo : hi + 1], xbuf[0, y, lo : hi + 1], ky0[0])
        _init(out[1, y, lo : hi + 1], xbuf[1, y, lo : hi + 1], ky0[0])
        _init(out[2, y, lo : hi + 1], xbuf[2, y, lo : hi + 1], ky0[0])
        _init(out[3, y, lo : hi + 1], xbuf[0, y, lo : hi + 1], zero)
        _init(out[4, y, lo : hi + 1], xbuf[0, y, lo : hi + 1], zero)
        _init(out[5, y, lo : hi + 1], xbuf[0, y, lo : hi + 1], ky2[0])
        for t in range(1, ry + 1):
            yp = min(y + t, ny - 1)
            ym = max(y - t, 0)
            _even(
                out[0, y, lo : hi + 1], xbuf[0, yp, lo : hi + 1], xbuf[0, ym, lo : hi + 1], ky0[t]
            )
            _even(
                out[1, y, lo : hi + 1], xbuf[1, yp, lo : hi + 1], xbuf[1, ym, lo : hi + 1], ky0[t]
            )
            _even(
                out[2, y, lo : hi + 1], xbuf[2, yp, lo : hi + 1], xbuf[2, ym, lo : hi + 1], ky0[t]
            )
            _odd(out[3, y, lo : hi + 1], xbuf[0, yp, lo : hi + 1], xbuf[0, ym, lo : hi + 1], ky1[t])
            _odd(out[4, y, lo : hi + 1], xbuf[1, yp, lo : hi + 1], xbuf[1, ym, lo : hi + 1], ky1[t])
            _even(
                out[5, y, lo : hi + 1], xbuf[0, yp, lo : hi + 1], xbuf[0, ym, lo : hi + 1], ky2[t]
            )


@njit(cache=True, nogil=True)
def z_pass(ring, slots, rowlo, rowhi, kz0, kz1, kz2, dbuf):
    """Filter along z on the rows of one slice with points: the nine derivatives.

    ``ring[slots[rz + dz]]`` is the y pass (:func:`xy_pass`) of slice ``clamp(z + dz)``;
    ``dbuf`` ``[9, ny, nx]`` receives, over ``rowlo[y]..rowhi[y]``, the derivatives of order
    (oz, oy, ox) = (0,0,1), (0,0,2), (0,1,0), (0,1,1), (0,2,0), (1,0,0), (1,0,1), (1,1,0),
    (2,0,0) in voxel units.
    """
    ny = rowlo.size
    rz = kz0.size - 1
    c = slots[rz]
    zero = np.float32(0.0)
    for y in range(ny):
        lo = rowlo[y]
        hi = rowhi[y]
        if lo > hi:
            continue
        _init(dbuf[0, y, lo : hi + 1], ring[c, 1, y, lo : hi + 1], kz0[0])
        _init(dbuf[1, y, lo : hi + 1], ring[c, 2, y, lo : hi + 1], kz0[0])
        _init(dbuf[2, y, lo : hi + 1], ring[c, 3, y, lo : hi + 1], kz0[0])
        _init(dbuf[3, y, lo : hi + 1], ring[c, 4, y, lo : hi + 1], kz0[0])
        _init(dbuf[4, y, lo : hi + 1], ring[c, 5, y, lo : hi + 1], kz0[0])
        _init(dbuf[5, y, lo : hi + 1], ring[c, 0, y, lo : hi + 1], zero)
        _init(dbuf[6, y, lo : hi + 1], ring[c, 0, y, lo : hi + 1], zero)
        _init(dbuf[7, y, lo : hi + 1], ring[c, 0, y, lo : hi + 1], zero)
        _init(dbuf[8, y, lo : hi + 1], ring[c, 0, y, lo : hi + 1], kz2[0])
        for t in range(1, rz + 1):
            p = slots[rz + t]
            q = slots[rz - t]
            _even(
                dbuf[0, y, lo : hi + 1],
                ring[p, 1, y, lo : hi + 1],
                ring[q, 1, y, lo : hi + 1],
                kz0[t],
            )
            _even(
                dbuf[1, y, lo : hi + 1],
                ring[p, 2, y, lo : hi + 1],
                ring[q, 2, y, lo : hi + 1],
                kz0[t],
            )
            _even(
                dbuf[2, y, lo : hi + 1],
                ring[p, 3, y, lo : hi + 1],
                ring[q, 3, y, lo : hi + 1],
                kz0[t],
            )
            _even(
                dbuf[3, y, lo : hi + 1],
                ring[p, 4, y, lo : hi + 1],
                ring[q, 4, y, lo : hi + 1],
                kz0[t],
            )
            _even(
                dbuf[4, y, lo : hi + 1],
                ring[p, 5, y, lo : hi + 1],
                ring[q, 5, y, lo : hi + 1],
                kz0[t],
            )
            _odd(
                dbuf[5, y, lo : hi + 1],
                ring[p, 0, y, lo : hi + 1],
                ring[q, 0, y, lo : hi + 1],
                kz1[t],
            )
            _odd(
                dbuf[6, y, lo : hi + 1],
                ring[p, 1, y, lo : hi + 1],
                ring[q, 1, y, lo : hi + 1],
                kz1[t],
            )
            _odd(
                dbuf[7, y, lo : hi + 1],
                ring[p, 3, y, lo : hi + 1],
                ring[q, 3, y, lo : hi + 1],
                kz1[t],
            )
            _even(
                dbuf[8, y, lo : hi + 1],
                ring[p, 0, y, lo : hi + 1],
                ring[q, 0, y, lo : hi + 1],
                kz2[t],
            )


@njit(inline="always")
def _numerator(d001, d002, d010, d011, d020, d100, d101, d110, d200, inv):
    """Mean-curvature numerator ``g^T H g - |g|^2 tr H`` and ``|g|^2`` (world units).

    ``dZYX`` is the derivative of order (Z, Y, X) along (z, y, x) in voxel units.
    """
    inv_z = inv[0]
    inv_y = inv[1]
    inv_x = inv[2]
    gz = d100 * inv_z
    gy = d010 * inv_y
    gx = d001 * inv_x
    hzz = d200 * inv_z * inv_z
    hyy = d020 * inv_y * inv_y
    hxx = d002 * inv_x * inv_x
    hzy = d110 * inv_z * inv_y
    hzx = d101 * inv_z * inv_x
    hyx = d011 * inv_y * inv_x
    num = -(gz * gz * (hyy + hxx) + gy * gy * (hzz + hxx) + gx * gx * (hzz + hyy))
    num += 2.0 * (gz * gy * hzy + gz * gx * hzx + gy * gx * hyx)
    return num, gz * gz + gy * gy + gx * gx


@njit(cache=True, nogil=True)
def z_points(dbuf, ys, xs, inv, num, mag2):
    """Numerator of the mean curvature and ``|grad f|^2`` (world units) at ``(ys, xs)``.

    ``dbuf`` holds the nine derivatives of :func:`z_pass`; the results are float64.
    """
    for p in range(ys.size):
        y = ys[p]
        x = xs[p]
        n, m = _numerator(
            np.float64(dbuf[0, y, x]),
            np.float64(dbuf[1, y, x]),
            np.float64(dbuf[2, y, x]),
            np.float64(dbuf[3, y, x]),
            np.float64(dbuf[4, y, x]),
            np.float64(dbuf[5, y, x]),
            np.float64(dbuf[6, y, x]),
            np.float64(dbuf[7, y, x]),
            np.float64(dbuf[8, y, x]),
            inv,
        )
        num[p] = n
        mag2[p] = m


@njit(cache=True, nogil=True)
def mask_points(mask, y_off, x_off):
    """Return the rows and columns of the true pixels of ``mask``, as ``numpy.nonzero``.

    Row-major order, offset by ``(y_off, x_off)``, as int64.
    """
    ny, nx = mask.shape
    n = 0
    for y in range(ny):
        for x in range(nx):
            if mask[y, x]:
                n += 1
    ys = np.empty(n, np.int64)
    xs = np.empty(n, np.int64)
    n = 0
    for y in range(ny):
        for x in range(nx):
            if mask[y, x]:
                ys[n] = y + y_off
                xs[n] = x + x_off
                n += 1
    return ys, xs


@njit(cache=True, nogil=True)
def write_curvature(num, mag2, ys, xs, thr, thr_hi, out, cand):
    """Write ``|H| = |num| / (2 |g|^3)`` at the points ``(ys, xs)`` of the slice ``out``.

    Points with ``mag2 <= thr`` are flat (0).  Returns the largest ``mag2``; ``cand`` marks
    the points that are not flat but whose ``mag2`` is at most ``thr_hi`` (they may be flat
    against the whole volume's gradient maximum).  The arithmetic of the numpy code in
    :func:`~dvr_perception.rays._curvature_passes._field_curvature`, point by point.
    """
    seen = 0.0
    for p in range(num.size):
        m = mag2[p]
        seen = max(seen, m)
        flat = m <= thr
        cand[p] = (not flat) and m <= thr_hi
        if flat:
            out[ys[p], xs[p]] = 0.0
        else:
            out[ys[p], xs[p]] = np.float32(abs(num[p]) / (2.0 * m * np.sqrt(m)))
    return seen


@njit(cache=True, nogil=True)
def mark_pages(plane, ys, xs, flags):
    """``flags[y >> 3, x >> 3] = 1`` for the points ``(ys, xs)`` of ``plane`` that are not 0."""
    for p in range(ys.size):
        y = ys[p]
        x = xs[p]
        if plane[y, x] != 0.0:
            flags[y >> 3, x >> 3] = 1


@njit(cache=True, nogil=True)
def slab_fill(slab, depth, index, pages):
    """Copy the first ``depth`` planes of ``slab`` into its numbered pages, and zero them.

    ``index[r, c]`` is the page of rows ``8 r ...`` and columns ``8 c ...`` in ``pages``
    (``(n, 8, 8, 8)``; every value is written, 0 where the slab does not reach), -1 where it
    holds only zeros (left as it is).  The slab is all zero afterwards.
    """
    _, ny, nx = slab.shape
    zero = np.float32(0.0)
    for r in range(index.shape[0]):
        y0 = r * 8
        for c in range(index.shape[1]):
            p = index[r, c]
            if p < 0:
                continue
            x0 = c * 8
            if depth == 8 and y0 + 8 <= ny and x0 + 8 <= nx:
                for z in range(8):
                    for j in range(8):
                        row = slab[z, y0 + j]
                        dst = pages[p, z, j]
                        for i in range(8):
                            dst[i] = row[x0 + i]
                            row[x0 + i] = zero
                continue
            for z in range(8):
                for j in range(8):
                    y = y0 + j
                    for i in range(8):
                        x = x0 + i
                        if z < depth and y < ny and x < nx:
                            pages[p, z, j, i] = slab[z, y, x]
                            slab[z, y, x] = zero
                        else:
                            pages[p, z, j, i] = zero


@njit(inline="always")
def _value(src, z, y, x, match, offset):
    if match >= 0:
        return np.float32(1.0) if src[z, y, x] == match else np.float32(0.0)
    return np.float32(src[z, y, x]) - offset


@njit(parallel=True, cache=True)
def cell_diffs(src, match, offset, size, z0, y0, x0, nz, ny, nx, out):
    """Largest absolute difference of neighbouring voxels along z, y, x in each cell.

    Cell ``(i, j, k)`` covers voxels ``z0 + size * i ...`` (clipped to ``[z0, z0 + nz)`` and
    so on); the pair ``(v, v + e)`` counts for the cell of ``v`` (the neighbour index is
    clamped to the volume, so pairs leaving it count 0).  The field is ``src - offset``, or
    ``src == match`` when ``match >= 0``.  ``out[..., :3]`` are those differences and
    ``out[..., 3]``, ``out[..., 4]`` the smallest and largest value of the cell's voxels.
    """
    cz, _, cx = out.shape[:3]
    vz, vy, vx = src.shape
    out[:, :, :, :3] = 0.0
    out[:, :, :, 3] = np.inf
    out[:, :, :, 4] = -np.inf
    for i in prange(cz):
        for z in range(z0 + size * i, min(z0 + size * (i + 1), z0 + nz)):
            zn = min(z + 1, vz - 1)
            for y in range(y0, y0 + ny):
                yn = min(y + 1, vy - 1)
                j = (y - y0) // size
                for k in range(cx):
                    dz = out[i, j, k, 0]
                    dy = out[i, j, k, 1]
                    dx = out[i, j, k, 2]
                    lo = out[i, j, k, 3]
                    hi = out[i, j, k, 4]
                    for x in range(x0 + size * k, min(x0 + size * (k + 1), x0 + nx)):
                        v = _value(src, z, y, x, match, offset)
                        dz = max(dz, abs(_value(src, zn, y, x, match, offset) - v))
                        dy = max(dy, abs(_value(src, z, yn, x, match, offset) - v))
                        xn = min(x + 1, vx - 1)
                        dx = max(dx, abs(_value(src, z, y, xn, match, offset) - v))
                        lo = min(lo, v)
                        hi = max(hi, v)
                    out[i, j, k, 0] = dz
                    out[i, j, k, 1] = dy
                    out[i, j, k, 2] = dx
                    out[i, j, k, 3] = lo
                    out[i, j, k, 4] = hi


@njit(parallel=True, cache=True)
def cells_gradient_max(src, match, offset, cells, kz0, kz1, ky0, ky1, kx0, kx1, inv, out):
    """Exact ``max |grad f|^2`` (world units) over each cell ``[z0, z1, y0, y1, x0, x1)``.

    Same filters as :func:`xy_pass` and :func:`z_points` (orders 0 and 1 only); indices are
    clamped to the volume.
    """
    vz, vy, vx = src.shape
    rz = kz0.size - 1
    ry = ky0.size - 1
    rx = kx0.size - 1
    for c in prange(cells.shape[0]):
        z0, z1, y0, y1, x0, x1 = (
            cells[c, 0],
            cells[c, 1],
            cells[c, 2],
            cells[c, 3],
            cells[c, 4],
            cells[c, 5],
        )
        nz = z1 - z0 + 2 * rz
        ny = y1 - y0 + 2 * ry
        nx = x1 - x0
        xa = np.empty((2, nz, ny, nx), np.float32)
        pad = np.empty(nx + 2 * rx, np.float32)
        for kz in range(nz):
            z = min(max(z0 - rz + kz, 0), vz - 1)
            for ky in range(ny):
                y = min(max(y0 - ry + ky, 0), vy - 1)
                for i in range(nx + 2 * rx):
                    pad[i] = _value(src, z, y, min(max(x0 - rx + i, 0), vx - 1), match, offset)
                for i in range(nx):
                    ci = i + rx
                    s0 = kx0[0] * pad[ci]
                    s1 = np.float32(0.0)
                    for t in range(1, rx + 1):
                        s0 += kx0[t] * (pad[ci + t] + pad[ci - t])
                        s1 += kx1[t] * (pad[ci + t] - pad[ci - t])
                    xa[0, kz, ky, i] = s0
                    xa[1, kz, ky, i] = s1
        ya = np.empty((3, nz, y1 - y0, nx), np.float32)
        for kz in range(nz):
            for j in range(y1 - y0):
                ky = j + ry
                for i in range(nx):
                    a00 = ky0[0] * xa[0, kz, ky, i]
                    a01 = ky0[0] * xa[1, kz, ky, i]
                    a10 = np.float32(0.0)
                    for t in range(1, ry + 1):
                        yp = min(ky + t, ny - 1)
                        ym = max(ky - t, 0)
                        # rows outside the volume were clamped when xa was filled
                        a00 += ky0[t] * (xa[0, kz, yp, i] + xa[0, kz, ym, i])
                        a01 += ky0[t] * (xa[1, kz, yp, i] + xa[1, kz, ym, i])
                        a10 += ky1[t] * (xa[0, kz, yp, i] - xa[0, kz, ym, i])
                    ya[0, kz, j, i] = a00
                    ya[1, kz, j, i] = a01
                    ya[2, kz, j, i] = a10
        best = 0.0
        for k in range(z1 - z0):
            kz = k + rz
            for j in range(y1 - y0):
                for i in range(nx):
                    gz = 0.0
                    gy = np.float64(kz0[0]) * ya[2, kz, j, i]
                    gx = np.float64(kz0[0]) * ya[1, kz, j, i]
                    for t in range(1, rz + 1):
                        gz += np.float64(kz1[t]) * (
                            np.float64(ya[0, kz + t, j, i]) - ya[0, kz - t, j, i]
                        )
                        gy += np.float64(kz0[t]) * (
                            np.float64(ya[2, kz + t, j, i]) + ya[2, kz - t, j, i]
                        )
                        gx += np.float64(kz0[t]) * (
                            np.float64(ya[1, kz + t, j, i]) + ya[1, kz - t, j, i]
                        )
                    gz *= inv[0]
                    gy *= inv[1]
                    gx *= inv[2]
                    best = max(best, gz * gz + gy * gy + gx * gx)
        out[c] = best
