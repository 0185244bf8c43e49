"""VTK transfer functions and volume properties from a structure spec, and back.

:func:`to_vtk_transfer_functions` gives each range structure of a spec exactly its trapezoid
as a ``vtkPiecewiseFunction`` (opacity) and a ``vtkColorTransferFunction``;
:func:`to_vtk_property` wraps them in a ``vtkVolumeProperty`` (the VTK reference renderer, the
PyVista front end); :func:`spec_from_vtk` recovers the structures from such functions.  The
ParaView and 3D Slicer exporters of this package write the same nodes.  VTK is imported on
first use.
"""

from __future__ import annotations

import math
import warnings

from dvr_perception._deprecation import renamed_keyword
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures.spec import Lighting, Structure, StructureSpec
from dvr_perception.structures.transfer import _opacities, _range_structures

__all__ = [
    "GPU_TABLE_SAMPLES",
    "spec_from_vtk",
    "to_vtk_property",
    "to_vtk_transfer_functions",
    "transfer_points",
]

#: Table entries a GPU renderer (VTK's GPU ray caster in ParaView) may sample our transfer
#: functions into (``to_vtk_transfer_functions(..., samples=...)``): its lookup texture is the
#: data range over the smallest node spacing, rounded up to a power of two, and OpenGL allows
#: 16384 texels (Mesa) or more; 4096 leaves room for a data range four times the nodes' span.
GPU_TABLE_SAMPLES = 4096
#: Offset of the colour points inside each range (fraction of the range width).
_COLOR_INSET = 1e-4
#: Width of the "vertical" ramp that stands for ``edge == 0`` (fraction of the range width).
_STEP_WIDTH = 1e-7


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
    color, opacity = transfer_points(spec, opacities=opacities, samples=samples,
                                     scalar_range=scalar_range)  # fmt: skip
    from dvr_perception import _vtk  # VTK only here: the core imports without it

    ctf = _vtk.vtkColorTransferFunction()
    otf = _vtk.vtkPiecewiseFunction()
    for x, y in opacity:
        otf.AddPoint(x, y)
    for x, r, g, b in color:
        ctf.AddRGBPoint(x, r, g, b)
    return ctf, otf


def transfer_points(
    spec: StructureSpec, *, opacities=None, samples: int | None = None, scalar_range=None
) -> tuple[list[tuple[float, float, float, float]], list[tuple[float, float]]]:
    """Return the points :func:`to_vtk_transfer_functions` adds, in its order (no VTK).

    Returns
    -------
    color : list of (x, r, g, b)
        The ``AddRGBPoint`` calls of the colour function.
    opacity : list of (x, y)
        The ``AddPoint`` calls of the opacity function.
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
    color, opacity = [], []
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
        opacity.extend((float(x), float(y)) for x, y in nodes)
        last = nodes[-1]
        inset = max(_COLOR_INSET * width, floor)
        r, g, b = (float(c) for c in spec.structures[k].colour)
        color.append((float(lo + inset), r, g, b))
        color.append((float(hi - inset), r, g, b))
    return color, opacity


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


@renamed_keyword("color_tf", "colour_tf")
def spec_from_vtk(colour_tf, opacity_tf, *, names=None) -> StructureSpec:
    """Recover trapezoid structures from VTK transfer functions (inverse of the converter).

    The opacity function must consist of 4-point trapezoids ``(lo, 0), (a, o), (b, o), (hi, 0)``
    (touching trapezoids may share their zero points).  Importance = plateau opacity, colour =
    colour at the plateau centre, edge = ramp width / range width.  ``colour_tf`` is the
    ``vtkColorTransferFunction`` (keyword ``color_tf=`` is a deprecated alias).
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
        colour = tuple(float(c) for c in colour_tf.GetColor(0.5 * (a + b)))
        structures.append(Structure(name, float(o), colour, range=(lo, hi), edge=edge))
        i += 3
    if names is not None and len(names) != len(structures):
        raise DVRInputError(
            f"names: got {len(names)} names for {len(structures)} structures "
            "in the opacity function"
        )
    return StructureSpec(tuple(structures))
