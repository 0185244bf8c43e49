"""The slice-by-slice engine of :func:`dvr_perception.rays.curvature.curvature_volume`.

A block (the extent plus the filters' ghost) is streamed in z slices: each slice is
classified and its boundary voxels found (:func:`_pass_boundary`), filtered along x and y into
a ring of slices, and the derivatives along z are finished at the boundary voxels only
(:func:`_field_pass`); :func:`_gradient_max` bounds and finds the largest gradient by branch
and bound.  Every step has a numba kernel (``nk``, :mod:`dvr_perception.rays._curvature_kernels`)
and a numpy twin used without numba.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.classify import _classify, _label_structures, _lookup_table

#: Gaussian kernels are cut at this many sigmas.
_TRUNCATE = 3.5
#: ``|grad f|`` at most this fraction of the field's maximum is "flat" (``H`` undefined, 0).
_MIN_GRADIENT = 1e-4
_TINY = float(np.finfo(np.float32).tiny)
#: Side of the cells of the branch and bound of the gradient maximum.
_CELL = 16


def _kernel(sigma: float, order: int) -> np.ndarray:
    """Return a sampled Gaussian (derivative) kernel for ``correlate1d``, exact on quadratics.

    The sampled derivative-of-Gaussian kernels are rescaled so that they reproduce the first
    and second derivatives of low-order polynomials exactly; for small ``sigma`` they tend to
    the central differences ``[-1/2, 0, 1/2]`` and ``[1, -2, 1]``.
    """
    radius = max(1, math.ceil(_TRUNCATE * sigma))
    j = np.arange(-radius, radius + 1, dtype=np.float64)
    phi = np.exp(-0.5 * (j / sigma) ** 2)
    if order == 0:
        w = phi / phi.sum()
    elif order == 1:
        w = j * phi
        w /= np.sum(w * j)
    else:
        w = (j**2 - np.sum(j**2 * phi) / phi.sum()) * phi
        w *= 2.0 / np.sum(w * j**2)
    return w.astype(np.float32)


def _axis_sigmas(sigma: float, spacing) -> tuple[float, float, float]:
    """Gaussian sigma in voxels per array axis (z, y, x): isotropic in world space."""
    sx, sy, sz = spacing
    step = min(spacing) * sigma
    return (step / sz, step / sy, step / sx)


def _radius(sigma_voxels: float) -> int:
    return max(1, math.ceil(_TRUNCATE * sigma_voxels))


@dataclass
class _Field:
    """A scalar field whose iso-surface curvature is taken: the data or a label indicator."""

    key: int | None  # None: the data; else the label structure's index
    src: np.ndarray  # volume.data or volume.labels
    match: int  # -1: src - offset; else the indicator src == match
    offset: float
    gradient_max: float | None = None
    bound2: float = 0.0  # an upper bound of gradient_max ** 2

    def slice(self, z: int, ys: slice, xs: slice) -> np.ndarray:
        if self.match >= 0:
            a = (self.src[z, ys, xs] == self.match).astype(np.float32)
        else:
            a = self.src[z, ys, xs].astype(np.float32)
        a -= np.float32(self.offset)
        return a


class _Geometry:
    """Kernels, radii and the block (extent plus ghost, clipped to the volume) of a run."""

    def __init__(self, shape, spacing, sigma: float, extent):
        self.shape = shape
        self.sigmas = _axis_sigmas(sigma, spacing)
        self.radii = tuple(_radius(s) for s in self.sigmas)  # z, y, x
        sx, sy, sz = spacing
        self.inv = np.array([1.0 / sz, 1.0 / sy, 1.0 / sx])
        self.full = [[_kernel(s, o) for o in range(3)] for s in self.sigmas]
        self.half = [
            [w[r:].copy() for w in ws] for ws, r in zip(self.full, self.radii, strict=True)
        ]
        self.extent = extent
        self.block = tuple(
            (max(0, a - r - 1), min(n, b + r + 1))
            for (a, b), r, n in zip(extent, self.radii, shape, strict=True)
        )

    def with_extent(self, extent) -> _Geometry:
        """Return the same geometry for another extent."""
        geo = copy.copy(self)
        geo.extent = extent
        geo.block = tuple(
            (max(0, a - r - 1), min(n, b + r + 1))
            for (a, b), r, n in zip(extent, self.radii, self.shape, strict=True)
        )
        return geo

    @property
    def window(self):
        """The extent in block coordinates, as slices (y, x) of a block slice."""
        (_, _), (ey0, ey1), (ex0, ex1) = self.extent
        by0, bx0 = self.block[1][0], self.block[2][0]
        return slice(ey0 - by0, ey1 - by0), slice(ex0 - bx0, ex1 - bx0)

    @property
    def yx(self):
        """The block's (y, x) slices of a volume slice."""
        return slice(*self.block[1]), slice(*self.block[2])


