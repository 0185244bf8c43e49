"""numba twins of the per-volume arrays of :mod:`dvr_perception.rays._grid`.

Each kernel computes exactly what its numpy original does, value for value (the same float32
and float64 operations in the same order, no fast-math), one z-plane per parallel work item:
:func:`index_volume`, :func:`normal_codes`, :func:`cell_classes` and, fused, the voxel
records where shading reads them (:func:`records_where`).  Tested equal on every
shared volume (``tests/rays/test_grid_numba.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = [
    "block_occupancy",
    "cell_classes",
    "empty_blocks",
    "index_volume",
    "normal_codes",
    "page_fill",
    "page_flags",
    "page_read",
    "records_where",
    "structure_blocks",
]

_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0
_RAD2DEG = 180.0 / math.pi
_ZERO_CODE = 255 * 256


@njit(parallel=True, cache=True)
def index_volume(data, lo, scale, size, out):
    """``clip(floor((v - lo) * scale), 0, size - 1)`` per voxel, as uint16."""
    nz, ny, nx = data.shape
    top = float(size - 1)
    for z in prange(nz):
        for y in range(ny):
            for x in range(nx):
                v = math.floor((np.float64(data[z, y, x]) - lo) * scale)
                out[z, y, x] = np.uint16(min(max(v, 0.0), top))


@njit(cache=True, inline="always")
def _code(data, z, y, x, nz, ny, nx, ax, ay, az):
    """One voxel's code, as :func:`normal_codes` computes it."""
    z0 = max(z - 1, 0)
    z1 = min(z + 1, nz - 1)
    y0 = max(y - 1, 0)
    y1 = min(y + 1, ny - 1)
    x0 = max(x - 1, 0)
    x1 = min(x + 1, nx - 1)
    gx = np.float64((np.float32(data[z, y, x0]) - np.float32(data[z, y, x1])) / ax)
    gy = np.float64((np.float32(data[z, y0, x]) - np.float32(data[z, y1, x])) / ay)
    gz = np.float64((np.float32(data[z0, y, x]) - np.float32(data[z1, y, x])) / az)
    mag = math.sqrt(gx * gx + gy * gy + gz * gz)
    if mag == 0.0:
        return _ZERO_CODE
    theta = math.atan2(gy, gx) * _RAD2DEG
    if theta < 0.0:
        theta += 360.0
    phi = math.asin(min(max(gz / mag, -1.0), 1.0)) * _RAD2DEG
    lo = min(max(math.floor(theta * (255.0 / 359.0) + 0.5), 0.0), 255.0)
    hi = min(max(math.floor((phi + 90.0) * (254.0 / 180.0) + 0.5), 0.0), 254.0)
    return np.int64(lo + 256.0 * hi)


@njit(parallel=True, cache=True)
def normal_codes(data, aspect, out):
    """VTK's encoded central-difference normals (``_grid.normal_codes``), uint16 per voxel.

    A missing neighbour at the border is the voxel itself.
    """
    nz, ny, nx = data.shape
    ax, ay, az = aspect[0], aspect[1], aspect[2]
    for zz in prange(nz):
        z = np.int64(zz)
        for y in range(ny):
            for x in range(nx):
                out[z, y, x] = _code(data, z, y, x, nz, ny, nx, ax, ay, az)


@njit(parallel=True, cache=True)
def cell_classes(index, cat, run, labels, has_labels, out):
    """Class of every cell from its 8 corners' table indices (``_grid.cell_map``).

    Per row of cells, the 4 corners shared by neighbouring cells along x are reduced once.
    """
    nz, ny, nx = index.shape
    n = len(cat)
    for zz in prange(nz):
        z = np.int64(zz)
        cmin = np.empty(nx, np.int64)
        cmax = np.empty(nx, np.int64)
        clab = np.zeros(nx, np.bool_)
        for y in range(ny):
            if z == nz - 1 or y == ny - 1:
                for x in range(nx):
                    out[z, y, x] = 0
                continue
            for x in range(nx):
                a = np.int64(index[z, y, x])
                b = np.int64(index[z, y + 1, x])
                c = np.int64(index[z + 1, y, x])
                d = np.int64(index[z + 1, y + 1, x])
                cmin[x] = min(min(a, b), min(c, d))
                cmax[x] = max(max(a, b), max(c, d))
                if has_labels:
                    lab_a = labels[z, y, x] > 0 or labels[z, y + 1, x] > 0
                    clab[x] = lab_a or labels[z + 1, y, x] > 0 or labels[z + 1, y + 1, x] > 0
            for x in range(nx - 1):
                lo = min(cmin[x], cmin[x + 1])
                hi = max(cmax[x], cmax[x + 1])
                klo = min(max(np.int64(math.floor(lo * _W_SCALE + _W_BIAS)) - 2, 0), n - 1)
                khi = min(max(np.int64(math.floor(hi * _W_SCALE + _W_BIAS)) + 1, 0), n - 1)
                if (has_labels and (clab[x] or clab[x + 1])) or run[klo] != run[khi]:
                    out[z, y, x] = 255
                else:
                    out[z, y, x] = cat[klo]
            out[z, y, nx - 1] = 0


@njit(parallel=True, cache=True)
def records_where(data, aspect, index, cells, out):
    """``index | code << 16`` per voxel, the code computed only where shading can read it.

    Shading reads the 8 corners of cells that are not empty (``cells`` != 0); every other
    voxel gets the zero-gradient code.
    """
    nz, ny, nx = data.shape
    ax, ay, az = aspect[0], aspect[1], aspect[2]
    for zz in prange(nz):
        z = np.int64(zz)
        for y in range(ny):
            for x in range(nx):
                need = False
                for cz in range(max(z - 1, 0), z + 1):
                    for cy in range(max(y - 1, 0), y + 1):
                        for cx in range(max(x - 1, 0), x + 1):
                            if cells[cz, cy, cx] != 0:
                                need = True
                code = _ZERO_CODE
                if need:
                    code = _code(data, z, y, x, nz, ny, nx, ax, ay, az)
                out[z, y, x] = np.uint32(index[z, y, x]) | (np.uint32(code) << np.uint32(16))


