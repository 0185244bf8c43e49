"""The quick preview the browser renders itself (vtk.js) while the camera moves.

The volume at full resolution, reduced to every n-th voxel only above a memory budget of
:data:`PREVIEW_VOXELS` (256\u00b3) voxels, with the current transfer function (range
structures, one colour and opacity function as
:func:`~dvr_perception.export.vtk.to_vtk_transfer_functions` builds them for the
server's VTK image, with the same opacity unit distance), sits in a render window of its own
that the server never renders: trame-vtk sends its scene to the page, where vtk.js's GPU ray
caster draws it at interactive rate, with a sample every :data:`RAY_STEP_VOXELS` voxels along
the rays.  When the camera rests, the engine's exact image is shown again.  The page's label
names the resolution (:func:`preview_detail`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

__all__ = [
    "PREVIEW_VOXELS",
    "RAY_STEP_VOXELS",
    "Preview",
    "preview_detail",
    "preview_step",
    "preview_volume",
]

#: Memory budget of the preview: most voxels of the copy sent to the browser (256\u00b3, 16.8
#: million; 34 MB as 16-bit values).  A larger volume is reduced to every n-th voxel.
PREVIEW_VOXELS = 256**3


#: Voxels between two samples along a preview ray (the server's image: one sample a voxel).
#: vtk.js draws one full-size frame when the camera stops, which the server's exact image soon
#: covers; its cost grows with the samples per ray, and in software GL it held the page (and
#: with it the numbers of the rested view) for 1.4-1.7 s with one sample a voxel of cthead.
RAY_STEP_VOXELS = 2.0


def preview_step(shape, max_voxels: int = PREVIEW_VOXELS) -> int:
    """Return the smallest n such that every n-th voxel of ``shape`` fits ``max_voxels``.

    Examples
    --------
    >>> preview_step((256, 256, 113)), preview_step((256, 256, 257)), preview_step((512,) * 3)
    (1, 2, 2)
    """
    if int(max_voxels) < 1:
        raise ValueError(f"preview: max_voxels must be at least 1, got {max_voxels}")
    step = 1
    while math.prod(-(-int(d) // step) for d in shape) > int(max_voxels):
        step += 1
    return step


def preview_volume(volume, *, max_voxels: int = PREVIEW_VOXELS):
    """Return ``volume``, or every n-th voxel of it when it holds more than ``max_voxels``.

    The copy keeps the volume's origin (its first voxel), direction and ``oriented`` flag;
    labels are left out (the preview shows range structures only).  Values in 64-bit floats
    are sent as 32-bit floats (what vtk.js's textures hold).

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> full = Volume(np.zeros((130, 20, 64), np.uint8))
    >>> preview_volume(full) is full
    True
    >>> small = preview_volume(full, max_voxels=64**3 // 16)
    >>> small.data.shape, small.spacing
    ((44, 7, 22), (3.0, 3.0, 3.0))
    """
    step = preview_step(volume.data.shape, max_voxels)
    data = volume.data if step == 1 else volume.data[::step, ::step, ::step]
    if data.dtype == np.float64:
        data = data.astype(np.float32)
    if step == 1 and data is volume.data and volume.labels is None:
        return volume
    spacing = tuple(float(s) * step for s in volume.spacing)
    # the same grid, strided: every other field (origin, axes, orientation) stays
    return replace(volume, data=np.ascontiguousarray(data), spacing=spacing, labels=None)


def preview_detail(full_shape, shape) -> str:
    """Name the preview's resolution for the page's label (sizes along x, y, z).

    Examples
    --------
    >>> preview_detail((256, 256, 113), (256, 256, 113))
    'full volume, 256\u00d7256\u00d7113 voxels'
    >>> preview_detail((512, 512, 300), (256, 256, 150))[:43]
    'every 2nd voxel, 256\u00d7256\u00d7150 of 512\u00d7512\u00d7300'
    """
    dims = "\u00d7".join(str(int(d)) for d in shape)
    if tuple(shape) == tuple(full_shape):
        return f"full volume, {dims} voxels"
    step = -(-int(full_shape[0]) // max(int(shape[0]), 1))
    nth = {2: "2nd", 3: "3rd"}.get(step, f"{step}th")
    full = "\u00d7".join(str(int(d)) for d in full_shape)
    budget = round(PREVIEW_VOXELS ** (1 / 3))
    return f"every {nth} voxel, {dims} of {full}: above the {budget}\u00b3-voxel budget"


class Preview:
    """Render window (never rendered on the server) holding the preview volume.

    Parameters
    ----------
    volume : Volume
        The full volume (reduced above :data:`PREVIEW_VOXELS`).
    spec : StructureSpec
        Its transfer function.
    """

    def __init__(self, volume, spec) -> None:
        from vtkmodules.vtkRenderingCore import (
            vtkRenderer,
            vtkRenderWindow,
            vtkVolume,
            vtkVolumeProperty,
        )
        from vtkmodules.vtkRenderingVolumeOpenGL2 import vtkOpenGLGPUVolumeRayCastMapper

        self.renderer = vtkRenderer()
        self.window = vtkRenderWindow()
        self.window.SetOffScreenRendering(1)
        self.window.AddRenderer(self.renderer)
        self.mapper = vtkOpenGLGPUVolumeRayCastMapper()
        # vtk.js lowers the image resolution while the camera moves, to keep the rate
        self.mapper.SetAutoAdjustSampleDistances(1)
        self.property = vtkVolumeProperty()
        self.property.SetInterpolationTypeToLinear()
        self.actor = vtkVolume()
        self.actor.SetMapper(self.mapper)
        self.actor.SetProperty(self.property)
        self.renderer.AddVolume(self.actor)
        self.set_volume(volume, spec)

    def set_volume(self, volume, spec) -> None:
        """Show ``volume`` (reduced above :data:`PREVIEW_VOXELS`) with ``spec``."""
        from dvr_perception.volume.convert import to_vtk_image

        self.unit = min(float(s) for s in volume.spacing)
        self.volume = preview_volume(volume)
        self.detail = preview_detail(volume.dims, self.volume.dims)  # x, y, z
        self.image = to_vtk_image(self.volume)
        self.mapper.SetInputData(self.image)
        # a sample every RAY_STEP_VOXELS voxels of the copy along the ray
        self.mapper.SetSampleDistance(RAY_STEP_VOXELS * min(float(s) for s in self.volume.spacing))
        self.set_spec(spec)

    def set_spec(self, spec) -> None:
        """Show ``spec``'s range structures (label structures are left out of the preview)."""
        from dvr_perception.export.vtk import to_vtk_transfer_functions

        ranged = tuple(s for s in spec.structures if s.range is not None)
        self.actor.SetVisibility(bool(ranged))
        if not ranged:
            return
        ctf, otf = to_vtk_transfer_functions(replace(spec, structures=ranged))
        self.property.SetColor(ctf)
        self.property.SetScalarOpacity(otf)
        # opacity per unit of ray length as in the server's rendering (also for a reduced copy)
        unit = spec.rendering.opacity_unit_distance or self.unit
        self.property.SetScalarOpacityUnitDistance(float(unit))
        self.property.SetShade(int(bool(spec.rendering.shade)))
        self.renderer.SetBackground(*(float(c) for c in spec.background))

    def set_camera(self, vtk_camera, size) -> None:
        """Copy the server's camera (and window size) into the preview."""
        cam = self.renderer.GetActiveCamera()
        cam.SetPosition(vtk_camera.GetPosition())
        cam.SetFocalPoint(vtk_camera.GetFocalPoint())
        cam.SetViewUp(vtk_camera.GetViewUp())
        cam.SetViewAngle(vtk_camera.GetViewAngle())
        cam.SetClippingRange(vtk_camera.GetClippingRange())
        self.window.SetSize(int(size[0]), int(size[1]))