def _check_extent(extent, shape) -> tuple:
    if extent is None:
        return tuple((0, n) for n in shape)
    try:
        ext = tuple((int(a), int(b)) for a, b in extent)
        ok = len(ext) == 3 and all(float(a) == int(a) and float(b) == int(b) for a, b in extent)
    except (TypeError, ValueError):
        ok = False
    if not ok or not all(0 <= a < b <= n for (a, b), n in zip(ext, shape, strict=True)):
        raise DVRInputError(
            "curvature_volume: extent must be ((z0, z1), (y0, y1), (x0, x1)) with "
            f"0 <= z0 < z1 <= {shape[0]}, 0 <= y0 < y1 <= {shape[1]}, 0 <= x0 < x1 <= "
            f"{shape[2]} (half-open voxel ranges), got {extent!r}"
        )
    return ext


def _boundary_numpy(prev, cur, nxt, wy: slice, wx: slice) -> np.ndarray:
    """Boundary mask of the window ``(wy, wx)`` of slice ``cur`` (numpy twin of the kernel)."""
    diff = np.zeros(cur.shape, bool)
    d = cur[:, 1:] != cur[:, :-1]
    diff[:, 1:] |= d
    diff[:, :-1] |= d
    d = cur[1:] != cur[:-1]
    diff[1:] |= d
    diff[:-1] |= d
    for other in (prev, nxt):
        if other is not None:
            diff |= cur != other
    return diff[wy, wx]


def _row_ranges(mask: np.ndarray, x_first: int) -> tuple[np.ndarray, np.ndarray]:
    """First and last x (block coordinates) of each row of ``mask`` (lo > hi when none)."""
    any_ = mask.any(axis=1)
    lo = np.where(any_, np.argmax(mask, axis=1) + x_first, 1 << 30)
    hi = np.where(any_, mask.shape[1] - 1 - np.argmax(mask[:, ::-1], axis=1) + x_first, -1)
    return lo.astype(np.int64), hi.astype(np.int64)


