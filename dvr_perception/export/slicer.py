"""3D Slicer volume-property file (``.vp.json``, Slicer's volume-property schema v1.0.0).

Layout written (the keys Slicer's ``vtkMRMLVolumePropertyJsonStorageNode`` reads and writes)::

    {"@schema": ".../volume-property-schema-v1.0.0.json#",
     "volumeProperties": [{
        "effectiveRange": [lo, hi],
        "isoSurfaceValues": [], "independentComponents": true, "interpolationType": "linear",
        "useClippedVoxelIntensity": false, "clippedVoxelIntensity": 0.0,
        "scatteringAnisotropy": 0.0,
        "components": [{
           "componentWeight": 1.0, "shade": bool,
           "lighting": {"diffuse", "ambient", "specular", "specularPower"},
           "disableGradientOpacity": true, "scalarOpacityUnitDistance": u,
           "rgbTransferFunction": {"type": "colorTransferFunction",
                                   "points": [{"x", "color": [r, g, b], "midpoint", "sharpness"}]},
           "scalarOpacity": {"type": "piecewiseLinearFunction",
                             "points": [{"x", "y", "midpoint", "sharpness"}]},
           "gradientOpacity": {... constant 1 ...}}]}],
     "dvr_perception": {"structures": [...], "notes": [...]}}

The transfer-function points are the nodes of
:func:`dvr_perception.export.vtk.to_vtk_transfer_functions`.  Gradient opacity is
disabled (the project's renderer has none).  Slicer has one material per component, so the
first structure's lighting is written; when structures' lighting differ a
:class:`~dvr_perception.errors.DVRWarning` is emitted and a note is added.  The extra top-level
``"dvr_perception"`` object is allowed by the schema (``additionalProperties``) and ignored by
Slicer.

Label structures (a spec of a 3D Slicer segmentation, ``--structures organs.seg.nrrd``)
    A volume property maps voxel values to colour and opacity, so it cannot colour a CT by a
    segmentation.  For a spec whose structures are all label structures the property is written
    for the *label volume* itself: each segment's label value ``L`` gets its colour and its
    rendering opacity on ``[L - 0.45, L + 0.45]`` (0 between labels and on the background 0),
    and ``interpolationType`` is ``"nearest"`` so that samples keep the voxels' label values.
    In Slicer, load the ``.seg.nrrd`` as a volume (not as a segmentation) so that its voxels
    keep the label values, and apply the ``.vp.json`` to it in Volume Rendering.  The
    ``"dvr_perception"`` block then also holds ``"segments"``: one ``{"name", "label",
    "color", "opacity", "importance"}`` per structure, with the segment names, so the optimised
    opacities can be carried back to the segments (e.g. as segment opacities in Segmentations).
    A spec that mixes range and label structures is refused.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from dvr_perception._files import write_json
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.export._common import check_intensity_spec, transfer_nodes
from dvr_perception.structures.spec import StructureSpec

__all__ = ["SLICER_VP_SCHEMA", "save_slicer_vp", "slicer_volume_property"]

#: The schema URL Slicer writes into ``.vp.json`` files.
SLICER_VP_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/VolumeRendering/"
    "Resources/Schema/volume-property-schema-v1.0.0.json#"
)


def _function(kind: str, points: list[dict]) -> dict:
    return {"type": kind, "points": points}


def _unit_distance(spec, volume, notes: list[str]) -> float:
    unit = spec.rendering.opacity_unit_distance
    if unit is None and volume is not None:
        unit = min(float(s) for s in volume.spacing)
    if unit is None:
        notes.append(
            "scalarOpacityUnitDistance: the spec sets no opacity_unit_distance and no volume "
            "was given; wrote 1.0 (pass the volume to use its smallest voxel spacing)"
        )
        return 1.0
    unit = float(unit)
    if not (math.isfinite(unit) and unit > 0):
        raise DVRInputError(f"rendering.opacity_unit_distance must be positive, got {unit}")
    return unit


def slicer_volume_property(spec, volume=None, *, opacities=None) -> dict:
    """3D Slicer ``.vp.json`` document rendering ``spec`` like our VTK transfer functions.

    Parameters
    ----------
    spec : StructureSpec
        Range structures, or label structures only (see the module docstring).
    volume : Volume, optional
        The volume to be rendered: its scalar range widens ``effectiveRange`` and its smallest
        voxel spacing is the opacity unit distance when the spec sets none.
    opacities : array_like, optional
        One rendering opacity per structure (default: each structure's ``render_opacity``).

    Returns
    -------
    dict
        The JSON document (see the module docstring).

    Raises
    ------
    DVRInputError
        If ``spec`` mixes label and range structures, an opacity is out of [0, 1] or the unit
        distance is not positive.

    Warns
    -----
    DVRWarning
        If structures' lighting differ (the first structure's is written).

    Examples
    --------
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> spec = StructureSpec((Structure("bone", 0.8, (1, 1, 1), range=(100, 200), edge=0.1),))
    >>> vp = slicer_volume_property(spec)
    >>> comp = vp["volumeProperties"][0]["components"][0]
    >>> [(p["x"], p["y"]) for p in comp["scalarOpacity"]["points"]]
    [(100.0, 0.0), (110.0, 0.8), (190.0, 0.8), (200.0, 0.0)]
    """
    notes: list[str] = []
    labelled = isinstance(spec, StructureSpec) and all(s.label is not None for s in spec.structures)
    extra: dict = {}
    if labelled:
        color, opacity, extra = _label_nodes(spec, opacities)
        notes.append(
            "label structures: this property renders the segmentation's label volume (load the "
            ".seg.nrrd as a volume, nearest interpolation); 'segments' lists the segments"
        )
    else:
        check_intensity_spec(spec, "Slicer volume property")
        color, opacity = transfer_nodes(spec, opacities)
    lights = [s.lighting for s in spec.structures]
    light = lights[0]
    if any(lt != light for lt in lights[1:]):
        msg = (
            "structures have different lighting; a Slicer volume property has one material "
            f"per component, so structure {spec.structures[0].name!r}'s lighting was written"
        )
        warnings.warn(msg, DVRWarning, stacklevel=2)
        notes.append(msg)
    unit = _unit_distance(spec, volume, notes)
    xs = [n[0] for n in opacity] + [n[0] for n in color]
    lo, hi = min(xs), max(xs)
    if volume is not None and not labelled:
        vlo, vhi = volume.scalar_range
        lo, hi = min(lo, vlo), max(hi, vhi)
    component = {
        "componentWeight": 1.0,
        "shade": bool(spec.rendering.shade),
        "lighting": {
            "diffuse": float(light.diffuse),
            "ambient": float(light.ambient),
            "specular": float(light.specular),
            "specularPower": float(light.specular_power),
        },
        "disableGradientOpacity": True,
        "scalarOpacityUnitDistance": unit,
        "rgbTransferFunction": _function(
            "colorTransferFunction",
            [{"x": n[0], "color": n[1:4], "midpoint": n[4], "sharpness": n[5]} for n in color],
        ),
        "scalarOpacity": _function(
            "piecewiseLinearFunction",
            [{"x": n[0], "y": n[1], "midpoint": n[2], "sharpness": n[3]} for n in opacity],
        ),
        "gradientOpacity": _function(
            "piecewiseLinearFunction",
            [{"x": x, "y": 1.0, "midpoint": 0.5, "sharpness": 0.0} for x in (0.0, 1.0)],
        ),
    }
    return {
        "@schema": SLICER_VP_SCHEMA,
        "volumeProperties": [
            {
                "effectiveRange": [lo, hi],
                "isoSurfaceValues": [],
                "independentComponents": True,
                "interpolationType": "nearest" if labelled else "linear",
                "useClippedVoxelIntensity": False,
                "clippedVoxelIntensity": 0.0,
                "scatteringAnisotropy": 0.0,
                "components": [component],
            }
        ],
        "dvr_perception": {"structures": list(spec.names), **extra, "notes": notes},
    }


def _label_nodes(spec, opacities) -> tuple[list[list[float]], list[list[float]], dict]:
    """Colour and opacity nodes that give each label value its structure's colour and opacity."""
    from dvr_perception.structures.transfer import _opacities

    ops = _opacities(spec, opacities)
    order = sorted(range(len(spec.structures)), key=lambda i: spec.structures[i].label)
    color: list[list[float]] = []
    opacity: list[list[float]] = []
    for i in order:
        s = spec.structures[i]
        label, rgb, op = float(s.label), [float(c) for c in s.colour], float(ops[i])
        for x, y in ((label - _HALF, 0.0), (label - _EDGE, op), (label + _EDGE, op)):
            opacity.append([x, y, 0.5, 0.0])
        opacity.append([label + _HALF, 0.0, 0.5, 0.0])
        for x in (label - _EDGE, label + _EDGE):
            color.append([x, *rgb, 0.5, 0.0])
    segments = [
        {
            "name": s.name,
            "label": int(s.label),
            "color": [float(c) for c in s.colour],
            "opacity": float(ops[i]),
            "importance": float(s.importance),
        }
        for i, s in enumerate(spec.structures)
    ]
    return color, opacity, {"segments": segments}


#: Half-width of a label's flat opacity (and colour) around its value, and where it reaches 0.
_EDGE, _HALF = 0.45, 0.5


def save_slicer_vp(spec, path, volume=None, *, opacities=None) -> Path:
    """Write :func:`slicer_volume_property` to a ``.vp.json`` file (atomically).

    Parameters
    ----------
    spec : StructureSpec
        Range structures only.
    path : str or os.PathLike
        Output file; Slicer recognises the ``.vp.json`` extension.  Its directory must exist.
    volume : Volume, optional
        See :func:`slicer_volume_property`.
    opacities : array_like, optional
        One rendering opacity per structure.

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import json, tempfile
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> spec = StructureSpec((Structure("bone", 0.8, (1, 1, 1), range=(100, 200)),))
    >>> out = save_slicer_vp(spec, Path(tempfile.mkdtemp()) / "bone.vp.json")
    >>> sorted(json.loads(out.read_text()))
    ['@schema', 'dvr_perception', 'volumeProperties']
    """
    doc = slicer_volume_property(spec, volume, opacities=opacities)
    return write_json(path, doc)
