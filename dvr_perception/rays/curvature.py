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

import itertools
import math
import os
import queue
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from dvr_perception._numba import kernels
from dvr_perception._progress import reporter
from dvr_perception.errors import DVRCancelled, DVRInputError
from dvr_perception.rays._curvature_pages import BandPages, assemble, page_cuts
from dvr_perception.rays._curvature_passes import (
    _axis_sigmas,
    _check_extent,
    _chunk,
    _Field,
    _Geometry,
    _gradient_max,
    _kernel,
    _radius,
    _resolve_flat,
)
from dvr_perception.rays.classify import _check_labels, _label_structures, classify_structures

__all__ = [
    "CurvatureGlobals",
    "classify_structures",
    "curvature_ghost",
    "curvature_globals",
    "curvature_pages",
    "curvature_volume",
    "mean_curvature",
]


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


# ---------------------------------------------------------------------------------------------
# curvature on the boundary voxels, slice by slice (the engine: rays/_curvature_passes.py)

#: Voxels of a y band's ring of y-pass slices (6 planes of float32 each): about 1M fits the
#: processor's cache.
_BAND_VOXELS = 1 << 18
#: Fewest rows of a y band cut to give many threads work (each band filters its ghost rows).
_MIN_ROWS = 16
#: Extents of at least this many voxels are cut into a band per thread (a 256^3 one is).
_SPLIT_VOXELS = 1 << 23


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
    formed in float64.  :func:`curvature_pages` gives the whole volume's result in 8^3 pages
    without either output.

    Where ``|grad f| <= 1e-4 * gradient_max`` the iso-surface is undefined and ``|H|`` is 0
    (``gradient_max`` is the whole volume's, as in :func:`mean_curvature`).  Without
    ``gradient_max`` the test is decided without the maximum whenever possible: the maximum
    lies between the largest gradient of the boundary voxels computed and a bound from the
    data range; only boundary voxels with a gradient between those two thresholds make the
    maximum be searched for, and only as far as it decides them (branch and bound, see
    :func:`curvature_globals`).  Results are the same either way.
    """
    out, boundary = _compute(volume, spec, sigma, extent, gradient_max, offset, progress)
    return out, boundary


def curvature_pages(
    volume, spec, *, sigma: float = 1.0, gradient_max=None, offset=None, progress=None
) -> tuple[np.ndarray, np.ndarray]:
    """Compute the whole volume's :func:`curvature_volume` in 8^3 pages, never dense.

    Parameters
    ----------
    volume, spec, sigma, gradient_max, offset, progress
        As :func:`curvature_volume` (of the whole volume: no ``extent``).

    Returns
    -------
    index : numpy.ndarray
        int32 ``(ceil(Z / 8), ceil(Y / 8), ceil(X / 8))`` page numbers, -1 where every
        value of the page is 0.
    pages : numpy.ndarray
        float32 ``(n, 8, 8, 8)`` (0 outside the volume).  Bit for bit what
        :meth:`CurvaturePages.from_dense
        <dvr_perception.rays.curvature_field.CurvaturePages.from_dense>` makes of
        ``curvature_volume(volume, spec, ...)[0]``, page numbers included.

    Notes
    -----
    The y bands of :func:`curvature_volume` are cut on page edges, and each keeps its values
    in pages as they are computed (:mod:`dvr_perception.rays._curvature_pages`): what is held
    besides the pages is a few slices per band (a band's slices with label structures)
    instead of the float32 ``|H|`` and bool boundary volumes.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=20)
    >>> index, pages = curvature_pages(vol, spec)
    >>> index.shape, pages.shape[1:]
    ((3, 3, 3), (8, 8, 8))
    """
    return _compute(volume, spec, sigma, None, gradient_max, offset, progress, paged=True)


def _compute(volume, spec, sigma, extent, gradient_max, offset, progress, *, paged=False):
    """:func:`curvature_volume` (``paged``: :func:`curvature_pages`, of the whole volume)."""
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
    if not paged:
        out = np.zeros(shape, dtype=np.float32)
        boundary = np.zeros(shape, dtype=bool)
    nk = _curvature_kernels()
    geo = _Geometry(data.shape, volume.spacing, sig, ext)
    fields = _fields(volume, spec, globals_, gradient_max, offset)
    for fld in fields:
        if fld.gradient_max is not None:
            continue  # the bound only serves the flatness test without the maximum
        if fld.key is None:
            lo, hi = float(data.min()) - fld.offset, float(data.max()) - fld.offset
        else:
            lo, hi = -fld.offset, 1.0 - fld.offset  # an indicator's values are 0 and 1
        fld.bound2 = _range_bound2(geo, hi - lo, max(abs(lo), abs(hi)))
    _, (ey0, ey1), (ex0, ex1) = ext
    # y bands (the ring of a band stays in the processor's cache), run by a pool of threads
    rows = max(_BAND_VOXELS // ((ex1 - ex0) * (2 * geo.radii[0] + 1)), 8)
    # a band for every thread (of 16 rows or more) on a large extent: a 512-row extent made 9
    # bands, idling 7 of 16 threads (the same bits however it is cut).  A small one keeps its
    # single band: a few ms of work, whose progress is then reported slice by slice.
    bands = max(1, round((ey1 - ey0) / rows))
    if (ext[0][1] - ext[0][0]) * (ey1 - ey0) * (ex1 - ex0) >= _SPLIT_VOXELS:
        bands = max(bands, min(_threads(), (ey1 - ey0) // _MIN_ROWS))
    if paged:  # a page in one band only
        cuts = page_cuts(ey0, ey1, bands)
    else:
        cuts = [ey0 + ((ey1 - ey0) * i) // bands for i in range(bands + 1)]
    chunks = [(ext[0], (a, b), ext[2]) for a, b in itertools.pairwise(cuts)]

    workers = min(_threads(), len(chunks))
    # progress: slices done per band (one writer each), reported from the calling thread
    per_band = (ext[0][1] - ext[0][0]) * (1 + len(fields))
    done = [0] * len(chunks)
    stopped: list = []
    # paged: each band's pages (label fields write a band's voxels in turn, over every slice),
    # and a boundary mask per worker, made here (the workers' heaps would keep their memory)
    sinks = [None] * len(chunks)
    masks = queue.SimpleQueue()
    if paged:
        rows_max = max(b - a for a, b in itertools.pairwise(cuts))
        for _ in range(workers):
            masks.put(np.empty(shape[0] * rows_max * shape[2], bool))
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

        if paged:
            shape_n = (shape[0], wy.stop - wy.start, shape[2])
            sink = BandPages(*shape_n, chunk[1][0], nk, whole=len(fields) > 1)
            mask = masks.get()
            try:
                bnd = mask[: math.prod(shape_n)].reshape(shape_n)  # contiguous
                res = _chunk(volume, spec, sub, nk, fields, sink, bnd,
                             tick if report else None)  # fmt: skip
            finally:
                masks.put(mask)
            sink.finish()
            sinks[n] = sink
        else:
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
        if paged:

            def zero(k, ys, xs):
                n = int(np.searchsorted(cuts, ys[0], side="right")) - 1  # maybe: one band
                sinks[n].zero(k, ys, xs)

        else:

            def zero(k, ys, xs):
                out[k, ys, xs] = 0.0

        _resolve_flat(fld, geo, nk, seen, maybe, zero)
    if paged:
        del masks
        pages = assemble(sinks, shape)
        report(1.0)
        return pages
    report(1.0)
    return out, boundary


def _range_bound2(geo, span: float, magnitude: float) -> float:
    """Upper bound of ``|grad f|^2`` (world units) of a field whose values span ``span``.

    Along an axis the derivative is ``sum_t w_t (S(v + t) - S(v - t))`` over ``t > 0``
    (``w_t > 0``, ``S`` a convex combination of values), at most ``span * sum_t w_t``
    (about a third of ``span`` at ``sigma = 1``); ``1e-5 * magnitude`` (the largest
    ``|value|``) covers the float32 rounding of the filters.
    """
    total = 0.0
    for a in range(3):
        w = geo.half[a][1].astype(np.float64)[1:]
        total += (float(w.sum()) * (span + 1e-5 * magnitude) * float(geo.inv[a])) ** 2
    return total * (1 + 1e-5)


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
