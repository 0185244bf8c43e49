"""Automatic structure proposal: tissue classes for a CT in Hounsfield units, else data classes.

**CT in Hounsfield units** (:func:`is_hounsfield`: signed values whose minimum lies where air
and the CT's padding lie, -3100 to -900, with at least 0.1 % of the voxels at air (-900 or
below) and 1 % at fat, water or soft tissue (-200 to 200); or a DICOM series or file, whose
values come rescaled, with a minimum of -50 or below and that 1 % of soft tissue).  The
structures are the standard HU windows of the tissues present (at least 0.1 % of the voxels,
metal 0.001 %):

============================  ==============  =========  ==========
structure                     HU              colour     importance
============================  ==============  =========  ==========
air and lung                  -950 to -400    pale blue  0.15
fat                           -190 to -30     yellow     0.1
soft tissue                   -30 to 150      pink       0.3
contrast-enhanced vessels     150 to 300      red        0.8
bone                          300 to 3000     ivory      0.9
metal                         3000 and up     steel      0.5
============================  ==============  =========  ==========

Fat and soft tissue are the body-composition thresholds (-190/-30/150 HU).  The vessel window
is proposed only when the histogram has a mode there (an enhanced scan); otherwise bone starts
at 150 HU.  Air below -950 HU (around the patient) is background, not a structure.

**Any other volume**: classes found in the data.  The intensity histogram (exact for integer
data, else 1024 bins of a seeded sample) is split by optimal one-dimensional k-means (dynamic
programming over the bins, deterministic).  The number of classes is chosen by the data: the
smallest that leaves at most :data:`UNEXPLAINED` of the variance left by the background /
foreground split unexplained (at most 8 structures); ``n_structures`` asks for a count instead.
The lowest class is taken as background (air, resin, empty space); when the lowest value alone
holds more than :data:`SPIKE` of the voxels (padding), it alone is the background and the
classes above it are found again without it, whose weight would pull the values next to it
into the background class.  Every other class becomes
one range structure named by intensity order, ranges touching midway between the classes,
importance rising with intensity, colours from a ramp by intensity rank (dark red to ivory).
The lowest classes, each holding more voxels than all classes above it together and at least
10 % of the volume (the bulk that fills it: noise around an object, an embedding), start nearly
transparent (opacity :data:`BULK_OPACITY`), as does a lowest class whose histogram only falls
away from the background (its tail: noise, partial volume at the surface).

Limits: intensity alone cannot part tissues whose values overlap (in an MRI, grey and white
matter are cut at the k-means boundary of one histogram hump, not by anatomy); a broad class
(two humps with a valley between, a long falling tail) can be split over several classes; a
CT stored without its rescale (e.g. shifted to unsigned values) is treated as any data; thin
contrast vessels under the 0.1 % floor are folded into bone.
"""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures._counts import int_histogram
from dvr_perception.structures.spec import Structure, StructureSpec

__all__ = ["HU_TISSUES", "describe_proposal", "is_hounsfield", "propose_structures"]

