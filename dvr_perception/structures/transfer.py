"""Transfer-function tables for the engine: membership, classification and lookup tables.

The lookup table built by :func:`build_lut` has the same discretisation as the table
``vtkFixedPointVolumeRayCastMapper`` builds for the same data type and scalar range (see
``docs/vtk_conventions.md``, facts 1-3): for integer data whose range spans at most 32767,
one entry per integer value; otherwise 32768 entries spread over the range.  Entry ``i``
stands for the value ``lo + i / scale`` and a value ``v`` maps to the entry
``floor((v - lo) * scale)`` (clipped to the table).

Structure ids are indices into ``spec.structures``; ``-1`` means "no structure".  A value has
a structure id exactly where its membership is positive (the open interval ``(lo, hi)``).

The converters to and from VTK transfer functions are with the other exporters, in
:mod:`dvr_perception.export.vtk` (their old names here are deprecated aliases).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from dvr_perception._deprecation import deprecated_alias
from dvr_perception.errors import DVRInputError
from dvr_perception.structures.spec import Structure, StructureSpec

__all__ = [
    "TransferLUT",
    "build_lut",
    "classify",
    "colour_table",
    "lut_index",
    "membership",
    "opacity_table",
]

#: Table size VTK's fixed-point mapper uses for float data and wide integer ranges.
VTK_FLOAT_TABLE_SIZE = 32768


@dataclass(frozen=True, eq=False)
class TransferLUT:
    """A discretised structure classification (VTK fixed-point table layout).

    Attributes
    ----------
    lo : float
        Value of entry 0 (the data minimum).
    scale : float
        Entries per unit value: ``index = floor((v - lo) * scale)``, clipped to the table.
    ids : numpy.ndarray
        ``int16[N]`` structure id of each entry (``-1`` for none).
    membership : numpy.ndarray
        ``float32[N]`` membership of each entry's value in its structure.
    """

    lo: float
    scale: float
    ids: np.ndarray
    membership: np.ndarray

    @property
    def size(self) -> int:
        """Number of table entries."""
        return int(self.ids.shape[0])

    @property
    def values(self) -> np.ndarray:
        """The value each entry stands for (``lo + i / scale``), float64."""
        return self.lo + np.arange(self.size) / self.scale


def _check_range_structure(s: Structure, k: int) -> tuple[float, float, float]:
    if s.range is None:
        raise DVRInputError(
            f"structure {k} ({s.name!r}): has no intensity range (it is a label structure); "
            "expected 'range': [lo, hi]"
        )
    lo, hi = (float(x) for x in s.range)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise DVRInputError(
            f"structure {k} ({s.name!r}): range must be two finite numbers with lo < hi, "
            f"got {s.range}"
        )
    edge = float(s.edge)
    if not 0.0 <= edge <= 0.5:
        raise DVRInputError(f"structure {k} ({s.name!r}): edge must be in [0, 0.5], got {s.edge}")
    return lo, hi, edge


def _range_structures(spec: StructureSpec) -> list[tuple[int, float, float, float]]:
    """``(id, lo, hi, edge)`` of the range structures, validated and checked for overlap."""
    out = [
        (k, *_check_range_structure(s, k))
        for k, s in enumerate(spec.structures)
        if s.range is not None
    ]
    ordered = sorted(out, key=lambda t: t[1])
    for a, b in itertools.pairwise(ordered):
        if b[1] < a[2]:
            na, nb = spec.structures[a[0]].name, spec.structures[b[0]].name
            raise DVRInputError(
                f"structures {na!r} {list(spec.structures[a[0]].range)} and {nb!r} "
                f"{list(spec.structures[b[0]].range)} overlap; ranges may touch but not overlap"
            )
    return out


def _trapezoid(v: np.ndarray, lo: float, hi: float, edge: float) -> np.ndarray:
    inside = (v > lo) & (v < hi)
    w = edge * (hi - lo)
    if w == 0:
        return inside.astype(np.float64)
    m = np.minimum((v - lo) / w, (hi - v) / w)
    return np.where(inside, np.clip(m, 0.0, 1.0), 0.0)


def membership(values, structure: Structure) -> np.ndarray:
    """Trapezoidal membership of intensities in one range structure.

    Parameters
    ----------
    values : array_like
        Intensities (any shape).
    structure : Structure
        A structure with an intensity ``range``.

    Returns
    -------
    numpy.ndarray
        float32 array of the same shape, in [0, 1].

    Examples
    --------
    >>> s = Structure("bone", 1.0, (1, 1, 1), range=(100, 200), edge=0.1)
    >>> membership([100, 105, 150, 200], s).tolist()
    [0.0, 0.5, 1.0, 0.0]
    """
    lo, hi, edge = _check_range_structure(structure, 0)
    v = np.asarray(values, dtype=np.float64)
    return _trapezoid(v, lo, hi, edge).astype(np.float32)


def classify(values, spec: StructureSpec) -> tuple[np.ndarray, np.ndarray]:
    """Structure id and membership of every intensity.

    Label structures are ignored (they are classified by the label volume, not by intensity).

    Returns
    -------
    ids : numpy.ndarray
        int16, same shape as ``values``; ``-1`` where no structure has positive membership.
    membership : numpy.ndarray
        float32, same shape, 0 where ``ids == -1``.

    Examples
    --------
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(0, 10)),
    ...                       Structure("b", 1.0, (0, 0, 1), range=(10, 20))))
    >>> ids, m = classify([0, 5, 10, 15, 25], spec)
    >>> ids.tolist()
    [-1, 0, -1, 1, -1]
    """
    v = np.asarray(values, dtype=np.float64)
    ids = np.full(v.shape, -1, dtype=np.int16)
    mem = np.zeros(v.shape, dtype=np.float32)
    for k, lo, hi, edge in _range_structures(spec):
        m = _trapezoid(v, lo, hi, edge)
        hit = m > 0
        ids[hit] = k
        mem[hit] = m[hit]
    return ids, mem


def build_lut(spec: StructureSpec, *, scalar_range, dtype) -> TransferLUT:
    """Build the structure lookup table VTK's fixed-point mapper would build.

    Parameters
    ----------
    spec : StructureSpec
        The structures (label structures are ignored).
    scalar_range : tuple of float
        ``(min, max)`` of the **data** (VTK uses the actual range, not the dtype's).
    dtype : numpy dtype-like
        Data type of the volume.

    Returns
    -------
    TransferLUT

    Examples
    --------
    >>> spec = StructureSpec((Structure("a", 1.0, (1, 1, 1), range=(10, 20)),))
    >>> lut = build_lut(spec, scalar_range=(0, 255), dtype="uint8")
    >>> lut.size, int(lut.ids[15]), float(lut.membership[15])
    (256, 0, 1.0)
    """
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise DVRInputError(f"build_lut: dtype must be a numpy dtype, got {dtype!r}") from None
    if dt.kind not in "uif":
        raise DVRInputError(f"build_lut: dtype must be integer or float, got {dt}")
    try:
        lo, hi = (float(x) for x in scalar_range)
    except (TypeError, ValueError):
        raise DVRInputError(
            f"build_lut: scalar_range must be (min, max), got {scalar_range!r}"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise DVRInputError(
            f"build_lut: scalar_range must be finite with min <= max, got {scalar_range}"
        )
    if dt.kind in "ui" and hi - lo <= VTK_FLOAT_TABLE_SIZE - 1:
        n, scale = int(hi - lo + 1), 1.0
        values = lo + np.arange(n, dtype=np.float64)
    else:
        n = VTK_FLOAT_TABLE_SIZE
        scale = (n - 1) / (hi - lo) if hi > lo else 1.0
        values = lo + np.arange(n, dtype=np.float64) * ((hi - lo) / (n - 1))
    ids, mem = classify(values, spec)
    return TransferLUT(lo=lo, scale=scale, ids=ids, membership=mem)


def lut_index(values, lut: TransferLUT) -> np.ndarray:
    """Table index of each value: ``floor((v - lo) * scale)`` clipped to ``[0, N-1]`` (int32).

    Examples
    --------
    >>> spec = StructureSpec((Structure("a", 1.0, (1, 1, 1), range=(10, 20)),))
    >>> lut = build_lut(spec, scalar_range=(5, 50), dtype="uint8")
    >>> lut_index([5, 6.7, 50, 99], lut).tolist()
    [0, 1, 45, 45]
    """
    v = np.asarray(values, dtype=np.float64)
    idx = np.floor((v - lut.lo) * lut.scale)
    return np.clip(idx, 0, lut.size - 1).astype(np.int32)


def _opacities(spec: StructureSpec, opacities) -> np.ndarray:
    if opacities is None:
        ops = np.array([s.render_opacity for s in spec.structures], dtype=np.float64)
    else:
        ops = np.asarray(opacities, dtype=np.float64).ravel()
        if ops.shape != (len(spec.structures),):
            raise DVRInputError(
                f"opacities: expected {len(spec.structures)} values (one per structure), "
                f"got {ops.size}"
            )
    if not np.all(np.isfinite(ops)) or np.any((ops < 0) | (ops > 1)):
        raise DVRInputError(f"opacities: every opacity must be in [0, 1], got {ops.tolist()}")
    return ops


def opacity_table(lut: TransferLUT, opacities) -> np.ndarray:
    """Per-entry opacity ``opacities[id] * membership`` (0 where id = -1), float32[N].

    ``opacities`` has one value per structure of the spec the table was built from.
    """
    ops = np.asarray(opacities, dtype=np.float64).ravel()
    nmax = int(lut.ids.max(initial=-1)) + 1
    if ops.size < nmax or not np.all(np.isfinite(ops)) or np.any((ops < 0) | (ops > 1)):
        raise DVRInputError(
            f"opacities: expected at least {nmax} values in [0, 1], got {ops.tolist()}"
        )
    out = np.zeros(lut.size, dtype=np.float32)
    hit = lut.ids >= 0
    out[hit] = ops[lut.ids[hit]] * lut.membership[hit]
    return out


def colour_table(lut: TransferLUT, colours) -> np.ndarray:
    """Per-entry RGB colour of the entry's structure (black where id = -1), float32[N, 3]."""
    cols = np.asarray(colours, dtype=np.float64).reshape(-1, 3)
    nmax = int(lut.ids.max(initial=-1)) + 1
    if cols.shape[0] < nmax or not np.all(np.isfinite(cols)):
        raise DVRInputError(f"colours: expected at least {nmax} finite RGB triples")
    out = np.zeros((lut.size, 3), dtype=np.float32)
    hit = lut.ids >= 0
    out[hit] = cols[lut.ids[hit]]
    return out


color_table = deprecated_alias(
    colour_table,
    "dvr_perception.structures.transfer.color_table",
    "dvr_perception.structures.transfer.colour_table",
)

#: Names that moved to :mod:`dvr_perception.export.vtk` (deprecated aliases for one release).
_MOVED = ("GPU_TABLE_SAMPLES", "spec_from_vtk", "to_vtk_property", "to_vtk_transfer_functions")


def __getattr__(name: str):
    if name in _MOVED:
        import warnings

        warnings.warn(
            f"dvr_perception.structures.transfer.{name} is deprecated; use "
            f"dvr_perception.export.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        from dvr_perception.export import vtk  # layering: deprecated alias

        return getattr(vtk, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
