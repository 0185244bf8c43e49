"""Transfer-function tables for the engine, and converters to and from VTK transfer functions.

The lookup table built by :func:`build_lut` has the same discretisation as the table
``vtkFixedPointVolumeRayCastMapper`` builds for the same data type and scalar range (see
``docs/vtk_conventions.md``, facts 1-3): for integer data whose range spans at most 32767,
one entry per integer value; otherwise 32768 entries spread over the range.  Entry ``i``
stands for the value ``lo + i / scale`` and a value ``v`` maps to the entry
``floor((v - lo) * scale)`` (clipped to the table).

Structure ids are indices into ``spec.structures``; ``-1`` means "no structure".  A value has
a structure id exactly where its membership is positive (the open interval ``(lo, hi)``).
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures.spec import Lighting, Structure, StructureSpec

__all__ = [
    "GPU_TABLE_SAMPLES",
    "TransferLUT",
    "build_lut",
    "classify",
    "color_table",
    "lut_index",
    "membership",
    "opacity_table",
    "spec_from_vtk",
    "to_vtk_property",
    "to_vtk_transfer_functions",
]

#: Table size VTK's fixed-point mapper uses for float data and wide integer ranges.
VTK_FLOAT_TABLE_SIZE = 32768
#: Table entries a GPU renderer (VTK's GPU ray caster in ParaView) may sample our transfer
#: functions into (``to_vtk_transfer_functions(..., samples=...)``): its lookup texture is the
#: data range over the smallest node spacing, rounded up to a power of two, and OpenGL allows
#: 16384 texels (Mesa) or more; 4096 leaves room for a data range four times the nodes' span.
GPU_TABLE_SAMPLES = 4096
#: Offset of the colour points inside each range (fraction of the range width).
_COLOR_INSET = 1e-4
#: Width of the "vertical" ramp that stands for ``edge == 0`` (fraction of the range width).
_STEP_WIDTH = 1e-7


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


def color_table(lut: TransferLUT, colors) -> np.ndarray:
    """Per-entry RGB colour of the entry's structure (black where id = -1), float32[N, 3]."""
    cols = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
    nmax = int(lut.ids.max(initial=-1)) + 1
    if cols.shape[0] < nmax or not np.all(np.isfinite(cols)):
        raise DVRInputError(f"colors: expected at least {nmax} finite RGB triples")
    out = np.zeros((lut.size, 3), dtype=np.float32)
    hit = lut.ids >= 0
    out[hit] = cols[lut.ids[hit]]
    return out


def to_vtk_transfer_functions(
    spec: StructureSpec, *, opacities=None, samples: int | None = None, scalar_range=None
):
    """Build VTK colour and scalar-opacity functions equal to the spec's trapezoids.

    Each structure gives four opacity points ``(lo, 0), (lo + w, o), (hi - w, o), (hi, 0)``
    (``w = edge * (hi - lo)``) and two colour points just inside ``(lo, hi)``, so VTK's
    colour interpolation never mixes two structures where the opacity is non-zero.

    Parameters
    ----------
    spec : StructureSpec
        Range structures only.
    opacities : array_like, optional
        One rendering opacity per structure (default: each structure's ``render_opacity``).
    samples : int, optional
        For a renderer that samples the functions into a table of about ``samples`` entries
        over ``scalar_range`` (VTK's GPU ray caster, ParaView): keep the nodes at least
        ``span / samples`` apart (``span``: the wider of ``scalar_range`` and the nodes'
        extent).  VTK's GPU mapper sizes its lookup texture as the range over the smallest
        node spacing, rounded up to a power of two; the colour points' inset of
        ``1e-4 * (hi - lo)`` alone asks for 32768 texels on the engine data, more than
        OpenGL allows (16384 on Mesa), and VTK warns ("incorrect lookup table mapping").  A
        spacing finer than one table entry cannot be shown anyway.  Default: exact nodes
        (the CPU reference renderer's tables need them).  :data:`GPU_TABLE_SAMPLES` is the
        value for ParaView.
    scalar_range : (float, float), optional
        The data range the renderer maps over (with ``samples``).

    Returns
    -------
    (vtkColorTransferFunction, vtkPiecewiseFunction)
    """
    ops = _opacities(spec, opacities)
    if any(s.range is None for s in spec.structures):
        bad = next(s.name for s in spec.structures if s.range is None)
        raise DVRInputError(
            f"structure {bad!r}: label structures cannot be expressed as a VTK intensity "
            "transfer function; expected only range structures"
        )
    ranges = sorted(_range_structures(spec), key=lambda t: t[1])
    gap = _node_gap(ranges, samples, scalar_range)
    from dvr_perception import _vtk  # VTK only here: the core imports without it

    ctf = _vtk.vtkColorTransferFunction()
    otf = _vtk.vtkPiecewiseFunction()
    last = None  # the opacity node added last
    for k, lo, hi, edge in ranges:
        width = hi - lo
        floor = min(gap, width / 3.0)
        w = max(edge * width, _STEP_WIDTH * width, floor)
        o = float(ops[k])
        nodes = [(lo, 0.0), (lo + w, o), (hi - w, o), (hi, 0.0)]
        if gap and nodes[2][0] - nodes[1][0] < gap:  # a (near) triangle: one peak node
            nodes[1:3] = [(0.5 * (lo + hi), o)]
        if gap and last is not None and last[1] == 0.0 and 0.0 < lo - last[0] < gap:
            nodes = nodes[1:]  # zero from the previous structure's end already
        for x, y in nodes:
            otf.AddPoint(x, y)
        last = nodes[-1]
        inset = max(_COLOR_INSET * width, floor)
        r, g, b = (float(c) for c in spec.structures[k].color)
        ctf.AddRGBPoint(lo + inset, r, g, b)
        ctf.AddRGBPoint(hi - inset, r, g, b)
    return ctf, otf


