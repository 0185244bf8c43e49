"""Per-structure colour, opacity **and** Phong lighting in a PyVista plotter.

Mechanism: **independent components on** ``vtkFixedPointVolumeRayCastMapper``.  The scalar
array is repeated into ``n <= 4`` components, one per *material group* (structures with equal
:class:`~dvr_perception.structures.spec.Lighting`).  The ``vtkVolumeProperty`` gets, per
component ``c``, the colour and opacity trapezoids of the structures of group ``c`` only and
that group's ambient/diffuse/specular/power.  Structure ranges never overlap, so at any
sample at most one component has non-zero opacity; VTK then combines the components as
``alpha = sum(a_c**2) / sum(a_c) = a`` and ``colour = shade_c(colour_c) * a``, i.e. exactly
one transfer function with per-structure shading.  It is the mapper our engine reproduces
(:mod:`dvr_perception.rays.engine`), so the image agrees with the engine as closely as VTK's
single-material reference does (SSIM 0.997 on the 96x96 phantom).

Why not the alternatives (measured here, VTK 9.7, EGL + llvmpipe):

* ``vtkMultiVolume`` (one ``vtkVolume`` per structure on ``vtkOpenGLGPUVolumeRayCastMapper``,
  same input on each port) matches the engine unshaded (SSIM 0.995) but ignored the
  per-volume diffuse/specular terms (shaded SSIM 0.92-0.93, diffuse-only 0.89): no usable
  per-structure lighting.
* A label-map mask has no per-label material (used only for label structures, below).

Label structures (a spec with ``label`` ids and ``volume.labels``): our engine gives a sample
its nearest voxel's label's structure whatever its intensity, and classifies the other
samples by intensity.  VTK's way is a **label-map mask** on
``vtkOpenGLGPUVolumeRayCastMapper`` (``SetMaskInput`` + ``SetMaskTypeToLabelMap``; the mask
is sampled at the nearest voxel): the mask is ``1 + j`` on the voxels of label structure ``j``
(:func:`dvr_perception.rays._grid.label_map`) and 0 elsewhere; mask 0 uses the range
structures' transfer functions, mask ``1 + j`` a constant colour and opacity
(``vtkVolumeProperty.SetLabelColor`` / ``SetLabelScalarOpacity``).  Jittering and automatic
sample distances are off.  The GPU mapper's shading differs from the fixed-point one in one
way that matters: it adds the ambient term uncoloured (a grey wash), so the ambient
coefficient is moved into the diffuse one (see :func:`_label_property`).  Measured against the
engine (VTK 9.7, EGL + llvmpipe): a 24^3 ramp with a labelled cube at 64x64, SSIM 0.967
unshaded and 0.948 shaded (0.932 with the uncoloured ambient); the 40^3 phantom with a
two-segment Slicer segmentation at 96x96, SSIM 0.986 unshaded and 0.951 shaded (0.913).  The
fixed-point mapper reaches 0.97-0.99 on range structures; the ramp alone through this GPU
path gives 0.948 shaded too, so the label mask itself costs nothing: the loss is the GPU
mapper's shading.  Tried on the 24^3 phantom (shaded, issue 21): the ambient kept (grey wash)
0.932, half of it folded 0.935, a *headlight*-type light (VTK's one-headlight shader colours
the ambient, but takes the light direction per sample from the camera position and uses Phong
reflection, not the half vector) 0.908, gradient opacity disabled and other specular powers no
change (no highlight in that view; gradient opacity was not in use) -- the fold stays.  Limit:
one material for the whole
volume (the most important structure's lighting; a :class:`~dvr_perception.errors.DVRWarning`
when the spec has several).

Limit: VTK has at most 4 independent components.  Unshaded specs always use one component.
A shaded spec with more than 4 distinct materials falls back to merging the most similar
materials (each merged group uses the lighting of its most important structure) and emits a
:class:`~dvr_perception.errors.DVRWarning`; colour and opacity stay exact per structure.

Lights follow our engine (``docs/vtk_conventions.md``, fact 22): PyVista's default lights are
removed and one camera light is added at ``spec.rendering.light_direction`` (camera
coordinates) with ``light_intensity``, white colour and white ambient colour.  The background
is ``spec.background``; the sample distance is ours, with automatic adjustment off.
"""