def _pass_boundary(volume, spec, geo: _Geometry, nk, boundary: np.ndarray, tick=None):
    """Classify and find the boundary voxels of the extent, slice by slice.

    Fills ``boundary`` and returns, per field key, the x ranges of its points per extent slice
    and block row, and the points of the label fields per extent slice (window flat indices).
    ``tick()`` is called after each slice.
    """
    (ez0, ez1), _, _ = geo.extent
    nz = geo.shape[0]
    yx = geo.yx
    wy, wx = geo.window
    nyb = yx[0].stop - yx[0].start
    labels = volume.labels
    labelled = _label_structures(spec)
    range_ids = [k for k, s in enumerate(spec.structures) if s.range is not None]
    # label structures that own their label (a later one with the same label takes it)
    owners = [
        (lab, k)
        for n, (lab, k) in enumerate(labelled)
        if lab not in [m for m, _ in labelled[n + 1 :]]
    ]
    nze = ez1 - ez0
    big = 1 << 30
    rowlo = np.full((nze, nyb), big, np.int64)
    rowhi = np.full((nze, nyb), -1, np.int64)
    label_points: dict[int, dict[int, np.ndarray]] = {k: {} for _, k in owners}
    ids_cache: dict[int, np.ndarray] = {}
    lut = _lookup_table(spec, volume.data.dtype)

    def ids_of(z):
        if z not in ids_cache:
            lab = labels[z][yx] if labels is not None else None
            ids_cache[z] = _classify(volume.data[z][yx], lab, spec, nk, lut)
            for old in [k for k in ids_cache if k < z - 1]:
                del ids_cache[old]
        return ids_cache[z]

    for z in range(ez0, ez1):
        if tick is not None:
            tick()
        prev = ids_of(z - 1) if z > 0 else None
        nxt = ids_of(z + 1) if z + 1 < nz else None
        cur = ids_of(z)
        out = boundary[z - ez0]
        j0 = wy.start
        if nk is not None:
            lo = np.empty(wy.stop - wy.start, np.int64)
            hi = np.empty(wy.stop - wy.start, np.int64)
            dummy = cur
            nk.boundary_slice(
                prev if prev is not None else dummy,
                cur,
                nxt if nxt is not None else dummy,
                prev is not None,
                nxt is not None,
                wy.start,
                wx.start,
                out,
                lo,
                hi,
            )
        else:
            out[...] = _boundary_numpy(prev, cur, nxt, wy, wx)
            lo, hi = _row_ranges(out, wx.start)
        rowlo[z - ez0, j0 : wy.stop] = lo
        rowhi[z - ez0, j0 : wy.stop] = hi
        if not owners or not out.any():
            continue
        in_range = np.isin(cur[wy, wx], range_ids)
        owner = np.full(out.shape, -1, np.int32)
        for _, k in owners:
            own = cur == k
            near = own.copy()
            near[1:] |= own[:-1]
            near[:-1] |= own[1:]
            near[:, 1:] |= own[:, :-1]
            near[:, :-1] |= own[:, 1:]
            for other in (prev, nxt):
                if other is not None:
                    near |= other == k
            near = near[wy, wx] & out & (own[wy, wx] | ~in_range)
            owner[near] = k
        for _, k in owners:
            idx = np.flatnonzero(owner == k)
            if idx.size:
                label_points[k][z - ez0] = idx
    return rowlo, rowhi, label_points


def _label_ranges(points: dict, nze: int, nyb: int, wy: slice, wx: slice, width: int):
    big = 1 << 30
    lo = np.full((nze, nyb), big, np.int64)
    hi = np.full((nze, nyb), -1, np.int64)
    for z, idx in points.items():
        rows = idx // width + wy.start
        xs = idx % width + wx.start
        np.minimum.at(lo[z], rows, xs)
        np.maximum.at(hi[z], rows, xs)
    return lo, hi


def _xy_numpy(src: np.ndarray, geo: _Geometry) -> np.ndarray:
    """Return the y pass of ``xy_pass`` on the whole slice, with ``scipy.ndimage``."""
    (ky, kx) = geo.full[1], geo.full[2]

    def c(a, w, axis):
        return ndimage.correlate1d(a, w, axis=axis, mode="nearest")

    x = [c(src, kx[o], 1) for o in range(3)]
    return np.stack(
        [
            c(x[0], ky[0], 0),
            c(x[1], ky[0], 0),
            c(x[2], ky[0], 0),
            c(x[0], ky[1], 0),
            c(x[1], ky[1], 0),
            c(x[0], ky[2], 0),
        ]
    )


def _z_numpy(ring, slots, ys, xs, geo: _Geometry):
    """Return what ``z_points`` gives, with numpy."""
    rz = geo.radii[0]
    kz = [w.astype(np.float64) for w in geo.full[0]]
    vals = ring[slots][:, :, ys, xs].astype(np.float64)  # [2 rz + 1, 6, points]
    y00, y01, y02, y10, y11, y20 = (vals[:, c] for c in range(6))
    assert vals.shape[0] == 2 * rz + 1

    def zc(w, a):
        return np.tensordot(w, a, axes=(0, 0))

    d001, d002, d010 = zc(kz[0], y01), zc(kz[0], y02), zc(kz[0], y10)
    d011, d020 = zc(kz[0], y11), zc(kz[0], y20)
    d100, d101, d110, d200 = zc(kz[1], y00), zc(kz[1], y01), zc(kz[1], y10), zc(kz[2], y00)
    iz, iy, ix = geo.inv
    gz, gy, gx = d100 * iz, d010 * iy, d001 * ix
    hzz, hyy, hxx = d200 * iz * iz, d020 * iy * iy, d002 * ix * ix
    hzy, hzx, hyx = d110 * iz * iy, d101 * iz * ix, d011 * iy * ix
    num = -(gz * gz * (hyy + hxx) + gy * gy * (hzz + hxx) + gx * gx * (hzz + hyy))
    num += 2.0 * (gz * gy * hzy + gz * gx * hzx + gy * gx * hyx)
    return num, gz * gz + gy * gy + gx * gx