#: Colours of the data classes, from the lowest intensity to the highest (darker and warmer to
#: lighter): a class's colour is picked evenly along this ramp by its rank, so the densest class
#: is always ivory, as bone is in a CT, and neighbours stay apart in hue and lightness.
PALETTE = (
    (0.50, 0.18, 0.12),  # dark red-brown
    (0.80, 0.30, 0.16),  # brick red
    (0.93, 0.52, 0.20),  # orange
    (0.85, 0.66, 0.42),  # tan
    (0.95, 0.62, 0.66),  # pink
    (0.55, 0.75, 0.90),  # pale blue
    (0.95, 0.90, 0.55),  # light yellow
    (1.00, 0.96, 0.84),  # ivory
)
MAX_STRUCTURES = len(PALETTE)
#: Share of the post-background variance the chosen number of data classes may leave.
UNEXPLAINED = 0.08
#: Share of the voxels above which the lowest value alone is the background (a spike: padding).
SPIKE = 0.9
#: Starting opacity of a data class with more voxels than all classes above it.
BULK_OPACITY = 0.03
#: Tissue windows of a CT in Hounsfield units: name, low, high, colour, importance.
HU_TISSUES = (
    ("air and lung", -950.0, -400.0, (0.62, 0.76, 0.90), 0.15),
    ("fat", -190.0, -30.0, (0.96, 0.84, 0.36), 0.1),
    ("soft tissue", -30.0, 150.0, (0.93, 0.60, 0.62), 0.3),
    ("contrast-enhanced vessels", 150.0, 300.0, (0.80, 0.08, 0.10), 0.8),
    ("bone", 300.0, 3000.0, (1.00, 0.96, 0.84), 0.9),
    ("metal", 3000.0, math.inf, (0.70, 0.76, 0.82), 0.5),
)
_MIN_SHARE = 1e-3
_MIN_SHARE_METAL = 1e-5
_MAX_SAMPLES = 4_000_000
_MAX_BINS = 1024
_DASH = "\N{EN DASH}"


def _sample(data: np.ndarray, seed: int) -> np.ndarray:
    """All values, or a seeded random sample of :data:`_MAX_SAMPLES` of them."""
    flat = data.reshape(-1)
    if flat.size > _MAX_SAMPLES:
        rng = np.random.default_rng(seed)
        flat = flat[rng.choice(flat.size, _MAX_SAMPLES, replace=False)]
    return flat


def _histogram(data: np.ndarray, seed: int):
    """Occupied bins ``(counts, lower edges, upper edges, centres)`` of at most 1024 bins.

    Integer data are counted exactly (one bin per integer, merged evenly when the range is
    wider than 1024); floating-point data are sampled (seeded) into 1024 equal bins.
    """
    lo, hi = float(data.min()), float(data.max())
    if data.dtype.kind in "ui" and hi - lo < 2**20:
        counts = int_histogram(data, int(lo), int(hi - lo) + 1).astype(np.float64)
        factor = math.ceil(len(counts) / _MAX_BINS)
        if factor > 1:
            padded = np.zeros(math.ceil(len(counts) / factor) * factor)
            padded[: len(counts)] = counts
            counts = padded.reshape(-1, factor).sum(axis=1)
        lower = lo + np.arange(len(counts)) * factor - 0.5
        upper = lower + factor
        centres = np.minimum(lower + 0.5 * factor, hi)
    else:
        flat = _sample(data, seed).astype(np.float64)
        counts, edges = np.histogram(flat, bins=_MAX_BINS, range=(lo, hi))
        counts = counts.astype(np.float64)
        lower, upper = edges[:-1], edges[1:]
        centres = 0.5 * (lower + upper)
    keep = counts > 0
    return counts[keep], lower[keep], upper[keep], centres[keep]