from __future__ import annotations

import math
import warnings
import weakref
from dataclasses import dataclass, field, replace

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.export.vtk import to_vtk_transfer_functions
from dvr_perception.structures.spec import Lighting, StructureSpec
from dvr_perception.structures.transfer import _opacities
from dvr_perception.volume.volume import Volume

__all__ = ["MAX_MATERIALS", "StructureVolume", "add_structures", "apply", "material_groups"]

#: Independent components VTK's volume mappers support.
MAX_MATERIALS = 4

# plotter -> {name: StructureVolume}; weak so a closed plotter is not kept alive
_HANDLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@dataclass(eq=False)
class StructureVolume:
    """Handle of a volume added by :func:`add_structures` (pass it to :func:`apply`).

    Attributes
    ----------
    plotter : weakref.proxy of pyvista.Plotter
        The plotter the volume lives in (a weak proxy: the handle is stored in a
        ``WeakKeyDictionary`` keyed by the plotter, so it must not keep the plotter alive).
    renderer : pyvista.Renderer
        The renderer (sub-plot) holding the volume and its light.
    volume : Volume
        The scalar volume.
    spec : StructureSpec
        The spec currently shown (with the opacities applied).
    actor : pyvista.Volume
        The ``vtkVolume``.
    light : pyvista.Light
        The one camera light.
    groups : tuple of tuple of int
        Structure ids of each component (material group).
    labelled : bool
        True when the spec has label structures (GPU mapper with a label-map mask).
    name : str
        Actor name in the plotter.
    """

    plotter: object
    renderer: object
    volume: Volume
    spec: StructureSpec
    actor: object
    light: object
    groups: tuple = ()
    name: str = "dvr"
    labelled: bool = False
    _arrays: list = field(default_factory=list, repr=False)
    _mask_key: tuple = field(default=(), repr=False)


def _lighting_key(lt: Lighting) -> np.ndarray:
    return np.array(
        [lt.ambient, lt.diffuse, lt.specular, math.log2(max(lt.specular_power, 1.0)) / 7.0]
    )


def material_groups(spec: StructureSpec, *, max_groups: int = MAX_MATERIALS):
    """Group structures by material, merging the most similar ones beyond ``max_groups``.

    Parameters
    ----------
    spec : StructureSpec
        The structures; an unshaded spec gives one group.
    max_groups : int, default: 4
        Most groups allowed (VTK's independent-component limit).

    Returns
    -------
    groups : tuple of tuple of int
        Structure ids per group, in order of first appearance.
    lightings : tuple of Lighting
        The material each group is rendered with.
    merged : bool
        True when distinct materials had to share a group.

    Examples
    --------
    >>> from dvr_perception.structures.spec import Structure
    >>> dull = Lighting(specular=0.0)
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(0, 10)),
    ...                       Structure("b", 0.5, (0, 1, 0), range=(10, 20), lighting=dull),
    ...                       Structure("c", 0.5, (0, 0, 1), range=(20, 30))))
    >>> material_groups(spec)[0]
    ((0, 2), (1,))
    """
    if not spec.rendering.shade:
        return (tuple(range(len(spec.structures))),), (Lighting(),), False
    groups: list[list[int]] = []
    keys: list[Lighting] = []
    for k, s in enumerate(spec.structures):
        if s.lighting in keys:
            groups[keys.index(s.lighting)].append(k)
        else:
            keys.append(s.lighting)
            groups.append([k])
    merged = len(groups) > max_groups
    while len(groups) > max_groups:
        pairs = [(i, j) for i in range(len(groups)) for j in range(i + 1, len(groups))]
        i, j = min(
            pairs,
            key=lambda p: float(
                np.sum((_lighting_key(keys[p[0]]) - _lighting_key(keys[p[1]])) ** 2)
            ),
        )
        groups[i] = sorted(groups[i] + groups.pop(j))
        keys.pop(j)
        lead = max(groups[i], key=lambda k: (spec.structures[k].importance, -k))
        keys[i] = spec.structures[lead].lighting
    return tuple(tuple(g) for g in groups), tuple(keys), merged