def _field_pass(fld: _Field, geo: _Geometry, nk, rowlo, rowhi, points_of, emit,
                tick=None) -> None:  # fmt: skip
    """Stream the block's slices through the in-plane passes and finish the points along z.

    ``points_of(k)`` gives the points (block rows, block columns) of extent slice ``k``;
    ``emit(k, ys, xs, num, mag2)`` receives them with their numerator and ``|grad f|^2``;
    ``tick()`` is called after each slice with points.
    """
    (ez0, ez1), _, _ = geo.extent
    bz0, bz1 = geo.block[0]
    nzb = bz1 - bz0
    rz, ry, _ = geo.radii
    yx = geo.yx
    nyb = yx[0].stop - yx[0].start
    nxb = yx[1].stop - yx[1].start
    nze = ez1 - ez0
    z_first = ez0 - bz0
    nring = 2 * rz + 1
    ring = np.zeros((nring, 6, nyb, nxb), np.float32)
    if nk is not None:
        shape2 = (nzb, nyb)
        ylo, yhi = np.empty(shape2, np.int64), np.empty(shape2, np.int64)
        xlo, xhi = np.empty(shape2, np.int64), np.empty(shape2, np.int64)
        nk.need_ranges(rowlo, rowhi, z_first, nzb, rz, ry, ylo, yhi, xlo, xhi)
        xbuf = np.zeros((3, nyb, nxb), np.float32)
        dbuf = np.zeros((9, nyb, nxb), np.float32)
        needed = (ylo <= yhi).any(axis=1)
    else:
        has = (rowlo <= rowhi).any(axis=1)
        needed = np.zeros(nzb, bool)
        for k in np.flatnonzero(has):
            z = z_first + k
            needed[max(0, z - rz) : min(nzb - 1, z + rz) + 1] = True
    pending = [k for k in range(nze) if (rowlo[k] <= rowhi[k]).any()]
    p = 0
    for zb in range(max(0, z_first - rz), min(nzb - 1, z_first + nze - 1 + rz) + 1):
        if needed[zb]:
            src = fld.slice(bz0 + zb, *yx)
            if nk is not None:
                hx, hy = geo.half[2], geo.half[1]
                nk.xy_pass(
                    src, xlo[zb], xhi[zb], ylo[zb], yhi[zb], *hx, *hy, xbuf, ring[zb % nring]
                )
            else:
                ring[zb % nring] = _xy_numpy(src, geo)
        while p < len(pending) and min(nzb - 1, z_first + pending[p] + rz) <= zb:
            k = pending[p]
            z = z_first + k
            slots = np.array(
                [min(max(z + dz, 0), nzb - 1) % nring for dz in range(-rz, rz + 1)], np.int64
            )
            ys, xs = points_of(k)
            if ys.size:
                if nk is not None:
                    num = np.empty(ys.size)
                    mag2 = np.empty(ys.size)
                    hz = geo.half[0]
                    nk.z_pass(ring, slots, rowlo[k], rowhi[k], hz[0], hz[1], hz[2], dbuf)
                    nk.z_points(dbuf, ys, xs, geo.inv, num, mag2)
                else:
                    num, mag2 = _z_numpy(ring, slots, ys, xs, geo)
                emit(k, ys, xs, num, mag2)
            p += 1
            if tick is not None:
                tick()


