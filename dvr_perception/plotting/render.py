"""Off-screen screenshots through a PyVista plotter: one view, or before/after side by side.

Both functions create their own off-screen :class:`pyvista.Plotter` (EGL when there is no
``DISPLAY``), show the volume with :func:`~dvr_perception.plotting.add_structures` and return
float images with row 0 at the top, like our engine's ``RayAnalysis.image``.
"""

from __future__ import annotations

import functools

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.plotting._structure_volume import add_structures
from dvr_perception.plotting.camera import apply_camera, set_plotter_camera
from dvr_perception.rays.camera import Camera

__all__ = ["before_after", "render_plotter"]


@functools.cache
def _can_render() -> tuple[bool, str]:
    from dvr_perception import _vtk

    return _vtk.can_render()


def _new_plotter(*, off_screen: bool, window_size, shape=(1, 1)):
    """Create a plotter whose render window works here (EGL without a display)."""
    from dvr_perception import _vtk

    ok, why = _can_render()
    if not ok:
        raise DVRInputError(f"VTK cannot render here: {why}")
    _vtk.rendering()  # selects the EGL window class when there is no DISPLAY
    import pyvista as pv

    return pv.Plotter(
        off_screen=off_screen, window_size=list(window_size), shape=shape, border=False
    )


def _grab(plotter) -> np.ndarray:
    plotter.render()
    img = plotter.screenshot(return_img=True)
    return np.asarray(img[..., :3], dtype=np.float32) / 255.0


def render_plotter(volume, spec, camera: Camera, *, opacities=None) -> np.ndarray:
    """Render through an off-screen PyVista plotter and return the screenshot.

    Parameters
    ----------
    volume : Volume
        The scalar volume.
    spec : StructureSpec
        Range structures, background and render settings.
    camera : Camera
        View and image size.
    opacities : sequence of float, optional
        Rendering opacity per structure (default: each structure's ``render_opacity``).

    Returns
    -------
    numpy.ndarray
        ``(camera.height, camera.width, 3)`` float32 in [0, 1], row 0 at the top.

    Examples
    --------
    >>> from dvr_perception.structures import make_phantom
    >>> vol, spec = make_phantom(size=32)
    >>> cam = Camera.from_view(vol.bounds, width=64, height=48)
    >>> render_plotter(vol, spec, cam).shape  # doctest: +SKIP
    (48, 64, 3)
    """
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    pl = _new_plotter(off_screen=True, window_size=(camera.width, camera.height))
    try:
        add_structures(pl, volume, spec, opacities=opacities)
        set_plotter_camera(pl, camera)
        return _grab(pl)
    finally:
        pl.close()


def before_after(volume, spec_before, spec_after, camera: Camera, *, off_screen=True):
    """Show two specs side by side with linked views (e.g. before and after optimising).

    Parameters
    ----------
    volume : Volume
        The scalar volume.
    spec_before, spec_after : StructureSpec
        Left and right view (each with its own background and light).
    camera : Camera
        View; each half is ``camera.width x camera.height``.
    off_screen : bool, default: True
        ``False`` opens an interactive window (blocks until it is closed).

    Returns
    -------
    numpy.ndarray
        ``(camera.height, 2 * camera.width, 3)`` float32 screenshot, row 0 at the top.

    Examples
    --------
    >>> from dvr_perception.structures import make_phantom
    >>> vol, spec = make_phantom(size=32)
    >>> cam = Camera.from_view(vol.bounds, width=48, height=48)
    >>> before_after(vol, spec, spec, cam).shape  # doctest: +SKIP
    (48, 96, 3)
    """
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    pl = _new_plotter(
        off_screen=bool(off_screen), window_size=(2 * camera.width, camera.height), shape=(1, 2)
    )
    try:
        for col, (what, spec) in enumerate((("before", spec_before), ("after", spec_after))):
            pl.subplot(0, col)
            add_structures(pl, volume, spec, name=f"dvr_{what}")
        pl.link_views()
        for renderer in pl.renderers:
            apply_camera(renderer.GetActiveCamera(), camera)
            renderer.camera_set = True
            renderer.ResetCameraClippingRange()
        if not off_screen:
            pl.show(auto_close=False)
        return _grab(pl)
    finally:
        pl.close()