def _check(volume, spec, opacities) -> np.ndarray:
    if not isinstance(volume, Volume):
        raise DVRInputError(f"volume: expected a Volume, got {type(volume).__name__}")
    if not isinstance(spec, StructureSpec):
        raise DVRInputError(f"spec: expected a StructureSpec, got {type(spec).__name__}")
    if not spec.structures:
        raise DVRInputError("spec: expected at least one structure, got none")
    if _label_ids(spec) and volume.labels is None:
        raise DVRInputError(
            "volume.labels: the spec has label structures but the volume has no label volume "
            "(load the spec's 'labels' file with attach_labels, or Volume(..., labels=...))"
        )
    return _opacities(spec, opacities)


def _distance(value, volume: Volume, what: str) -> float:
    d = float(min(volume.spacing)) if value is None else float(value)
    if not (math.isfinite(d) and d > 0):
        raise DVRInputError(f"spec.rendering.{what} must be positive, got {d}")
    return d


def _property(spec, volume, ops, groups, lightings):
    import pyvista as pv

    unit = _distance(spec.rendering.opacity_unit_distance, volume, "opacity_unit_distance")
    prop = pv.VolumeProperty()
    prop.SetIndependentComponents(1)
    prop.SetInterpolationTypeToLinear()
    for c, (group, lt) in enumerate(zip(groups, lightings, strict=True)):
        sub = replace(spec, structures=tuple(spec.structures[k] for k in group))
        ctf, otf = to_vtk_transfer_functions(sub, opacities=[ops[k] for k in group])
        prop.SetColor(c, ctf)
        prop.SetScalarOpacity(c, otf)
        prop.SetScalarOpacityUnitDistance(c, unit)
        prop.SetShade(c, int(bool(spec.rendering.shade)))
        prop.SetAmbient(c, lt.ambient)
        prop.SetDiffuse(c, lt.diffuse)
        prop.SetSpecular(c, lt.specular)
        prop.SetSpecularPower(c, lt.specular_power)
    return prop


def _label_ids(spec: StructureSpec) -> tuple[int, ...]:
    """Structure indices of the label structures of ``spec``, in order."""
    return tuple(k for k, s in enumerate(spec.structures) if s.label is not None)


def _label_mask(volume: Volume, spec: StructureSpec):
    """uint8 mask image: ``1 + j`` on voxels of label structure ``j``, else 0."""
    from dvr_perception import _vtk
    from dvr_perception.rays._grid import label_map
    from dvr_perception.volume.convert import to_vtk_image

    ids = _label_ids(spec)
    lab = label_map(volume, [spec.structures[k].label for k in ids])
    flat = np.ascontiguousarray(lab).reshape(-1)
    arr = _vtk.numpy_to_vtk(flat, deep=False)
    arr.SetName("mask")
    img = _vtk.vtkImageData()
    img.CopyStructure(to_vtk_image(volume))
    img.GetPointData().SetScalars(arr)
    return img, [flat]