def _cell_diffs_numpy(fld: _Field, org, ncell, size: int) -> np.ndarray:
    """Return what ``cell_diffs`` gives, with numpy (a slab of cells at a time)."""
    vz, vy, vx = fld.src.shape
    out = np.zeros((*ncell, 5), np.float32)
    ys = slice(org[1], min(vy, org[1] + size * ncell[1]))
    xs = slice(org[2], min(vx, org[2] + size * ncell[2]))
    for i in range(ncell[0]):
        z0 = org[0] + size * i
        z1 = min(vz, z0 + size)
        zs = range(z0, min(vz, z1 + 1))
        f = np.stack([fld.slice(z, slice(ys.start, min(vy, ys.stop + 1)), xs) for z in zs])
        xs1 = slice(xs.start, min(vx, xs.stop + 1))
        fx = np.stack([fld.slice(z, ys, xs1) for z in range(z0, z1)])
        diffs = [
            np.abs(np.diff(f, axis=0))[: z1 - z0, : ys.stop - ys.start],
            np.abs(np.diff(f[: z1 - z0], axis=1))[:, : ys.stop - ys.start],
            np.abs(np.diff(fx, axis=2))[:, :, : xs.stop - xs.start],
        ]
        own = f[: z1 - z0, : ys.stop - ys.start]  # the cells' voxels
        for a, (d, fill, pick) in enumerate(
            [(d, 0.0, np.max) for d in diffs] + [(own, np.inf, np.min), (-own, np.inf, np.min)]
        ):
            pad = np.full((size, size * ncell[1], size * ncell[2]), fill, np.float32)
            pad[: d.shape[0], : d.shape[1], : d.shape[2]] = d
            cells = pick(pad.reshape(size, ncell[1], size, ncell[2], size), axis=(0, 2, 4))
            out[i, :, :, a] = cells if a < 4 else -cells
    return out


def _cells_gradient_max_numpy(fld: _Field, geo: _Geometry, boxes) -> np.ndarray:
    """Return what ``cells_gradient_max`` gives, with ``scipy.ndimage``."""
    vz, vy, vx = fld.src.shape
    kz, ky, kx = geo.full
    out = np.zeros(len(boxes))
    for n, (z0, z1, y0, y1, x0, x1) in enumerate(boxes):
        rz, ry, rx = geo.radii
        zi = np.clip(np.arange(z0 - rz, z1 + rz), 0, vz - 1)
        yi = np.clip(np.arange(y0 - ry, y1 + ry), 0, vy - 1)
        xi = np.clip(np.arange(x0 - rx, x1 + rx), 0, vx - 1)
        f = np.stack([fld.slice(int(z), slice(0, vy), slice(0, vx))[np.ix_(yi, xi)] for z in zi])
        g = 0.0
        for a in range(3):
            d = f
            for axis, ks in enumerate((kz, ky, kx)):
                d = ndimage.correlate1d(d, ks[1 if axis == a else 0], axis=axis, mode="nearest")
            d = d[rz : rz + z1 - z0, ry : ry + y1 - y0, rx : rx + x1 - x0].astype(np.float64)
            g = g + (d * geo.inv[a]) ** 2
        out[n] = float(np.max(g))
    return out


def _cell_bounds(diffs: np.ndarray, geo: _Geometry) -> np.ndarray:
    """Upper bound of ``|grad f|^2`` (world units) in every cell, from :func:`cell_diffs`.

    A voxel's filters reach ``r`` voxels, so the cells' neighbour differences ``D`` and value
    ranges are dilated over the cells in reach.  The derivative along an axis is ``sum_t
    w_t (S(v + t) - S(v - t))`` (``t > 0``, ``w_t > 0``, ``S`` the data smoothed across:
    a convex combination of values), and ``|S(v + t) - S(v - t)|`` is at most the value
    range ``R`` and at most ``2 t D``: the derivative is at most ``sum_t w_t min(R, 2 t D)``
    (``D`` itself for a ramp, where ``sum_t 2 t w_t = 1``; about a third of ``R`` across a
    step, where ``D`` alone would give ``R``).  A margin of ``1e-5`` times the largest
    magnitude covers the float32 rounding of the filters.
    """
    reach = [2 * math.ceil(r / _CELL) + 1 for r in geo.radii]
    near = ndimage.maximum_filter(diffs[..., :3], size=(*reach, 1), mode="constant", cval=0.0)
    lo = ndimage.minimum_filter(diffs[..., 3], size=reach, mode="constant", cval=np.inf)
    hi = ndimage.maximum_filter(diffs[..., 4], size=reach, mode="constant", cval=-np.inf)
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    span = hi - lo
    margin = 1e-5 * np.maximum(np.abs(lo), np.abs(hi))
    bound2 = np.zeros(span.shape)
    for a in range(3):
        w = geo.half[a][1].astype(np.float64)  # w[t], t = 0..r (w[0] = 0)
        d = near[..., a].astype(np.float64)
        b = sum(w[t] * (np.minimum(span, 2.0 * t * d) + margin) for t in range(1, w.size))
        bound2 += (b * geo.inv[a]) ** 2
    return bound2 * (1 + 1e-5)


