"""Automatic structure proposal from the intensity histogram (multi-level Otsu).

The histogram is split into ``n_structures + 1`` classes by
:func:`skimage.filters.threshold_multiotsu`; the lowest class is taken as background (air,
resin, empty space) and every other class becomes one range structure.  Ranges touch at the
thresholds, importance rises evenly with intensity (inner, denser structures are usually the
ones of interest) and colours come from a fixed colour-blind-safe palette.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures._counts import int_histogram
from dvr_perception.structures.spec import Structure, StructureSpec

__all__ = ["propose_structures"]

#: Okabe–Ito colour-blind-safe palette (without black), in the order structures are coloured.
PALETTE = (
    (0.902, 0.624, 0.000),  # orange
    (0.337, 0.706, 0.914),  # sky blue
    (0.000, 0.620, 0.451),  # bluish green
    (0.941, 0.894, 0.259),  # yellow
    (0.835, 0.369, 0.000),  # vermilion
    (0.000, 0.447, 0.698),  # blue
    (0.800, 0.475, 0.655),  # reddish purple
    (0.600, 0.600, 0.600),  # grey
)
MAX_STRUCTURES = len(PALETTE)
_MAX_SAMPLES = 4_000_000
_OTSU_BUDGET = 1e8  # ~0.4 s of multi-Otsu work
_DASH = "\N{EN DASH}"


def _histogram(data: np.ndarray, seed: int):
    """Equal-width histogram ``(counts, bin centres, bin width)`` and the distinct values.

    Integer data get one bin per integer; floating-point data (sampled when large) 1024 bins.
    ``distinct`` holds every occupied value (integers, or the sampled floats when there are few).
    """
    flat = data.ravel()
    if data.dtype.kind in "ui":
        lo, hi = int(flat.min()), int(flat.max())
        if hi - lo < 2**20:
            counts = int_histogram(data, lo, hi - lo + 1).astype(np.float64)
            centres = np.arange(lo, hi + 1, dtype=np.float64)
            return counts, centres, 1.0, centres[counts > 0]
    if flat.size > _MAX_SAMPLES:
        rng = np.random.default_rng(seed)
        flat = flat[rng.choice(flat.size, _MAX_SAMPLES, replace=False)]
    flat = flat.astype(np.float64)
    distinct = np.unique(flat)
    counts, edges = np.histogram(flat, bins=1024)
    centres = 0.5 * (edges[:-1] + edges[1:])
    return counts.astype(np.float64), centres, float(edges[1] - edges[0]), distinct


def _rebin(counts: np.ndarray, centres: np.ndarray, width: float, nbins: int):
    """Merge neighbouring bins (keeping empty ones) until there are at most ``nbins``."""
    factor = math.ceil(len(counts) / nbins)
    if factor <= 1:
        return counts, centres
    padded = np.zeros(math.ceil(len(counts) / factor) * factor)
    padded[: len(counts)] = counts
    merged = padded.reshape(-1, factor).sum(axis=1)
    first = centres[0] - width / 2
    new_centres = first + (np.arange(len(merged)) + 0.5) * factor * width
    return merged, new_centres


def _max_bins(classes: int) -> int:
    """Largest bin count for which multi-Otsu stays within a fixed work budget."""
    nbins = 256
    while nbins > 16 and classes * nbins ** (classes - 1) / math.factorial(classes - 1) > (
        _OTSU_BUDGET
    ):
        nbins //= 2
    return nbins


def _thresholds(counts, centres, width, distinct, classes: int) -> np.ndarray:
    """Up to ``classes - 1`` increasing cuts, each midway between two occupied values."""
    if len(distinct) <= classes:
        return 0.5 * (distinct[:-1] + distinct[1:])
    c, v = _rebin(counts, centres, width, _max_bins(classes))
    if np.count_nonzero(c) < classes:  # a few far-apart clusters of values
        occupied = v[c > 0]
        t = 0.5 * (occupied[:-1] + occupied[1:])
    else:
        from skimage.filters import threshold_multiotsu  # imported here: 0.4 s, rarely needed

        t = np.asarray(threshold_multiotsu(hist=(c, v), classes=classes), dtype=np.float64)
    # values from a threshold bin's centre upwards go to the upper class (as np.digitize)
    k = np.searchsorted(distinct, t, side="left")
    k = k[(k > 0) & (k < len(distinct))]
    return np.unique(0.5 * (distinct[k - 1] + distinct[k]))


def _label(lo: float, hi: float, integer: bool, last: bool) -> str:
    """``"lo–hi"`` with, for integer data, the first and last integer the range holds."""
    if integer:  # a shared edge value belongs to the upper range
        top = math.floor(hi) if last else math.ceil(hi) - 1
        return f"{math.ceil(lo)}{_DASH}{top}"
    return f"{lo:.4g}{_DASH}{hi:.4g}"


def propose_structures(volume, *, n_structures: int = 3, seed: int = 0) -> StructureSpec:
    """Propose ``n_structures`` range structures from the histogram of ``volume``.

    Parameters
    ----------
    volume : Volume
        The volume to analyse.
    n_structures : int
        Number of structures wanted (1 to 8).  Fewer are proposed, with a
        :class:`~dvr_perception.errors.DVRWarning`, when the volume has too few distinct values.
    seed : int
        Seed of the random voxel sample used for large floating-point volumes (integer volumes
        use the exact histogram); the result is deterministic for a given seed.

    Returns
    -------
    StructureSpec
        Contiguous, touching ranges above the background class, named
        ``"layer k (lo–hi)"``, importance rising from 0.15 to 0.85 with intensity.

    Raises
    ------
    DVRInputError
        If ``n_structures`` is out of range or the volume is constant.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> data = np.repeat(np.array([0, 0, 100, 200], np.uint8), 8).reshape(2, 4, 4)
    >>> spec = propose_structures(Volume(data), n_structures=2)
    >>> [s.range for s in spec.structures]
    [(50.0, 150.0), (150.0, 200.0)]
    """
    if isinstance(n_structures, bool) or not isinstance(n_structures, (int, np.integer)):
        raise DVRInputError(
            f"propose_structures: n_structures must be an integer, got {n_structures!r}"
        )
    if not 1 <= n_structures <= MAX_STRUCTURES:
        raise DVRInputError(
            f"propose_structures: n_structures must be in [1, {MAX_STRUCTURES}], got {n_structures}"
        )
    data = volume.data
    counts, centres, width, distinct = _histogram(data, int(seed))
    if len(distinct) < 2:
        raise DVRInputError(
            f"volume {volume.name!r}: all voxels have the value {distinct[0]:g}; nothing to propose"
        )
    n = n_structures
    if len(distinct) <= n:
        warnings.warn(
            f"volume {volume.name!r} has only {len(distinct)} distinct value(s); proposing "
            f"{len(distinct) - 1} structure(s) instead of {n}",
            DVRWarning,
            stacklevel=2,
        )
        n = len(distinct) - 1
    # n + 1 classes: the lowest one is the background
    cuts = _thresholds(counts, centres, width, distinct, n + 1)
    vmax = float(data.max())
    integer = data.dtype.kind in "ui"
    edges = [float(c) for c in cuts if c < vmax] + [vmax]
    if len(edges) - 1 < n:
        warnings.warn(
            f"volume {volume.name!r}: the histogram supports only {len(edges) - 1} "
            f"structure(s); proposing {len(edges) - 1} instead of {n}",
            DVRWarning,
            stacklevel=2,
        )
    k = len(edges) - 1
    importances = [0.5] if k == 1 else list(np.linspace(0.15, 0.85, k))
    structures = []
    for i in range(k):
        lo, hi = edges[i], edges[i + 1]
        name = f"layer {i + 1} ({_label(lo, hi, integer, i == k - 1)})"
        structures.append(
            Structure(
                name=name,
                importance=round(float(importances[i]), 4),
                color=PALETTE[i],
                range=(lo, hi),
            )
        )
    return StructureSpec(structures=tuple(structures))