def _node_gap(ranges, samples, scalar_range) -> float:
    """Smallest node spacing for a table of ``samples`` entries (0: exact nodes)."""
    if samples is None or not ranges:
        return 0.0
    if int(samples) < 2:
        raise DVRInputError(f"samples: expected an integer >= 2, got {samples!r}")
    lo = min(r[1] for r in ranges)
    hi = max(r[2] for r in ranges)
    if scalar_range is not None:
        a, b = (float(v) for v in scalar_range)
        if math.isfinite(a) and math.isfinite(b):
            lo, hi = min(lo, a), max(hi, b)
    return (hi - lo) / int(samples)


def to_vtk_property(spec: StructureSpec, volume, *, opacities=None, shade=None):
    """Build a ``vtkVolumeProperty`` that renders ``volume`` with ``spec``.

    Linear interpolation; ``ScalarOpacityUnitDistance`` from ``spec.rendering`` or the smallest
    voxel spacing; one Phong material (the first structure's; a :class:`DVRWarning` is emitted
    when structures' lighting differ, because VTK's single-material mapper cannot show it).
    """
    ctf, otf = to_vtk_transfer_functions(spec, opacities=opacities)
    rs = spec.rendering
    unit = rs.opacity_unit_distance
    unit = float(min(volume.spacing)) if unit is None else float(unit)
    if not (math.isfinite(unit) and unit > 0):
        raise DVRInputError(f"rendering.opacity_unit_distance must be positive, got {unit}")
    from dvr_perception import _vtk

    prop = _vtk.vtkVolumeProperty()
    prop.SetColor(ctf)
    prop.SetScalarOpacity(otf)
    prop.SetInterpolationTypeToLinear()
    prop.SetScalarOpacityUnitDistance(unit)
    prop.SetShade(int(bool(rs.shade if shade is None else shade)))
    lights = [s.lighting for s in spec.structures]
    light = lights[0] if lights else Lighting()
    if any(lt != light for lt in lights[1:]):
        warnings.warn(
            "structures have different lighting; VTK's single-material volume mapper cannot "
            f"show per-structure lighting, using structure {spec.structures[0].name!r}'s",
            DVRWarning,
            stacklevel=2,
        )
    prop.SetAmbient(light.ambient)
    prop.SetDiffuse(light.diffuse)
    prop.SetSpecular(light.specular)
    prop.SetSpecularPower(light.specular_power)
    return prop


def _nodes(otf) -> list[tuple[float, float]]:
    node = [0.0, 0.0, 0.0, 0.0]
    out = []
    for i in range(otf.GetSize()):
        otf.GetNodeValue(i, node)
        out.append((float(node[0]), float(node[1])))
    return out


def spec_from_vtk(color_tf, opacity_tf, *, names=None) -> StructureSpec:
    """Recover trapezoid structures from VTK transfer functions (inverse of the converter).

    The opacity function must consist of 4-point trapezoids ``(lo, 0), (a, o), (b, o), (hi, 0)``
    (touching trapezoids may share their zero points).  Importance = plateau opacity, colour =
    colour at the plateau centre, edge = ramp width / range width.
    """
    pts = _nodes(opacity_tf)
    structures = []
    i = 0
    while i < len(pts):
        if pts[i][1] != 0.0:
            raise DVRInputError(
                f"opacity function: point {i} at x={pts[i][0]} starts a structure with "
                f"non-zero opacity {pts[i][1]}; expected the 4-point trapezoid pattern"
            )
        if i + 1 >= len(pts) or pts[i + 1][1] == 0.0:
            i += 1
            continue
        if i + 3 >= len(pts) or pts[i + 3][1] != 0.0 or pts[i + 1][1] != pts[i + 2][1]:
            raise DVRInputError(
                f"opacity function: points from x={pts[i][0]} do not form a trapezoid "
                "(0, o, o, 0); expected the 4-point pattern written by to_vtk_transfer_functions"
            )
        (lo, _), (a, o), (b, _), (hi, _) = pts[i : i + 4]
        edge = round((a - lo) / (hi - lo), 6)
        edge = 0.0 if edge <= 10 * _STEP_WIDTH else edge
        k = len(structures)
        name = names[k] if names is not None and k < len(names) else f"structure_{k + 1}"
        color = tuple(float(c) for c in color_tf.GetColor(0.5 * (a + b)))
        structures.append(Structure(name, float(o), color, range=(lo, hi), edge=edge))
        i += 3
    if names is not None and len(names) != len(structures):
        raise DVRInputError(
            f"names: got {len(names)} names for {len(structures)} structures "
            "in the opacity function"
        )
    return StructureSpec(tuple(structures))