def _gradient_max(fld: _Field, geo: _Geometry, nk, lower: float = 0.0, floor: float = 0.0):
    """Largest ``|grad f|`` over ``geo``'s extent, exact when it is at least ``floor``.

    Branch and bound over cells of 16³ voxels: the largest neighbour difference ``D`` along an
    axis and the value range in a cell's reach bound that derivative (:func:`_cell_bounds`);
    cells are filtered exactly in order of decreasing bound until the bound is below the best
    value found (or ``floor``).  ``lower`` is a known lower bound (a gradient seen elsewhere).
    """
    (ez0, ez1), (ey0, ey1), (ex0, ex1) = geo.extent
    c = _CELL
    lo = [max(0, a - r) for (a, _), r in zip(geo.extent, geo.radii, strict=True)]
    hi = [min(n, b + r) for (_, b), r, n in zip(geo.extent, geo.radii, geo.shape, strict=True)]
    org = lo
    ncell = [math.ceil((h - o) / c) for o, h in zip(org, hi, strict=True)]
    if nk is not None:
        diffs = np.zeros((*ncell, 5), np.float32)
        sizes = [min(h, o + c * n) - o for o, h, n in zip(org, hi, ncell, strict=True)]
        nk.cell_diffs(fld.src, fld.match, np.float32(fld.offset), c, *org, *sizes, diffs)
    else:
        diffs = _cell_diffs_numpy(fld, org, ncell, c)
    bound2 = _cell_bounds(diffs, geo)
    cells = []
    for i, j, k in zip(*np.nonzero(bound2 > max(lower, floor) ** 2), strict=True):
        z0, y0, x0 = org[0] + c * i, org[1] + c * j, org[2] + c * k
        box = (max(z0, ez0), min(z0 + c, ez1), max(y0, ey0), min(y0 + c, ey1))
        box += (max(x0, ex0), min(x0 + c, ex1))
        if box[0] < box[1] and box[2] < box[3] and box[4] < box[5]:
            cells.append((float(bound2[i, j, k]), box))
    cells.sort(key=lambda t: -t[0])
    best2 = lower * lower
    floor2 = floor * floor
    batch = 8
    hz, hy, hx = geo.half
    n = 0
    while n < len(cells) and cells[n][0] > max(best2, floor2):
        take = [box for b2, box in cells[n : n + batch] if b2 > max(best2, floor2)]
        if nk is not None:
            out = np.zeros(len(take))
            nk.cells_gradient_max(
                fld.src,
                fld.match,
                np.float32(fld.offset),
                np.array(take, np.int64),
                hz[0],
                hz[1],
                hy[0],
                hy[1],
                hx[0],
                hx[1],
                geo.inv,
                out,
            )
        else:
            out = _cells_gradient_max_numpy(fld, geo, take)
        best2 = max(best2, float(out.max()))
        n += batch
    return math.sqrt(best2)


