r"""Mean curvature of iso-surfaces and its restriction to structure boundaries.

The shape measure of the paper (section 4.2) compares the curvature of the structures with the
gradient of the image.  Following Kindlmann et al. (2003), the mean curvature of the iso-surface
through a point of a smooth field ``f`` with gradient ``g`` and Hessian ``Hf`` is

.. math:: H = \frac{g^T Hf\, g - |g|^2 \operatorname{tr}(Hf)}{2 |g|^3},

which is ``1/R`` for a sphere of radius ``R`` (with ``f`` decreasing outwards) and ``1/(2R)``
for a cylinder.  Derivatives are Gaussian derivatives of the data (one separable pass per axis,
shared between derivatives), scaled by the voxel spacing so curvature is in 1/world-units.
Only ``|H|`` is returned, so the orientation convention does not matter.
"""

from __future__ import annotations

import copy
import itertools
import math
import os
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from dvr_perception._numba import kernels
from dvr_perception._progress import reporter
from dvr_perception.errors import DVRCancelled, DVRInputError

__all__ = [
    "CurvatureGlobals",
    "classify_structures",
    "curvature_ghost",
    "curvature_globals",
    "curvature_volume",
    "mean_curvature",
]

_TRUNCATE = 3.5


def _check_spacing(spacing) -> tuple[float, float, float]:
    try:
        sp = tuple(float(s) for s in spacing)
    except (TypeError, ValueError):
        sp = ()
    if len(sp) != 3 or not all(math.isfinite(s) and s > 0 for s in sp):
        raise DVRInputError(
            f"mean_curvature: spacing must be three positive numbers (x, y, z), got {spacing!r}"
        )
    return sp  # type: ignore[return-value]


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


def _derivatives(f: np.ndarray, sigmas: tuple[float, float, float]) -> dict[tuple, np.ndarray]:
    """Gaussian derivatives of orders 1 and 2, keyed by (order_z, order_y, order_x).

    Separable filtering shares the passes along z and y between derivatives: 18 one-dimensional
    passes instead of 27.
    """

    def filt(a: np.ndarray, axis: int, order: int) -> np.ndarray:
        return ndimage.correlate1d(a, _kernel(sigmas[axis], order), axis=axis, mode="nearest")

    out: dict[tuple, np.ndarray] = {}
    for oz in (0, 1, 2):
        fz = filt(f, 0, oz)
        for oy in range(3 - oz):
            fzy = filt(fz, 1, oy)
            for ox in range(3 - oz - oy):
                if oz + oy + ox == 0:
                    continue
                out[(oz, oy, ox)] = filt(fzy, 2, ox)
            del fzy
        del fz
    return out


def _mean_curvature(
    f: np.ndarray, spacing, sigma: float, min_gradient: float, gradient_max=None
) -> np.ndarray:
    sx, sy, sz = spacing
    step = min(spacing) * sigma
    sigmas = (step / sz, step / sy, step / sx)  # per array axis (z, y, x), in voxels
    d = _derivatives(f, sigmas)
    inv = {0: 1.0 / sz, 1: 1.0 / sy, 2: 1.0 / sx}
    # world-unit derivatives, array axis order (z, y, x)
    g = [d[(1, 0, 0)], d[(0, 1, 0)], d[(0, 0, 1)]]
    for i in range(3):
        g[i] *= np.float32(inv[i])
    keys = {
        (0, 0): (2, 0, 0),
        (1, 1): (0, 2, 0),
        (2, 2): (0, 0, 2),
        (0, 1): (1, 1, 0),
        (0, 2): (1, 0, 1),
        (1, 2): (0, 1, 1),
    }
    h = {}
    for (i, j), k in keys.items():
        h[(i, j)] = d.pop(k)
        h[(i, j)] *= np.float32(inv[i] * inv[j])
    # numerator = g^T H g - |g|^2 tr(H), expanded so no 3x3 temporaries are needed
    num = np.zeros_like(f)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        # diagonal terms: g_i^2 H_ii - g_i^2 (H_ii + H_jj + H_kk) = -g_i^2 (H_jj + H_kk)
        tmp = h[(others[0], others[0])] + h[(others[1], others[1])]
        tmp *= g[i]
        tmp *= g[i]
        num -= tmp
    for i, j in ((0, 1), (0, 2), (1, 2)):
        tmp = g[i] * g[j]
        tmp *= h[(i, j)]
        tmp *= 2.0
        num += tmp
    del h, tmp
    mag2 = g[0] * g[0]
    mag2 += g[1] * g[1]
    mag2 += g[2] * g[2]
    del g
    gmax2 = float(mag2.max()) if gradient_max is None else float(gradient_max(mag2))
    thresh2 = max(min_gradient**2 * gmax2, np.finfo(np.float32).tiny)
    flat = mag2 <= thresh2
    mag2[flat] = 1.0
    num[flat] = 0.0
    # |H| = |num| / (2 |g|^3)
    np.sqrt(mag2, out=f)  # f is our own float32 copy; reuse it for |g|
    f *= mag2
    f *= 2.0
    np.abs(num, out=num)
    num /= f
    return num