def _label_property(spec, volume, ops):
    """One-material property: range structures on mask 0, label structure j on mask 1 + j."""
    import pyvista as pv

    from dvr_perception import _vtk

    ids = _label_ids(spec)
    ranged = tuple(k for k in range(len(spec.structures)) if k not in ids)
    lead = max(range(len(spec.structures)), key=lambda k: (spec.structures[k].importance, -k))
    lt = spec.structures[lead].lighting
    unit = _distance(spec.rendering.opacity_unit_distance, volume, "opacity_unit_distance")
    prop = pv.VolumeProperty()
    prop.SetIndependentComponents(1)
    prop.SetInterpolationTypeToLinear()
    if ranged:
        sub = replace(spec, structures=tuple(spec.structures[k] for k in ranged))
        ctf, otf = to_vtk_transfer_functions(sub, opacities=[ops[k] for k in ranged])
    else:
        ctf, otf = _vtk.vtkColorTransferFunction(), _vtk.vtkPiecewiseFunction()
        ctf.AddRGBPoint(0.0, 0.0, 0.0, 0.0)
        otf.AddPoint(0.0, 0.0)
    prop.SetColor(ctf)
    prop.SetScalarOpacity(otf)
    lo, hi = (float(v) for v in (np.min(volume.data), np.max(volume.data)))
    lo, hi = lo - 1.0, hi + 1.0
    for j, k in enumerate(ids):
        s = spec.structures[k]
        c = _vtk.vtkColorTransferFunction()
        o = _vtk.vtkPiecewiseFunction()
        for v in (lo, hi):
            c.AddRGBPoint(v, *(float(x) for x in s.colour))
            o.AddPoint(v, float(ops[k]))
        prop.SetLabelColor(1 + j, c)
        prop.SetLabelScalarOpacity(1 + j, o)
    prop.SetScalarOpacityUnitDistance(unit)
    prop.SetShade(int(bool(spec.rendering.shade)))
    # The GPU mapper adds the ambient term uncoloured (ka x the light's ambient colour, the
    # same grey on every structure: measured ambient-only on a red ramp, it gives
    # (0.18, 0.18, 0.18) where the engine and the fixed-point mapper give (0.18, 0, 0)).  The
    # ambient part goes into the diffuse one instead: exact where a surface faces the camera
    # light, darker where it turns away, and no grey wash over the colours.
    prop.SetAmbient(0.0)
    prop.SetDiffuse(min(1.0, lt.diffuse + lt.ambient))
    prop.SetSpecular(lt.specular)
    prop.SetSpecularPower(lt.specular_power)
    return prop


def _image(volume: Volume, ncomp: int):
    from dvr_perception import _vtk
    from dvr_perception.volume.convert import to_vtk_image

    base = to_vtk_image(volume)
    if ncomp == 1:
        return base, []
    flat = np.ascontiguousarray(volume.data).reshape(-1)
    comps = np.ascontiguousarray(np.repeat(flat[:, None], ncomp, axis=1))
    arr = _vtk.numpy_to_vtk(comps, deep=False)
    arr.SetName("scalars")
    img = _vtk.vtkImageData()
    img.CopyStructure(base)
    img.GetPointData().SetScalars(arr)
    return img, [comps]  # keep the numpy buffer alive while VTK uses it