def _chunk(volume, spec, geo: _Geometry, nk, fields, out, boundary, tick=None) -> list:
    """Boundary and ``|H|`` of one z chunk; per field, what :func:`_field_curvature` returns.

    ``out[k]`` is the plane of extent slice ``k`` that ``|H|`` is written to (an array's,
    or a :class:`~dvr_perception.rays._curvature_pages.BandPages`'); ``boundary`` is filled.
    """
    rowlo, rowhi, label_points = _pass_boundary(volume, spec, geo, nk, boundary, tick)
    res = [(0.0, []) for _ in fields]
    if not boundary.any():
        return res
    wy, wx = geo.window
    width = wx.stop - wx.start
    nze, nyb = rowlo.shape
    for n, fld in enumerate(fields):
        if fld.key is None:

            def points_of(k):
                mask = boundary[k]
                if any(k in d for d in label_points.values()):
                    mask = mask.copy()
                    for d in label_points.values():
                        if k in d:
                            mask.flat[d[k]] = False
                if nk is not None:
                    return nk.mask_points(mask, wy.start, wx.start)
                ys, xs = np.nonzero(mask)
                return ys + wy.start, xs + wx.start

            ranges = (rowlo, rowhi)
        else:
            own = label_points[fld.key]
            if not own:
                continue

            def points_of(k, own=own):
                idx = own.get(k, np.zeros(0, np.int64))
                return idx // width + wy.start, idx % width + wx.start

            ranges = _label_ranges(own, nze, nyb, wy, wx, width)
        res[n] = _field_curvature(fld, geo, nk, ranges, points_of, out, tick)
    return res


def _field_curvature(fld: _Field, geo: _Geometry, nk, ranges, points_of, out, tick=None):
    """Write ``|H|`` of one field at its points into ``out``, testing flatness when possible.

    Returns the largest ``|grad f|^2`` seen and the points that may be flat (slice, ys, xs,
    ``|grad f|^2``) when the field's gradient maximum is not known.
    """
    wy, wx = geo.window
    known = fld.gradient_max is not None
    thr = max(_MIN_GRADIENT**2 * fld.gradient_max**2, _TINY) if known else _TINY
    thr_hi = max(_MIN_GRADIENT**2 * fld.bound2, _TINY)
    seen = 0.0
    maybe = []
    mark = getattr(out, "mark", None)  # a band's pages note the values they are given

    def emit(k, ys, xs, num, mag2):
        nonlocal seen
        ys = ys - wy.start
        xs = xs - wx.start
        if nk is not None:  # the numbers below, point by point
            cand = np.empty(num.size, np.bool_)
            top = nk.write_curvature(num, mag2, ys, xs, thr, thr_hi, out[k], cand)
            if mark is not None:
                mark(k, ys, xs)
            if not known:
                seen = max(seen, top)
                if cand.any():
                    maybe.append((k, ys[cand], xs[cand], mag2[cand]))
            return
        flat = mag2 <= thr
        safe = np.where(flat, 1.0, mag2)
        h = np.abs(num) / (2.0 * safe * np.sqrt(safe))
        h[flat] = 0.0
        out[k][ys, xs] = h  # out[k]: a plane of an array, or of a band's pages
        if not known:
            seen = max(seen, float(mag2.max()))
            cand = (mag2 <= thr_hi) & ~flat
            if cand.any():
                maybe.append((k, ys[cand], xs[cand], mag2[cand]))

    _field_pass(fld, geo, nk, *ranges, points_of, emit, tick)
    return seen, maybe


def _resolve_flat(fld: _Field, geo: _Geometry, nk, seen: float, maybe: list, zero) -> None:
    """Zero the possibly flat points that are flat: ``|grad f| <= 1e-4 * gradient_max``.

    ``zero(k, ys, xs)`` sets the points ``(ys, xs)`` of extent slice ``k`` to 0 (they come
    from one band of :func:`~dvr_perception.rays.curvature.curvature_volume`).

    ``seen`` (the largest ``|grad f|^2`` of the points) is a lower bound of the maximum; only
    when a point lies above ``1e-4`` times it is the maximum itself searched for, and only as
    far as needed (:func:`_gradient_max` with the smallest undecided gradient as floor).
    """
    if not maybe:
        return
    mag2 = np.concatenate([m[3] for m in maybe])
    undecided = mag2 > max(_MIN_GRADIENT**2 * seen, _TINY)
    gmax2 = seen
    if undecided.any():
        floor = math.sqrt(float(mag2[undecided].min())) / _MIN_GRADIENT
        whole = geo.with_extent(tuple((0, n) for n in geo.shape))
        gmax2 = _gradient_max(fld, whole, nk, math.sqrt(seen), floor) ** 2
    thr = max(_MIN_GRADIENT**2 * gmax2, _TINY)
    for k, ys, xs, m in maybe:
        flat = m <= thr
        if flat.any():
            zero(k, ys[flat], xs[flat])