@njit(parallel=True, cache=True)
def structure_blocks(index, run, run_bits, bits, labels, has_labels, lab_base, last, out):
    """Per block of 4^3 cells, the structures its samples can reach (``_grid.structure_blocks``).

    The extremes of the voxels ``4 b .. 4 b + 4`` per axis, widened as ``cell_classes`` widens
    them and clamped to ``last``, select runs of table entries; their bits, with the bits of
    the label entries of those voxels, are ORed.
    """
    nz, ny, nx = index.shape
    bz, by, bx = out.shape
    for zb in prange(bz):
        for yb in range(by):
            for xb in range(bx):
                lo = np.int64(1) << 40
                hi = np.int64(-1)
                m = np.uint32(0)
                for z in range(4 * zb, min(4 * zb + 5, nz)):
                    for y in range(4 * yb, min(4 * yb + 5, ny)):
                        for x in range(4 * xb, min(4 * xb + 5, nx)):
                            v = np.int64(index[z, y, x] & 0xFFFF)  # (or a record)
                            lo = min(lo, v)
                            hi = max(hi, v)
                            if has_labels:
                                lv = np.int64(labels[z, y, x])
                                if lv > 0:
                                    m |= bits[lab_base + lv - 1]
                if hi >= 0:
                    klo = min(max(np.int64(math.floor(lo * _W_SCALE + _W_BIAS)) - 2, 0), last)
                    khi = min(max(np.int64(math.floor(hi * _W_SCALE + _W_BIAS)) + 1, 0), last)
                    for q in range(run[klo], run[khi] + 1):
                        m |= run_bits[q]
                out[zb, yb, xb] = m


@njit(parallel=True, cache=True)
def page_flags(dense, flags):
    """``flags[q, r, c] = 1`` where the 8^3 page ``(q, r, c)`` of ``dense`` holds a non-zero."""
    nz, ny, nx = dense.shape
    for q in prange(flags.shape[0]):
        for z in range(q * 8, min(q * 8 + 8, nz)):
            for y in range(ny):
                r = y >> 3
                for x in range(nx):
                    if dense[z, y, x] != 0.0:
                        flags[q, r, x >> 3] = 1


@njit(parallel=True, cache=True)
def page_fill(dense, index, pages):
    """Copy ``dense`` into its numbered pages (``index`` -1: not kept)."""
    nz, ny, nx = dense.shape
    for q in prange(index.shape[0]):
        for z in range(q * 8, min(q * 8 + 8, nz)):
            dz = z - q * 8
            for y in range(ny):
                r, dy = y >> 3, y & 7
                for c in range(index.shape[2]):
                    p = index[q, r, c]
                    if p >= 0:
                        for x in range(c * 8, min(c * 8 + 8, nx)):
                            pages[p, dz, dy, x - c * 8] = dense[z, y, x]


@njit(parallel=True, cache=True)
def page_read(index, pages, z0, y0, x0, out):
    """``out`` = the paged volume on the voxels from ``(z0, y0, x0)`` on (0 off the pages)."""
    for i in prange(out.shape[0]):
        z = z0 + i
        for j in range(out.shape[1]):
            y = y0 + j
            for k in range(out.shape[2]):
                x = x0 + k
                p = index[z >> 3, y >> 3, x >> 3]
                out[i, j, k] = pages[p, z & 7, y & 7, x & 7] if p >= 0 else 0.0


@njit(parallel=True, cache=True)
def empty_blocks(cells, block, out):
    """Whether every cell of each block of ``block**3`` cells is empty (``_grid.block_map``).

    The last plane of each axis holds no cells; a block reaching past the grid counts only its
    cells inside it.
    """
    nz, ny, nx = cells.shape[0] - 1, cells.shape[1] - 1, cells.shape[2] - 1
    bz, by, bx = out.shape
    for zb in prange(bz):
        for yb in range(by):
            for xb in range(bx):
                empty = True
                for z in range(block * zb, min(block * zb + block, nz)):
                    for y in range(block * yb, min(block * yb + block, ny)):
                        for x in range(block * xb, min(block * xb + block, nx)):
                            if cells[z, y, x] != 0:
                                empty = False
                                break
                        if not empty:
                            break
                    if not empty:
                        break
                out[zb, yb, xb] = empty


@njit(parallel=True, cache=True)
def block_occupancy(cells, out):
    """Per block of 4^3 cells, bit ``(z & 3) * 16 + (y & 3) * 4 + (x & 3)`` set where not empty.

    ``out`` (uint64, one per block as ``empty_blocks``' ``out``).  The last plane of each
    axis holds no cells: its bits stay 0.
    """
    nz, ny, nx = cells.shape[0] - 1, cells.shape[1] - 1, cells.shape[2] - 1
    bz, by, bx = out.shape
    one = np.uint64(1)
    for zb in prange(bz):
        for yb in range(by):
            for xb in range(bx):
                m = np.uint64(0)
                for z in range(4 * zb, min(4 * zb + 4, nz)):
                    for y in range(4 * yb, min(4 * yb + 4, ny)):
                        for x in range(4 * xb, min(4 * xb + 4, nx)):
                            if cells[z, y, x] != 0:
                                m |= one << np.uint64(((z & 3) << 4) | ((y & 3) << 2) | (x & 3))
                out[zb, yb, xb] = m