def _configure(handle: StructureVolume, spec: StructureSpec, ops: np.ndarray) -> None:
    """Set property, input, light and background of ``handle`` for ``spec``."""
    import pyvista as pv

    labelled = bool(_label_ids(spec))
    if labelled:
        groups, lightings = ((tuple(range(len(spec.structures))),), None)
        if spec.rendering.shade and len({s.lighting for s in spec.structures}) > 1:
            warnings.warn(
                "spec has label structures and several materials; VTK's label-map mask has "
                "one material, so every structure is lit like the most important one "
                "(colours and opacities stay per structure)",
                DVRWarning,
                stacklevel=3,
            )
    else:
        groups, lightings, merged = material_groups(spec)
        if merged:
            names = "; ".join(
                "+".join(spec.structures[k].name for k in g) for g in groups if len(g) > 1
            )
            warnings.warn(
                f"spec has more than {MAX_MATERIALS} distinct materials; VTK supports "
                f"{MAX_MATERIALS} independent components, so these structures share a "
                f"material: {names} (colours and opacities stay per structure)",
                DVRWarning,
                stacklevel=3,
            )
    volume = handle.volume
    sd = _distance(spec.rendering.sample_distance, volume, "sample_distance")
    mapper = handle.actor.GetMapper()
    mask_key = tuple(spec.structures[k].label for k in _label_ids(spec))
    if (
        mapper is None
        or labelled != handle.labelled
        or len(groups) != len(handle.groups)
        or mask_key != handle._mask_key
    ):
        # A new component count needs a new mapper *and* a new vtkVolume: both cache
        # per-component state (tables, gradients, transfer-function arrays) that VTK 9.7 does
        # not resize when the input's component count changes (heap corruption, then a
        # segmentation fault in a later render or free).  The new actor replaces the old one
        # under the same name; lights and camera stay.  Label structures need the GPU
        # mapper's label-map mask (rebuilt when the label ids change).
        from dvr_perception import _vtk

        if labelled:
            mapper = _vtk.rendering().vtkOpenGLGPUVolumeRayCastMapper()
            mapper.SetUseJittering(0)
            img, keep = _image(volume, 1)
            mask, keep_mask = _label_mask(volume, spec)
            mapper.SetInputData(img)
            mapper.SetMaskInput(mask)
            mapper.SetMaskTypeToLabelMap()
            keep = keep + keep_mask
        else:
            mapper = _vtk.rendering().vtkFixedPointVolumeRayCastMapper()
            mapper.SetImageSampleDistance(1.0)
            img, keep = _image(volume, len(groups))
            mapper.SetInputData(img)
        mapper.SetAutoAdjustSampleDistances(0)
        old = handle.actor
        if old.GetMapper() is not None:
            actor = pv.Volume()
            actor.SetVisibility(old.GetVisibility())
            actor.SetPickable(old.GetPickable())
            actor.SetUserMatrix(old.GetUserMatrix())
            actor.SetMapper(mapper)
            handle.renderer.add_actor(actor, name=handle.name, reset_camera=False, render=False)
            handle.actor = actor
        else:
            old.SetMapper(mapper)
        handle._arrays[:] = keep
    mapper.SetSampleDistance(sd)
    if labelled:
        handle.actor.SetProperty(_label_property(spec, volume, ops))
    else:
        handle.actor.SetProperty(_property(spec, volume, ops, groups, lightings))
    rs = spec.rendering
    handle.light.position = tuple(float(c) for c in rs.light_direction)
    handle.light.focal_point = (0.0, 0.0, 0.0)
    handle.light.intensity = float(rs.light_intensity)
    handle.renderer.set_background(pv.Color(tuple(float(c) for c in spec.background)))
    handle.groups = groups
    handle.labelled = labelled
    handle._mask_key = mask_key
    handle.spec = spec.with_opacities(ops)