def _kmeans_1d(x: np.ndarray, w: np.ndarray, kmax: int):
    """Optimal weighted 1-D k-means of sorted ``x`` for every k up to ``kmax``.

    Returns ``(sse, splits)``: ``sse[k]`` the within-class sum of squares with k classes,
    ``splits[k]`` the k - 1 indices where a new class starts.
    """
    n = len(x)
    cw = np.concatenate([[0.0], np.cumsum(w)])
    cs = np.concatenate([[0.0], np.cumsum(w * x)])
    cq = np.concatenate([[0.0], np.cumsum(w * x * x)])
    i = np.arange(n + 1)[:, None]
    j = np.arange(n + 1)[None, :]
    ww = cw[j] - cw[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        cost = (cq[j] - cq[i]) - np.where(ww > 0, (cs[j] - cs[i]) ** 2 / ww, 0.0)
    cost = np.where(j > i, np.maximum(cost, 0.0), np.inf)  # segment [i, j)
    best = np.full((kmax + 1, n + 1), np.inf)
    back = np.zeros((kmax + 1, n + 1), dtype=np.int64)
    best[1] = cost[0]
    for k in range(2, kmax + 1):
        total = best[k - 1][:, None] + cost
        back[k] = np.argmin(total, axis=0)
        best[k] = total[back[k], np.arange(n + 1)]
    sse, splits = {}, {}
    for k in range(1, kmax + 1):
        sse[k] = float(best[k, n])
        cut, end = [], n
        for kk in range(k, 1, -1):
            end = int(back[kk, end])
            cut.append(end)
        splits[k] = sorted(cut)
    return sse, splits


def _data_classes(data: np.ndarray, n_structures, seed: int):
    """Range edges ``[lo_1, hi_1 = lo_2, ..., hi_k]`` of the data classes above background.

    Also returns the share of the voxels (of the sample, for sampled float data) of each class.
    """
    counts, lower, upper, centres = _histogram(data, seed)
    if n_structures is None:
        kmax = min(MAX_STRUCTURES + 1, len(counts))
    else:
        kmax = min(n_structures + 1, len(counts))
    sse, splits = _kmeans_1d(centres, counts, kmax)
    if n_structures is None:
        floor = UNEXPLAINED * sse[min(2, kmax)]
        k = next((k for k in range(2, kmax + 1) if sse[k] <= floor), kmax)
    else:
        k = kmax
    starts = list(splits[k])
    if n_structures is None and len(starts) > 1:
        # the background class is not cut through its own hump (noise around one value): the
        # first class above it joins it when the counts at the cut are at least half its peak
        first = starts[0]
        if min(counts[first - 1], counts[first]) >= 0.5 * counts[:first].max():
            starts = starts[1:]
    if len(counts) > len(starts) + 1 and counts[0] > SPIKE * counts.sum():
        # the lowest value alone holds most of the voxels (padding, clipped air): it is the
        # background on its own, and the classes above it are found again without it, whose
        # weight would drag the values next to it into the background class
        _, fg_splits = _kmeans_1d(centres[1:], counts[1:], len(starts))
        starts = [1] + [s + 1 for s in fg_splits[len(starts)]]
    cuts = [0.5 * (upper[s - 1] + lower[s]) for s in starts]
    vmax = float(data.max())
    edges = [c for c in cuts if c < vmax] + [vmax]
    sizes = [
        float(counts[(centres >= lo) & ((centres < hi) if i < len(edges) - 2 else True)].sum())
        / float(counts.sum())
        for i, (lo, hi) in enumerate(itertools.pairwise(edges))
    ]
    return edges, sizes, _is_tail(counts[(centres >= edges[0]) & (centres < edges[1])])


def _is_tail(counts: np.ndarray) -> bool:
    """Whether a class's histogram only falls away from its lower end (the background's tail).

    Examples
    --------
    >>> _is_tail(np.array([90, 70, 50, 30, 20, 10.0])), _is_tail(np.array([10, 40, 90, 40, 10.0]))
    (True, False)
    """
    if len(counts) < 3:
        return False
    smooth = np.convolve(counts, np.ones(3) / 3.0, mode="valid")
    top = int(np.argmax(smooth))
    return bool(top <= len(smooth) // 5 and smooth[-1] < 0.5 * smooth[top])


def is_hounsfield(volume) -> bool:
    """Whether ``volume`` looks like a CT in Hounsfield units (see the module docstring).

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> ct = np.full((4, 4, 4), -1000, np.int16)
    >>> ct[1:3, 1:3, 1:3] = 40
    >>> is_hounsfield(Volume(ct)), is_hounsfield(Volume((ct + 1024).astype(np.uint16)))
    (True, False)
    """
    data = volume.data
    if data.dtype.kind not in "if":
        return False
    lo, hi = (float(v) for v in volume.scalar_range)
    if lo < -3100.0 or hi < 0.0 or hi > 40000.0:
        return False
    sample = _sample(data, 0)
    tissue = np.count_nonzero((sample >= -200) & (sample <= 200)) / sample.size
    if _from_dicom(volume) and lo <= -50.0:  # rescaled DICOM with fat or air: a CT
        return bool(tissue >= 0.01)
    if lo > -900.0:
        return False
    air = np.count_nonzero(sample <= -900) / sample.size
    return bool(air >= 0.001 and tissue >= 0.01)


def _from_dicom(volume) -> bool:
    """Whether ``volume`` was read from DICOM (a series folder or a ``.dcm`` file)."""
    source = str(getattr(volume, "source", "") or "")
    if not source or source == "phantom":
        return False
    from pathlib import Path

    path = Path(source)
    return path.suffix.lower() in (".dcm", ".dicom", ".ima") or path.is_dir()


def _has_mode(values: np.ndarray, lo: float, hi: float) -> bool:
    """Whether the histogram (10-unit bins) has a local peak in ``[lo, hi)`` above its dips."""
    counts, edges = np.histogram(values, bins=np.arange(lo - 50.0, hi + 100.0 + 1, 10.0))
    smooth = np.convolve(counts, np.ones(3) / 3.0, mode="same")
    centres = 0.5 * (edges[:-1] + edges[1:])
    inside = np.nonzero((centres >= lo) & (centres < hi))[0]
    if len(inside) == 0:
        return False
    p = inside[np.argmax(smooth[inside])]
    left, right = smooth[: p + 1].min(), smooth[p:].min()
    return smooth[p] > 0 and smooth[p] >= 1.25 * max(left, right)


def _hounsfield_structures(volume, seed: int) -> list[Structure]:
    """Return the tissue windows of :data:`HU_TISSUES` present in ``volume``."""
    sample = _sample(volume.data, seed).astype(np.float64)
    n = sample.size
    vmax = float(sample.max()) if n else 0.0
    vmax = max(vmax, float(volume.scalar_range[1]))
    contrast = _has_mode(sample, 150.0, 300.0)
    structures = []
    for name, lo, hi, color, importance in HU_TISSUES:
        if name.startswith("contrast") and not contrast:
            continue
        if name == "bone" and not contrast:
            lo = 150.0
        top = min(hi, vmax)
        if lo >= top:
            continue
        share = np.count_nonzero((sample >= lo) & (sample <= top)) / n
        need = _MIN_SHARE_METAL if name == "metal" else _MIN_SHARE
        if share < need:
            continue
        structures.append(
            Structure(name=name, importance=importance, colour=color, range=(lo, top))
        )
    return structures


def _class_colour(i: int, k: int) -> tuple[float, float, float]:
    """Colour of class ``i`` of ``k``: evenly along :data:`PALETTE`, the last one ivory.

    Examples
    --------
    >>> [_class_colour(i, 3) for i in range(3)] == [PALETTE[0], PALETTE[4], PALETTE[7]]
    True
    """
    if k <= 1:
        return PALETTE[-1]
    return PALETTE[round(i * (len(PALETTE) - 1) / (k - 1))]


def _label(lo: float, hi: float, integer: bool, last: bool) -> str:
    """``"lo–hi"`` with, for integer data, the first and last integer the range holds."""
    if integer:  # a shared edge value belongs to the upper range
        top = math.floor(hi) if last else math.ceil(hi) - 1
        return f"{math.ceil(lo)}{_DASH}{top}"
    return f"{lo:.4g}{_DASH}{hi:.4g}"


def describe_proposal(spec: StructureSpec) -> str:
    """One line saying how :func:`propose_structures` made ``spec`` (by tissue or from data).

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> ct = np.full((8, 8, 8), -1000, np.int16)
    >>> ct[2:6, 2:6, 2:6] = 40
    >>> describe_proposal(propose_structures(Volume(ct)))
    'structures proposed by tissue from Hounsfield units'
    """
    names = {t[0] for t in HU_TISSUES}
    if spec.structures and all(s.name in names for s in spec.structures):
        return "structures proposed by tissue from Hounsfield units"
    return "structures proposed from the data"


def propose_structures(
    volume, *, n_structures: int | None = None, seed: int = 0, hounsfield: bool | None = None
) -> StructureSpec:
    """Propose range structures for ``volume``: tissues of a CT in HU, else data classes.

    Parameters
    ----------
    volume : Volume
        The volume to analyse.
    n_structures : int, optional
        Number of data classes wanted (1 to 8), instead of the number the data choose; the
        Hounsfield tissue windows are then not used.  Fewer are proposed, with a
        :class:`~dvr_perception.errors.DVRWarning`, when the volume has too few distinct values.
    seed : int
        Seed of the random voxel sample used for large floating-point volumes (integer volumes
        use the exact histogram); the result is deterministic for a given seed.
    hounsfield : bool, optional
        Force (``True``) or refuse (``False``) the tissue windows; default
        :func:`is_hounsfield`.

    Returns
    -------
    StructureSpec
        Tissue structures (``"bone"``, ``"soft tissue"``...) or data classes named
        ``"class k (lo–hi)"`` by rising intensity, touching, importance rising from 0.15 to
        0.85 with intensity.

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
    if n_structures is not None:
        if isinstance(n_structures, bool) or not isinstance(n_structures, (int, np.integer)):
            raise DVRInputError(
                f"propose_structures: n_structures must be an integer, got {n_structures!r}"
            )
        if not 1 <= n_structures <= MAX_STRUCTURES:
            raise DVRInputError(
                f"propose_structures: n_structures must be in [1, {MAX_STRUCTURES}], got "
                f"{n_structures}"
            )
    data = volume.data
    lo_v, hi_v = (float(v) for v in volume.scalar_range)
    if lo_v == hi_v:
        raise DVRInputError(
            f"volume {volume.name!r}: all voxels have the value {lo_v:g}; nothing to propose"
        )
    if n_structures is None and (hounsfield if hounsfield is not None else is_hounsfield(volume)):
        structures = _hounsfield_structures(volume, int(seed))
        if structures:
            return StructureSpec(structures=tuple(structures))
    n = n_structures
    if n is not None:
        distinct = _histogram(data, int(seed))[0].size if data.dtype.kind in "ui" else None
        if distinct is not None and distinct <= n:
            warnings.warn(
                f"volume {volume.name!r} has only {distinct} distinct value(s); proposing "
                f"{distinct - 1} structure(s) instead of {n}",
                DVRWarning,
                stacklevel=2,
            )
            n = distinct - 1
    edges, sizes, tail = _data_classes(data, n, int(seed))
    k = len(edges) - 1
    if n is not None and k < n:
        warnings.warn(
            f"volume {volume.name!r}: the histogram supports only {k} structure(s); proposing "
            f"{k} instead of {n}",
            DVRWarning,
            stacklevel=2,
        )
    integer = data.dtype.kind in "ui"
    importances = [0.5] if k == 1 else list(np.linspace(0.15, 0.85, k))
    structures = []
    bulk = k > 1
    for i in range(k):
        lo, hi = float(edges[i]), float(edges[i + 1])
        name = f"class {i + 1} ({_label(lo, hi, integer, i == k - 1)})"
        # the lowest classes, each with more voxels than all classes above it, fill the volume
        # (background noise, an embedding, the bulk around an object): almost transparent
        bulk = bulk and i < k - 1 and sizes[i] > max(sum(sizes[i + 1 :]), 0.1)
        faint = bulk or (i == 0 and k > 1 and tail)
        structures.append(
            Structure(
                name=name,
                importance=round(float(importances[i]), 4),
                colour=_class_colour(i, k),
                range=(lo, hi),
                opacity=BULK_OPACITY if faint else None,
            )
        )
    return StructureSpec(structures=tuple(structures))
