"""Structural layers in the image: footprints, sub-regions and layer relations (Sec. 4.3.2).

* A structure's **footprint** is where its absolute visible opacity exceeds a threshold (the
  transparency measure adds where its occlusion-free opacity does: decision D3).
* Pixels covered by the same set of layers form **sub-regions** (split into connected
  components), classified as *empty* (no layer), *plain* (one layer) or *overlay* (several).
* Pairs of layers are related by the region connection calculus as *separate*, *touch*,
  *enclose* or *overlap* (Fig. 5).

Images are ``(H, W)`` with row 0 at the top; a stack of layers is ``(K, H, W)``.  The layer set
of a pixel is stored as a ``uint32`` bitmask (bit ``k`` set when layer ``k`` is present), so at
most 32 layers are supported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.measure import label

from dvr_perception._numba import kernels
from dvr_perception.errors import DVRInputError

__all__ = [
    "Region",
    "RegionMap",
    "Relation",
    "layer_footprints",
    "layer_relations",
    "subregions",
]

MAX_LAYERS = 32


@dataclass(frozen=True)
class Region:
    """One connected sub-region with a constant layer set.

    Attributes
    ----------
    id : int
        Index in :attr:`RegionMap.regions` and value in :attr:`RegionMap.region_id`.
    layers : frozenset of int
        Indices of the layers present.
    kind : {"empty", "plain", "overlay"}
        No layer, exactly one, or several.
    area : int
        Number of pixels.
    area_fraction : float
        ``area / (H * W)``.
    bbox : tuple of 4 int or None
        ``(min_row, min_col, max_row, max_col)``, max exclusive (as ``skimage.measure``);
        ``None`` from ``subregions(..., geometry=False)``.
    centroid : tuple of 2 float or None
        ``(row, col)`` mean pixel position; ``None`` from ``subregions(..., geometry=False)``.
    """

    id: int
    layers: frozenset[int]
    kind: str
    area: int
    area_fraction: float
    bbox: tuple[int, int, int, int] | None
    centroid: tuple[float, float] | None


@dataclass(frozen=True)
class RegionMap:
    """Sub-regions of an image (see :func:`subregions`).

    Attributes
    ----------
    region_id : ndarray of int32, shape (H, W)
        Region index of every pixel.
    layer_set : ndarray of uint32, shape (H, W)
        Bitmask of the layers present at every pixel.
    regions : tuple of Region
        ``regions[i].id == i``, ordered by the first pixel of each region in row-major order.
    """

    region_id: np.ndarray
    layer_set: np.ndarray
    regions: tuple[Region, ...]


@dataclass(frozen=True)
class Relation:
    """Region-connection-calculus relation of two layers ``i < j`` (see :func:`layer_relations`).

    Attributes
    ----------
    kind : {"separate", "touch", "enclose", "overlap"}
    layers : tuple of 2 int
        ``(i, j)`` with ``i < j``.
    encloser : int or None
        For ``"enclose"``, the layer that contains the other; else ``None``.
    intersection : int
        Number of pixels covered by both footprints.
    """

    kind: str
    layers: tuple[int, int]
    encloser: int | None
    intersection: int

    @property
    def enclosed(self) -> int | None:
        """For ``"enclose"``, the layer that is contained in the other; else ``None``."""
        if self.encloser is None:
            return None
        i, j = self.layers
        return j if self.encloser == i else i


def layer_footprints(visible, *, threshold: float = 0.05) -> np.ndarray:
    """Footprints of the structures: where their absolute visible opacity exceeds a threshold.

    Parameters
    ----------
    visible : array_like, shape (K, H, W)
        Absolute visible opacity of each structure per pixel (its visible share times the
        accumulated opacity), in [0, 1].
    threshold : float, optional
        A pixel belongs to structure ``s`` when ``visible[s] > threshold``.  The default 0.05
        (5 % of the pixel's light) ignores faint fringes and numerical dust while keeping
        deliberately faint but visible layers.

    Returns
    -------
    footprints : ndarray of bool, shape (K, H, W)

    Raises
    ------
    DVRInputError
        If ``visible`` is not a finite 3-D array or ``threshold`` is not in [0, 1).

    Examples
    --------
    >>> vis = np.array([[[0.0, 0.3], [0.04, 0.9]]])
    >>> layer_footprints(vis)[0]
    array([[False,  True],
           [False,  True]])
    """
    try:
        arr = np.asarray(visible, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError("visible must be a numeric (K, H, W) array") from None
    if arr.ndim != 3 or not np.all(np.isfinite(arr)):
        raise DVRInputError(f"visible must be a finite (K, H, W) array, got shape {arr.shape}")
    if not 0.0 <= float(threshold) < 1.0:
        raise DVRInputError(f"threshold must lie in [0, 1), got {threshold!r}")
    return arr > float(threshold)


def _layer_set_bits(visible, threshold: float, assigned=None, limits=None) -> np.ndarray:
    """(H, W) uint32 layer-set bitmask of footprints, without the (K, H, W) boolean stack.

    Bit ``k`` is set where ``visible[k] > threshold`` (:func:`layer_footprints`) or, with
    ``assigned`` (K, H, W) and ``limits`` (K,), where ``assigned[k] > limits[k]`` (the
    transparency measure's occlusion-free footprints, D3): the bitmask :func:`subregions`
    makes of those footprints.  ``visible`` and ``assigned`` are checked, finite and
    non-negative (float32 or float64; compared in float64).
    """
    if not 0.0 <= float(threshold) < 1.0:
        raise DVRInputError(f"threshold must lie in [0, 1), got {threshold!r}")
    k, height, width = visible.shape
    if k > MAX_LAYERS:
        raise DVRInputError(f"footprints: at most {MAX_LAYERS} layers are supported, got {k}")
    nk = kernels("dvr_perception.measures._kernels")
    if nk is None or k == 0:
        fp = np.asarray(visible, np.float64) > float(threshold)
        if assigned is not None:
            fp |= assigned > np.asarray(limits, np.float64)[:, None, None]
        return _bitmask(fp)
    flat = np.ascontiguousarray(visible).reshape(k, -1)
    if assigned is None:
        other, limits = flat, np.full(k, np.inf)
    else:
        other = np.ascontiguousarray(assigned).reshape(k, -1)
    out = np.empty(height * width, np.uint32)
    nk.layer_bits(flat, other, float(threshold), np.asarray(limits, np.float64), out)
    return out.reshape(height, width)


def _as_footprints(footprints) -> np.ndarray:
    arr = np.asarray(footprints)
    if arr.ndim != 3 or arr.shape[1] == 0 or arr.shape[2] == 0:
        raise DVRInputError(
            f"footprints must be a (K, H, W) array with H, W >= 1, got shape {arr.shape}"
        )
    if arr.dtype != np.bool_:
        if not (np.issubdtype(arr.dtype, np.number) and np.all((arr == 0) | (arr == 1))):
            raise DVRInputError("footprints must be boolean (or 0/1) masks")
        arr = arr.astype(bool)
    if arr.shape[0] > MAX_LAYERS:
        raise DVRInputError(
            f"footprints: at most {MAX_LAYERS} layers are supported, got {arr.shape[0]}"
        )
    return arr


def _bitmask(fp: np.ndarray) -> np.ndarray:
    bits = (np.uint32(1) << np.arange(fp.shape[0], dtype=np.uint32))[:, None, None]
    return np.bitwise_or.reduce(fp.astype(np.uint32) * bits, axis=0, initial=np.uint32(0))


def subregions(footprints, *, geometry: bool = True) -> RegionMap:
    """Split the image into sub-regions of constant layer composition (Sec. 4.3.2, Fig. 5).

    Pixels with the same set of layers are grouped and split into connected components with
    **8-connectivity** (``skimage.measure.label(..., connectivity=2)``), so thin diagonal
    structures are not shattered into single pixels.

    Parameters
    ----------
    footprints : array_like of bool, shape (K, H, W)
        Layer footprints, e.g. from :func:`layer_footprints`; ``K`` may be 0 (no layers).
    geometry : bool, optional
        Also give each region its bounding box and centroid (default); ``False`` leaves them
        ``None`` (the transparency measure needs neither, and skips their cost).

    Returns
    -------
    RegionMap
        Region index image, layer bitmask image and the regions, ordered by their first pixel
        in row-major order.

    Raises
    ------
    DVRInputError
        If ``footprints`` is not a (K, H, W) boolean array with ``H, W >= 1`` and ``K <= 32``.

    Examples
    --------
    >>> fp = np.zeros((2, 3, 4), bool)
    >>> fp[0, :, :3] = True
    >>> fp[1, :, 2:] = True
    >>> rmap = subregions(fp)
    >>> [(r.kind, sorted(r.layers), r.area) for r in rmap.regions]
    [('plain', [0], 6), ('overlay', [0, 1], 3), ('plain', [1], 3)]
    >>> rmap.region_id[0]
    array([0, 0, 1, 2], dtype=int32)
    """
    fp = _as_footprints(footprints)
    return _subregions(_bitmask(fp), fp.shape[0], geometry=geometry)


def _subregions(mask: np.ndarray, k: int, *, geometry: bool = True) -> RegionMap:
    """:func:`subregions` of the ``k`` layers of a (H, W) uint32 layer-set bitmask."""
    height, width = mask.shape
    nk = kernels("dvr_perception.measures._kernels")
    if nk is not None:
        region_id, first, area = nk.label_regions(np.ascontiguousarray(mask))
    else:
        labels = label(mask.astype(np.int64), background=-1, connectivity=2)  # labels 1..n
        region_id, first = _raster_ordered(labels)
        area = np.bincount(region_id.ravel(), minlength=first.size)
    flat = region_id.ravel()
    n = first.size
    sets = mask.ravel()[first].tolist()
    if geometry:
        rows, cols = np.divmod(np.arange(flat.size), width)
        c_row = (np.bincount(flat, weights=rows, minlength=n) / area).tolist()
        c_col = (np.bincount(flat, weights=cols, minlength=n) / area).tolist()
        boxes = [(sr.start, sc.start, sr.stop, sc.stop)
                 for sr, sc in ndimage.find_objects(region_id + 1)]  # fmt: skip
        centroids = list(zip(c_row, c_col, strict=True))
    else:
        boxes = centroids = [None] * n
    n_pix = height * width
    kinds: dict[int, tuple] = {}  # per layer bitmask: (layers, kind), built once
    for b in set(sets):
        layers = frozenset(q for q in range(k) if b >> q & 1)
        kinds[b] = (layers, "empty" if not layers else "plain" if len(layers) == 1 else "overlay")
    rows_ = zip(sets, area.tolist(), boxes, centroids, strict=True)
    regions = [
        Region(
            id=rid,
            layers=kinds[b][0],
            kind=kinds[b][1],
            area=a,
            area_fraction=a / n_pix,
            bbox=box,
            centroid=centroid,
        )
        for rid, (b, a, box, centroid) in enumerate(rows_)
    ]
    return RegionMap(region_id=region_id, layer_set=mask, regions=tuple(regions))


def _raster_ordered(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Region ids ``0..n-1`` numbered by first pixel in row-major order, and those pixels.

    ``skimage.measure.label`` numbers components that way already; that is checked in O(n)
    (each label first appears where it exceeds all earlier ones) and only if it fails are
    the labels sorted.
    """
    flat = labels.ravel()
    seen = np.maximum.accumulate(flat)
    first = np.flatnonzero(flat > np.concatenate(([0], seen[:-1])))
    if np.array_equal(flat[first], np.arange(1, first.size + 1)) and first.size == seen[-1]:
        return (labels - 1).astype(np.int32), first
    _, first = np.unique(flat, return_index=True)  # sorted by label value
    order = np.argsort(first, kind="stable")  # label values ranked by first pixel
    remap = np.empty(order.size + 1, dtype=np.int32)
    remap[order + 1] = np.arange(order.size, dtype=np.int32)
    return remap[labels], np.sort(first)


def _dilate8(fp: np.ndarray) -> np.ndarray:
    """3x3 (8-neighbourhood) dilation of each (H, W) image of a (K, H, W) stack.

    Boolean masks are dilated; bitmasks (unsigned integers) are OR-ed over the neighbourhood,
    which dilates every bit's mask at once.
    """
    out = fp.copy()
    out[:, 1:, :] |= fp[:, :-1, :]
    out[:, :-1, :] |= fp[:, 1:, :]
    rows = out.copy()
    out[:, :, 1:] |= rows[:, :, :-1]
    out[:, :, :-1] |= rows[:, :, 1:]
    return out


def layer_relations(footprints, *, tolerance: float = 0.02) -> dict[tuple[int, int], Relation]:
    """Relations of every pair of non-empty layer footprints (region connection calculus).

    For layers ``i < j`` with areas ``A_i, A_j``, intersection ``X`` and smaller area
    ``A_s = min(A_i, A_j)``:

    1. ``"separate"``: no pixel of one is within 1 px (8-neighbourhood) of the other;
    2. ``"enclose"``: the smaller footprint lies in the larger one up to ``tolerance``,
       ``A_s - X <= tolerance * A_s`` (:attr:`Relation.encloser` is the larger; on equal
       areas, the lower index);
    3. ``"touch"``: adjacent, with ``X <= tolerance * A_s``;
    4. ``"overlap"``: otherwise.

    Parameters
    ----------
    footprints : array_like of bool, shape (K, H, W)
        Layer footprints, e.g. from :func:`layer_footprints`.
    tolerance : float, optional
        Fraction of the smaller footprint forgiven as anti-aliasing noise, in [0, 0.5)
        (default 0.02).

    Returns
    -------
    dict
        ``{(i, j): Relation}`` for every pair ``i < j`` whose footprints are both non-empty;
        empty when fewer than two layers are visible.

    Raises
    ------
    DVRInputError
        If ``footprints`` is malformed (see :func:`subregions`) or ``tolerance`` is outside
        [0, 0.5).

    Examples
    --------
    >>> fp = np.zeros((2, 4, 6), bool)
    >>> fp[0, :, :3] = True  # left half
    >>> fp[1, :, 3:] = True  # right half, sharing an edge
    >>> layer_relations(fp)[(0, 1)].kind
    'touch'
    """
    fp = _as_footprints(footprints)
    return _relations(_bitmask(fp), fp.shape[0], tolerance)


def _relations(layer_set: np.ndarray, k: int, tolerance: float) -> dict:
    """:func:`layer_relations` of the ``k`` layers of a (H, W) layer-set bitmask image."""
    if not 0.0 <= float(tolerance) < 0.5:
        raise DVRInputError(f"tolerance must lie in [0, 0.5), got {tolerance!r}")
    tol = float(tolerance)
    # pixel counts per distinct layer set give every area and pairwise intersection exactly
    flat = layer_set.ravel()
    if k <= 16:
        count = np.bincount(flat, minlength=1 << k)
        sets = np.flatnonzero(count)
        count = count[sets]
    else:
        sets, count = np.unique(flat, return_counts=True)
    member = ((sets[:, None].astype(np.int64) >> np.arange(k)) & 1).astype(np.int64)  # (sets, k)
    area = (member * count[:, None]).sum(axis=0).astype(np.float64)
    inter = (member * count[:, None]).T @ member
    # i and j are adjacent when a pixel of j has layer i within its 8-neighbourhood
    adjacent = np.zeros((k, k), bool)
    nk = kernels("dvr_perception.measures._kernels")
    if nk is not None:
        for i, seen in enumerate(nk.neighbour_sets(layer_set, k).tolist()):
            adjacent[i] = (seen >> np.arange(k)) & 1 == 1
    else:
        near = _dilate8(layer_set[None])[0]
        for i in range(k):
            if area[i]:
                near_i = (near.ravel() >> np.uint32(i)) & np.uint32(1) == 1
                seen = np.bitwise_or.reduce(flat[near_i])
                adjacent[i] = (int(seen) >> np.arange(k)) & 1 == 1
    result: dict[tuple[int, int], Relation] = {}
    for i in range(k):
        for j in range(i + 1, k):
            if area[i] == 0 or area[j] == 0:
                continue
            x, small = int(inter[i, j]), min(area[i], area[j])
            encloser = None
            if not adjacent[i, j]:
                kind = "separate"
            elif small - x <= tol * small:
                kind, encloser = "enclose", (i if area[i] >= area[j] else j)
            elif x <= tol * small:
                kind = "touch"
            else:
                kind = "overlap"
            result[(i, j)] = Relation(kind=kind, layers=(i, j), encloser=encloser, intersection=x)
    return result