def add_structures(plotter, volume: Volume, spec: StructureSpec, *, opacities=None, name="dvr"):
    """Add ``volume`` to ``plotter`` with per-structure colour, opacity and lighting.

    Replaces the active renderer's lights by the spec's one camera light and sets its
    background (see the module docstring for the VTK mechanism).

    Parameters
    ----------
    plotter : pyvista.Plotter
        Target plotter; the volume goes into its active renderer (sub-plot).
    volume : Volume
        The scalar volume.
    spec : StructureSpec
        Range and label structures, background and render settings (label structures need
        ``volume.labels``, e.g. from :func:`~dvr_perception.structures.io.attach_labels`).
    opacities : sequence of float, optional
        Rendering opacity per structure (default: each structure's ``render_opacity``).
    name : str, default: "dvr"
        Actor name (adding the same name again replaces the volume).

    Returns
    -------
    StructureVolume
        Handle for :func:`apply`.

    Examples
    --------
    >>> import pyvista as pv
    >>> from dvr_perception.structures import make_phantom
    >>> vol, spec = make_phantom(size=32)
    >>> pl = pv.Plotter(off_screen=True)  # doctest: +SKIP
    >>> handle = add_structures(pl, vol, spec)  # doctest: +SKIP
    >>> handle.groups  # doctest: +SKIP
    ((0, 1, 2, 3, 4, 5),)
    """
    import pyvista as pv

    if not isinstance(plotter, pv.Plotter):
        raise DVRInputError(f"plotter: expected a pyvista.Plotter, got {type(plotter).__name__}")
    if not isinstance(name, str) or not name:
        raise DVRInputError(f"name: expected a non-empty string, got {name!r}")
    ops = _check(volume, spec, opacities)
    renderer = plotter.renderer
    renderer.remove_all_lights()
    light = pv.Light(light_type="camera light")
    light.ambient_color = (1.0, 1.0, 1.0)
    light.diffuse_color = (1.0, 1.0, 1.0)
    light.specular_color = (1.0, 1.0, 1.0)
    renderer.add_light(light)
    actor = pv.Volume()
    handle = StructureVolume(
        weakref.proxy(plotter), renderer, volume, spec, actor, light, name=name
    )
    _configure(handle, spec, ops)
    plotter.add_actor(actor, name=name, reset_camera=not renderer.camera_set, render=False)
    _HANDLES.setdefault(plotter, {})[name] = handle
    return handle


def _resolve(target, name) -> StructureVolume:
    if isinstance(target, StructureVolume):
        return target
    handles = _HANDLES.get(target) if target is not None else None
    if not handles:
        raise DVRInputError(
            "plotter_or_handle: expected a StructureVolume or a plotter with a volume added by "
            f"add_structures, got {type(target).__name__}"
        )
    if name is None:
        if len(handles) > 1:
            raise DVRInputError(
                f"name: the plotter holds several structure volumes {sorted(handles)}; pass name="
            )
        return next(iter(handles.values()))
    if name not in handles:
        raise DVRInputError(
            f"name: no structure volume {name!r} in the plotter ({sorted(handles)})"
        )
    return handles[name]


def apply(plotter_or_handle, result_or_spec, *, opacities=None, name=None, render=True):
    """Update a volume added by :func:`add_structures` in place (TFs, materials, light).

    Parameters
    ----------
    plotter_or_handle : pyvista.Plotter or StructureVolume
        The handle, or the plotter holding it.
    result_or_spec : StructureSpec or object with a ``spec`` attribute
        The new spec, e.g. an optimisation result or an optimiser callback's intermediate
        result; it must have as many structures as the shown spec.
    opacities : sequence of float, optional
        Override the spec's rendering opacities.
    name : str, optional
        Which volume, when the plotter holds several.
    render : bool, default: True
        Render the plotter afterwards.

    Returns
    -------
    StructureVolume
        The updated handle.
    """
    handle = _resolve(plotter_or_handle, name)
    spec = getattr(result_or_spec, "spec", result_or_spec)
    if not isinstance(spec, StructureSpec):
        raise DVRInputError(
            "result_or_spec: expected a StructureSpec or a result with a .spec, got "
            f"{type(result_or_spec).__name__}"
        )
    if len(spec.structures) != len(handle.spec.structures):
        raise DVRInputError(
            f"result_or_spec: the spec has {len(spec.structures)} structures but the plotter "
            f"shows {len(handle.spec.structures)}; add it with add_structures instead"
        )
    if spec.names != handle.spec.names:
        raise DVRInputError(
            f"result_or_spec: its structures {list(spec.names)} are not the ones shown "
            f"{list(handle.spec.names)} (a result for a different volume or spec?); add it "
            "with add_structures instead"
        )
    ops = _check(handle.volume, spec, opacities)
    _configure(handle, spec, ops)
    if render:
        handle.plotter.render()
    return handle