def mean_curvature(
    data,
    *,
    spacing=(1.0, 1.0, 1.0),
    sigma: float = 1.0,
    min_gradient: float = 1e-4,
    offset=None,
    gradient_max=None,
) -> np.ndarray:
    """Absolute mean curvature ``|H|`` of the iso-surfaces of a Gaussian-smoothed field.

    Parameters
    ----------
    data : array_like
        3-D scalar field indexed ``[z, y, x]``.
    spacing : tuple of float
        Voxel size along x, y, z in world units.
    sigma : float
        Gaussian scale in units of the smallest voxel spacing; the smoothing is isotropic in
        world space (so axes with coarser spacing get fewer voxels of blur).
    min_gradient : float
        Where ``|grad f|`` is at most this fraction of its maximum the iso-surface is undefined
        and ``0`` is returned.
    offset, gradient_max : callable, optional
        For a piece of a larger volume (MPI ranks, :mod:`dvr_perception.rays.ranks`): the
        whole volume's values of two global quantities, so the piece's curvature equals the
        whole volume's bit for bit.  ``offset(f)`` gets the piece as float32 and returns the
        value subtracted from it (default: the median of ``f[::max(1, nz // 8)]``);
        ``gradient_max(mag2)`` gets ``|grad f|^2`` of the piece and returns its maximum over
        the whole volume (default: ``mag2.max()``).

    Returns
    -------
    numpy.ndarray
        ``float32`` array of ``|H|`` in 1/world-units, same shape as ``data``; never NaN or inf.

    Notes
    -----
    The derivative kernels are sampled Gaussian derivatives rescaled to be exact on quadratics,
    so coarse axes (kernel sigma below one voxel) stay accurate.  Within about ``3.5 sigma`` of
    the grid border edge values are replicated, which bends iso-surfaces that cross the border.
    Cost: 18 one-dimensional passes; about 1.6 s for 256×256×128 and 3–4 s for 256³ (2 cores).

    Examples
    --------
    >>> z, y, x = np.mgrid[-12:13, -12:13, -12:13]
    >>> f = -np.sqrt(x**2 + y**2 + z**2)          # iso-surfaces are spheres
    >>> h = mean_curvature(f)
    >>> round(float(h[12, 12, 22]), 2)            # radius 10 -> 1/10
    0.1
    """
    arr = np.asarray(data)
    if arr.ndim != 3 or min(arr.shape) < 2:
        raise DVRInputError(
            f"mean_curvature: data must be a 3-D array with at least 2 voxels per axis, "
            f"got shape {arr.shape}"
        )
    if arr.dtype.kind not in "uifb":
        raise DVRInputError(f"mean_curvature: data must be numeric, got dtype {arr.dtype}")
    sp = _check_spacing(spacing)
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise DVRInputError(f"mean_curvature: sigma must be a positive number, got {sigma!r}")
    if not (isinstance(min_gradient, (int, float)) and 0 <= min_gradient < 1):
        raise DVRInputError(f"mean_curvature: min_gradient must be in [0, 1), got {min_gradient!r}")
    f = np.array(arr, dtype=np.float32, copy=True)
    if not np.all(np.isfinite(f)):
        raise DVRInputError("mean_curvature: data contains NaN or infinite values")
    # remove the offset so float32 keeps precision in the derivatives
    if offset is None:
        f -= np.float32(np.median(f[:: max(1, f.shape[0] // 8)]))
    else:
        f -= np.float32(offset(f))
    out = _mean_curvature(f, sp, float(sigma), float(min_gradient), gradient_max)
    return np.ascontiguousarray(out, dtype=np.float32)


def _curvature_kernels():
    """Return the numba kernels of this module, or None (numpy) without numba."""
    return kernels("dvr_perception.rays._curvature_kernels")


def _classify(data: np.ndarray, labels, spec, nk=None, lut=None) -> np.ndarray:
    """Structure ids of ``data`` (any shape) and its ``labels`` (same shape, or None).

    ``lut`` (from :func:`_lookup_table`) gives the range structures' ids by value.
    """
    if lut is not None:
        ids = lut[data]
        for lab, k in _label_structures(spec):
            ids[labels == lab] = k
        return ids
    ids = np.full(data.shape, -1, dtype=np.int16)
    ranged = sorted((s.range[0], s.range[1], k) for k, s in enumerate(spec.structures) if s.range)
    touches = [
        n + 1 < len(ranged) and ranged[n + 1][0] <= hi for n, (_, hi, _) in enumerate(ranged)
    ]
    if ranged and nk is not None and data.ndim == 2:
        nk.classify_slice(
            data,
            np.array([r[0] for r in ranged], np.float64),
            np.array([r[1] for r in ranged], np.float64),
            np.array([not t for t in touches], np.bool_),
            np.array([r[2] for r in ranged], np.int16),
            ids,
        )
    else:
        _range_ids(data, spec, ids)
    for lab, k in _label_structures(spec):
        ids[labels == lab] = k
    return ids


def _range_ids(data: np.ndarray, spec, ids: np.ndarray) -> None:
    """Write the range structures' ids of ``data`` into ``ids`` (numpy)."""
    ranged = sorted((s.range[0], s.range[1], k) for k, s in enumerate(spec.structures) if s.range)
    for n, (lo, hi, k) in enumerate(ranged):
        touches_next = n + 1 < len(ranged) and ranged[n + 1][0] <= hi
        inside = data >= lo
        inside &= (data < hi) if touches_next else (data <= hi)
        ids[inside] = k


def _lookup_table(spec, dtype) -> np.ndarray | None:
    """Range-structure id of every value of an unsigned type of at most 16 bits, else None."""
    dtype = np.dtype(dtype)
    if dtype.kind != "u" or dtype.itemsize > 2:
        return None
    values = np.arange(2 ** (8 * dtype.itemsize), dtype=np.int64).astype(dtype)
    ids = np.full(values.shape, -1, dtype=np.int16)
    _range_ids(values, spec, ids)
    return ids


def _label_structures(spec) -> list[tuple[int, int]]:
    """``(label, structure index)`` of the label structures, in spec order."""
    return [(s.label, k) for k, s in enumerate(spec.structures) if s.label is not None]


def classify_structures(volume, spec) -> np.ndarray:
    """Structure id of every voxel (index into ``spec.structures``; ``-1`` for none).

    A range structure ``[lo, hi]`` owns the values ``lo <= v < hi``, and also ``v == hi`` when
    no other range starts there (touching ranges give the shared value to the upper structure).
    Label structures own the voxels whose label equals their id and take precedence.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> vol = Volume(np.array([0, 10, 20, 30], np.uint8).reshape(1, 2, 2).repeat(2, 0))
    >>> s = lambda n, r: Structure(n, 0.5, (1, 1, 1), range=r)
    >>> spec = StructureSpec((s("a", (5, 20)), s("b", (20, 30))))
    >>> classify_structures(vol, spec)[0].tolist()
    [[-1, 0], [1, 1]]
    """
    _check_labels(volume, spec)
    return _classify(volume.data, volume.labels, spec)


def _check_labels(volume, spec) -> None:
    if _label_structures(spec) and volume.labels is None:
        raise DVRInputError(
            f"volume {volume.name!r}: the spec has label structures but the volume has "
            "no label volume"
        )


# ---------------------------------------------------------------------------------------------
# curvature on the boundary voxels, slice by slice

#: ``|grad f|`` at most this fraction of the field's maximum is "flat" (``H`` undefined, 0).
_MIN_GRADIENT = 1e-4
_TINY = float(np.finfo(np.float32).tiny)
#: Side of the cells of the branch and bound of the gradient maximum.
_CELL = 16
#: Voxels of a y band's ring of y-pass slices (6 planes of float32 each): about 1M fits the
#: processor's cache.
_BAND_VOXELS = 1 << 18


def _axis_sigmas(sigma: float, spacing) -> tuple[float, float, float]:
    """Gaussian sigma in voxels per array axis (z, y, x): isotropic in world space."""
    sx, sy, sz = spacing
    step = min(spacing) * sigma
    return (step / sz, step / sy, step / sx)


def _radius(sigma_voxels: float) -> int:
    return max(1, math.ceil(_TRUNCATE * sigma_voxels))


def _check_sigma(sigma, where: str = "curvature_volume") -> float:
    if not (
        isinstance(sigma, (int, float, np.integer, np.floating))
        and not isinstance(sigma, bool)
        and math.isfinite(sigma)
        and sigma > 0
    ):
        raise DVRInputError(f"{where}: sigma must be a positive number, got {sigma!r}")
    return float(sigma)


def curvature_ghost(sigma: float, spacing) -> int:
    """Voxels of ghost a brick needs around its extent for :func:`curvature_volume`.

    The largest Gaussian kernel radius over the three axes, plus one for the boundary test.

    Parameters
    ----------
    sigma : float
        Gaussian scale in units of the smallest voxel spacing (as :func:`mean_curvature`).
    spacing : tuple of float
        Voxel size along x, y, z.

    Returns
    -------
    int
        Ghost width in voxels (the same on every axis).

    Examples
    --------
    >>> curvature_ghost(1.0, (1.0, 1.0, 2.0))
    5
    """
    sp = _check_spacing(spacing)
    sig = _check_sigma(sigma, "curvature_ghost")
    return max(_radius(s) for s in _axis_sigmas(sig, sp)) + 1


def _offset_of(arr: np.ndarray, match: int | None = None) -> float:
    """Median of every ``nz // 8``-th slice (as float32), as :func:`mean_curvature` removes."""
    sub = arr[:: max(1, arr.shape[0] // 8)]
    sub = (sub == match) if match is not None else sub
    return float(np.median(sub.astype(np.float32)))


@dataclass(frozen=True)
class CurvatureGlobals:
    """Whole-volume quantities that make a brick's curvature equal the full result's.

    Parameters
    ----------
    sigma : float
        The Gaussian scale they were computed for.
    offset : float
        Subtracted from the data before filtering.  It only conditions the float32 precision of
        the derivatives (any value inside the data range gives results equal to rounding).
    gradient_max : float or None
        Largest ``|grad f|`` (world units, smoothed data) over the volume; ``|H|`` is 0 where
        ``|grad f| <= 1e-4 * gradient_max``.  None when the spec has no range structure.
    label_gradient_max : dict
        The same for the smoothed indicator of each label structure (structure index -> max).
    """

    sigma: float
    offset: float
    gradient_max: float | None
    label_gradient_max: dict = field(default_factory=dict)

    def combine(self, other: CurvatureGlobals) -> CurvatureGlobals:
        """Return the maxima of both (e.g. MPI ranks' local values), with this offset.

        Examples
        --------
        >>> a = CurvatureGlobals(1.0, 0.0, 2.0, {1: 0.5})
        >>> a.combine(CurvatureGlobals(1.0, 3.0, 5.0, {1: 0.25})).gradient_max
        5.0
        """
        if not isinstance(other, CurvatureGlobals) or other.sigma != self.sigma:
            raise DVRInputError(
                "CurvatureGlobals.combine: other must be CurvatureGlobals for the same sigma"
            )

        def top(a, b):
            return b if a is None else a if b is None else max(a, b)

        labels = dict(self.label_gradient_max)
        for k, v in other.label_gradient_max.items():
            labels[k] = top(labels.get(k), v)
        return CurvatureGlobals(
            self.sigma, self.offset, top(self.gradient_max, other.gradient_max), labels
        )


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
    out = np.zeros((*ncell, 3), np.float32)
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
        for a, d in enumerate(diffs):
            pad = np.zeros((size, size * ncell[1], size * ncell[2]), np.float32)
            pad[: d.shape[0], : d.shape[1], : d.shape[2]] = d
            cells = pad.reshape(size, ncell[1], size, ncell[2], size).max(axis=(0, 2, 4))
            out[i, :, :, a] = cells
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


def _gradient_max(fld: _Field, geo: _Geometry, nk, lower: float = 0.0, floor: float = 0.0):
    """Largest ``|grad f|`` over ``geo``'s extent, exact when it is at least ``floor``.

    Branch and bound over cells of 16³ voxels: the largest neighbour difference ``D`` along an
    axis in a cell's reach bounds that derivative (the derivative-of-Gaussian weights ``w_j``
    have ``sum(w_j j) = 1`` and are positive for ``j > 0``, so ``|sum w_j f_j| <= D``); cells
    are filtered exactly in order of decreasing bound until the bound is below the best value
    found (or ``floor``).  ``lower`` is a known lower bound (a gradient seen elsewhere).
    """
    (ez0, ez1), (ey0, ey1), (ex0, ex1) = geo.extent
    c = _CELL
    lo = [max(0, a - r) for (a, _), r in zip(geo.extent, geo.radii, strict=True)]
    hi = [min(n, b + r) for (_, b), r, n in zip(geo.extent, geo.radii, geo.shape, strict=True)]
    org = lo
    ncell = [math.ceil((h - o) / c) for o, h in zip(org, hi, strict=True)]
    if nk is not None:
        diffs = np.zeros((*ncell, 3), np.float32)
        sizes = [min(h, o + c * n) - o for o, h, n in zip(org, hi, ncell, strict=True)]
        nk.cell_diffs(fld.src, fld.match, np.float32(fld.offset), c, *org, *sizes, diffs)
    else:
        diffs = _cell_diffs_numpy(fld, org, ncell, c)
    # a voxel's filters reach r voxels: dilate the per-cell differences accordingly
    reach = [2 * math.ceil(r / c) + 1 for r in geo.radii]
    bound = ndimage.maximum_filter(diffs, size=(*reach, 1), mode="constant", cval=0.0)
    bound2 = ((bound.astype(np.float64) * geo.inv) ** 2).sum(axis=-1) * (1 + 1e-5)
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


def _fields(volume, spec, globals_: CurvatureGlobals | None, gradient_max, offset):
    """Return the fields of ``spec`` (data, then the label structures owning their label)."""
    out = []
    if any(s.range is not None for s in spec.structures):
        off = offset
        if off is None:
            off = globals_.offset if globals_ is not None else _offset_of(volume.data)
        gm = gradient_max if not isinstance(gradient_max, CurvatureGlobals) else None
        if globals_ is not None:
            gm = globals_.gradient_max
        out.append(_Field(None, volume.data, -1, float(off), gm))
    labelled = _label_structures(spec)
    for n, (lab, k) in enumerate(labelled):
        if lab in [m for m, _ in labelled[n + 1 :]]:
            continue
        gm = globals_.label_gradient_max.get(k) if globals_ is not None else None
        out.append(_Field(k, volume.labels, int(lab), _offset_of(volume.labels, lab), gm))
    return out


def curvature_globals(volume, spec, *, sigma: float = 1.0, extent=None) -> CurvatureGlobals:
    """Compute the whole-volume quantities of :func:`curvature_volume` once for many bricks.

    Parameters
    ----------
    volume : Volume
        The volume (with its label volume when the spec has label structures).
    spec : StructureSpec
        The structures.
    sigma : float
        Gaussian scale, see :func:`mean_curvature`.
    extent : tuple, optional
        ``((z0, z1), (y0, y1), (x0, x1))``: take the gradient maxima over these voxels only
        (reading the ghost around them), e.g. the part of the volume an MPI rank owns; combine
        the ranks' results with :meth:`CurvatureGlobals.combine` (a max reduction).

    Returns
    -------
    CurvatureGlobals
        The data offset (median of every ``nz // 8``-th slice) and the exact largest gradient
        magnitude of the smoothed data and of each label indicator.

    Notes
    -----
    The maximum is found by branch and bound: an upper bound per 16³ cell (the largest
    neighbour difference in the cell's reach bounds the derivative-of-Gaussian filters, whose
    weights ``w_j j`` sum to one) orders the cells, and cells are filtered exactly until the
    bound falls below the best value.  Without numba the gradient is filtered everywhere.
    """
    sig = _check_sigma(sigma, "curvature_globals")
    _check_labels(volume, spec)
    data = volume.data
    geo = _Geometry(data.shape, volume.spacing, sig, _check_extent(extent, data.shape))
    nk = _curvature_kernels()
    fields = _fields(volume, spec, None, None, None)
    gmax = None
    labels = {}
    for fld in fields:
        value = _gradient_max(fld, geo, nk)
        if fld.key is None:
            gmax = value
        else:
            labels[fld.key] = value
    off = fields[0].offset if fields and fields[0].key is None else _offset_of(data)
    return CurvatureGlobals(sig, off, gmax, labels)


def curvature_volume(
    volume, spec, *, sigma: float = 1.0, extent=None, gradient_max=None, offset=None,
    progress=None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``|H|`` on the boundary voxels of the structures of ``spec``.

    Voxels are classified with :func:`classify_structures`; a boundary voxel is one whose
    structure id differs from one of its 6 neighbours.  The curvature is that of the intensity
    iso-surfaces; a boundary voxel of (or next to) a label structure, that is not itself in a
    range structure, takes the curvature of the smoothed indicator of that label instead.

    Parameters
    ----------
    volume : Volume
        The volume (and its label volume, if the spec has label structures).
    spec : StructureSpec
        The structures.
    sigma : float
        Gaussian scale, see :func:`mean_curvature`.
    extent : tuple, optional
        ``((z0, z1), (y0, y1), (x0, x1))``, half-open voxel ranges: return the brick of these
        voxels only, equal to that slice of the full result.  It reads the volume up to
        :func:`curvature_ghost` voxels around the extent.
    gradient_max : float or CurvatureGlobals, optional
        The whole volume's largest ``|grad f|`` of the smoothed data (a float), or all the
        whole-volume quantities (:func:`curvature_globals`).  Pass it when computing many
        bricks, or when ``volume`` is only a piece of a larger volume (an MPI rank's part,
        with at least :func:`curvature_ghost` voxels of ghost around ``extent`` where it does
        not touch the whole volume's border).
    offset : float, optional
        Subtracted from the data before filtering (default: the globals', else the median of
        every ``nz // 8``-th slice); it only conditions float32 precision.
    progress : callable, optional
        Called from the calling thread with the fraction done, a float in [0, 1]: 0.0 first,
        then as the bands' z slices are classified and filtered (at most about 100 calls in
        all, non-decreasing), 1.0 last.  A callback that raises :class:`StopIteration`
        cancels the computation: :class:`~dvr_perception.errors.DVRCancelled` is raised.
        The result does not depend on it.

    Returns
    -------
    curvature : numpy.ndarray
        ``float32`` ``[z, y, x]`` array of ``|H|`` (1/world-units), 0 off the boundary.
    boundary : numpy.ndarray
        ``bool`` ``[z, y, x]`` boundary mask.

    Notes
    -----
    ``|H|`` is evaluated only at boundary voxels.  The extent is cut into bands along y
    (handed to one thread per numba thread) and each band is streamed in z slices: a slice is
    classified, then filtered along x and y (on the rows the boundary voxels read) into a ring
    of ``2 r_z + 1`` slices, from which the derivatives along z are finished on the rows with
    boundary voxels; the numerator and ``|H|`` are evaluated at those voxels only.
    Temporaries are a few slices of a band (about 1/4 M voxels of ring per thread), besides
    the two outputs.  The filters are the same as :func:`mean_curvature`'s, in float32 (sums
    in a fixed order, so a brick gives exactly the bits of the full result); the numerator is
    formed in float64.

    Where ``|grad f| <= 1e-4 * gradient_max`` the iso-surface is undefined and ``|H|`` is 0
    (``gradient_max`` is the whole volume's, as in :func:`mean_curvature`).  Without
    ``gradient_max`` the test is decided without the maximum whenever possible: the maximum
    lies between the largest gradient of the boundary voxels computed and a bound from the
    data range; only boundary voxels with a gradient between those two thresholds make the
    maximum be searched for, and only as far as it decides them (branch and bound, see
    :func:`curvature_globals`).  Results are the same either way.
    """
    sig = _check_sigma(sigma)
    _check_labels(volume, spec)
    report = reporter(progress)
    data = volume.data
    ext = _check_extent(extent, data.shape)
    globals_ = None
    if isinstance(gradient_max, CurvatureGlobals):
        if gradient_max.sigma != sig:
            raise DVRInputError(
                f"curvature_volume: gradient_max was computed for sigma={gradient_max.sigma}, "
                f"not {sig}"
            )
        globals_ = gradient_max
    elif gradient_max is not None and not (
        isinstance(gradient_max, (int, float, np.integer, np.floating))
        and math.isfinite(gradient_max)
        and gradient_max >= 0
    ):
        raise DVRInputError(
            "curvature_volume: gradient_max must be a non-negative number or CurvatureGlobals, "
            f"got {gradient_max!r}"
        )
    if offset is not None and not (
        isinstance(offset, (int, float, np.integer, np.floating)) and math.isfinite(offset)
    ):
        raise DVRInputError(f"curvature_volume: offset must be a finite number, got {offset!r}")
    shape = tuple(b - a for a, b in ext)
    out = np.zeros(shape, dtype=np.float32)
    boundary = np.zeros(shape, dtype=bool)
    nk = _curvature_kernels()
    geo = _Geometry(data.shape, volume.spacing, sig, ext)
    fields = _fields(volume, spec, globals_, gradient_max, offset)
    sum_inv2 = float((geo.inv**2).sum())
    for fld in fields:
        if fld.gradient_max is not None:
            continue  # the bound only serves the flatness test without the maximum
        if fld.key is None:
            fld.bound2 = (float(data.max()) - float(data.min())) ** 2 * sum_inv2 * (1 + 1e-5)
        else:
            fld.bound2 = sum_inv2 * (1 + 1e-5)  # an indicator's differences are at most 1
    _, (ey0, ey1), (ex0, ex1) = ext
    # y bands (the ring of a band stays in the processor's cache), run by a pool of threads
    rows = max(_BAND_VOXELS // ((ex1 - ex0) * (2 * geo.radii[0] + 1)), 8)
    bands = max(1, round((ey1 - ey0) / rows))
    cuts = [ey0 + ((ey1 - ey0) * i) // bands for i in range(bands + 1)]
    chunks = [(ext[0], (a, b), ext[2]) for a, b in itertools.pairwise(cuts)]

    workers = min(_threads(), len(chunks))
    # progress: slices done per band (one writer each), reported from the calling thread
    per_band = (ext[0][1] - ext[0][0]) * (1 + len(fields))
    done = [0] * len(chunks)
    stopped: list = []
    report(0.0)

    def run(n):
        chunk = chunks[n]
        wy = slice(chunk[1][0] - ey0, chunk[1][1] - ey0)
        sub = geo.with_extent(chunk)

        def tick():
            if stopped:
                raise DVRCancelled("progress: cancelled")  # another band's caller stopped
            done[n] = min(done[n] + 1, per_band)
            if workers == 1:
                report(0.95 * sum(done) / (per_band * len(chunks)))

        res = _chunk(volume, spec, sub, nk, fields, out[:, wy], boundary[:, wy],
                     tick if report else None)  # fmt: skip
        done[n] = per_band
        return res

    if workers == 1:
        results = [run(n) for n in range(len(chunks))]
    else:
        with ThreadPoolExecutor(workers) as pool:
            futures = [pool.submit(run, n) for n in range(len(chunks))]
            _follow(futures, done, per_band * len(chunks), report, stopped)
            results = [f.result() for f in futures]
    for n, fld in enumerate(fields):
        seen = max(r[n][0] for r in results)
        maybe = [
            (k, ys + chunk[1][0] - ey0, xs, mag2)
            for r, chunk in zip(results, chunks, strict=True)
            for k, ys, xs, mag2 in r[n][1]
        ]
        _resolve_flat(fld, geo, nk, seen, maybe, out)
    report(1.0)
    return out, boundary


def _follow(futures, done, total, report, stopped) -> None:
    """Report the bands' progress from the calling thread until they are all done.

    A cancelled report (:class:`~dvr_perception.errors.DVRCancelled`) makes the bands stop at
    their next slice before it is raised.
    """
    if not report:
        return
    pending = set(futures)
    try:
        while pending:
            _, pending = wait(pending, timeout=0.05, return_when=FIRST_COMPLETED)
            report(0.95 * sum(done) / total)
    except DVRCancelled:
        stopped.append(True)
        for f in futures:
            f.cancel()
        raise


def _threads() -> int:
    """Return how many threads (z chunks) to use: numba's thread count, else the CPUs."""
    try:
        import numba

        return max(1, int(numba.get_num_threads()))
    except ImportError:
        return max(1, os.cpu_count() or 1)


def _chunk(volume, spec, geo: _Geometry, nk, fields, out, boundary, tick=None) -> list:
    """Boundary and ``|H|`` of one z chunk; per field, what :func:`_field_curvature` returns."""
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

    def emit(k, ys, xs, num, mag2):
        nonlocal seen
        ys = ys - wy.start
        xs = xs - wx.start
        flat = mag2 <= thr
        safe = np.where(flat, 1.0, mag2)
        h = np.abs(num) / (2.0 * safe * np.sqrt(safe))
        h[flat] = 0.0
        out[k, ys, xs] = h
        if not known:
            seen = max(seen, float(mag2.max()))
            cand = (mag2 <= thr_hi) & ~flat
            if cand.any():
                maybe.append((k, ys[cand], xs[cand], mag2[cand]))

    _field_pass(fld, geo, nk, *ranges, points_of, emit, tick)
    return seen, maybe


def _resolve_flat(fld: _Field, geo: _Geometry, nk, seen: float, maybe: list, out) -> None:
    """Zero the possibly flat points that are flat: ``|grad f| <= 1e-4 * gradient_max``.

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
        out[k, ys[flat], xs[flat]] = 0.0
