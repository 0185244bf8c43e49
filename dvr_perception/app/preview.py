"""The quick preview the browser renders itself (vtk.js) while the camera moves.

A small copy of the volume (at most :data:`PREVIEW_DIM` voxels along each axis, every n-th
voxel) with the current transfer function (range structures, one colour and opacity function
as :func:`~dvr_perception.structures.transfer.to_vtk_transfer_functions` builds them) sits in
a render window of its own that the server never renders: trame-vtk sends its scene to the
page, where vtk.js draws it at interactive rate.  When the camera rests, the engine's exact
image is shown again.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["PREVIEW_DIM", "Preview", "preview_volume"]

#: Most voxels along an axis of the preview copy.
PREVIEW_DIM = 64


def preview_volume(volume, *, max_dim: int = PREVIEW_DIM):
    """Return every n-th voxel of ``volume`` (n the smallest with at most ``max_dim`` a side).

    The copy keeps the volume's origin (its first voxel), direction and ``oriented`` flag;
    labels are left out (the preview shows range structures only).

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> small = preview_volume(Volume(np.zeros((130, 20, 64), np.uint8)), max_dim=64)
    >>> small.data.shape, small.spacing
    ((44, 7, 22), (3.0, 3.0, 3.0))
    """
    step = max(1, -(-max(volume.data.shape) // int(max_dim)))
    if step == 1:
        return volume
    data = np.ascontiguousarray(volume.data[::step, ::step, ::step])
    spacing = tuple(float(s) * step for s in volume.spacing)
    # the same grid, strided: every other field (origin, axes, orientation) stays
    return replace(volume, data=data, spacing=spacing, labels=None)


class Preview:
    """Render window (never rendered on the server) holding the preview volume.

    Parameters
    ----------
    volume : Volume
        The full volume (a small copy is kept).
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
        # vtk.js lengthens the step along the rays while the camera moves, to keep the rate
        self.mapper.SetAutoAdjustSampleDistances(1)
        self.property = vtkVolumeProperty()
        self.property.SetInterpolationTypeToLinear()
        self.actor = vtkVolume()
        self.actor.SetMapper(self.mapper)
        self.actor.SetProperty(self.property)
        self.renderer.AddVolume(self.actor)
        self.set_volume(volume, spec)

    def set_volume(self, volume, spec) -> None:
        """Show a small copy of ``volume`` with ``spec``."""
        from dvr_perception.volume.convert import to_vtk_image

        self.unit = min(float(s) for s in volume.spacing)
        self.volume = preview_volume(volume)
        self.image = to_vtk_image(self.volume)
        self.mapper.SetInputData(self.image)
        # one sample a voxel of the copy along the ray
        self.mapper.SetSampleDistance(min(float(s) for s in self.volume.spacing))
        self.set_spec(spec)

    def set_spec(self, spec) -> None:
        """Show ``spec``'s range structures (label structures are left out of the preview)."""
        from dvr_perception.structures.transfer import to_vtk_transfer_functions

        ranged = tuple(s for s in spec.structures if s.range is not None)
        self.actor.SetVisibility(bool(ranged))
        if not ranged:
            return
        ctf, otf = to_vtk_transfer_functions(replace(spec, structures=ranged))
        self.property.SetColor(ctf)
        self.property.SetScalarOpacity(otf)
        # opacity per unit of ray length as in the full rendering (the copy's voxels are larger)
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
