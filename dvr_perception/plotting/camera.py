"""Exchange cameras between a PyVista plotter and :class:`~dvr_perception.rays.camera.Camera`.

Both use VTK's conventions (vertical view angle in degrees, parallel scale = half the image
height in world units), so the round trip copies numbers; the image size is the plotter's
window size.
"""

from __future__ import annotations

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera

__all__ = ["camera_from_plotter", "set_plotter_camera"]


def _check_plotter(plotter, what: str = "plotter"):
    import pyvista as pv

    if not isinstance(plotter, pv.Plotter):
        raise DVRInputError(f"{what}: expected a pyvista.Plotter, got {type(plotter).__name__}")


def camera_from_plotter(plotter) -> Camera:
    """Return the active renderer's camera and the window size as a :class:`Camera`.

    Parameters
    ----------
    plotter : pyvista.Plotter

    Returns
    -------
    Camera

    Examples
    --------
    >>> import pyvista as pv
    >>> pl = pv.Plotter(off_screen=True, window_size=(64, 48))
    >>> cam = camera_from_plotter(pl)
    >>> (cam.width, cam.height)
    (64, 48)
    >>> pl.close()
    """
    _check_plotter(plotter)
    cam = plotter.renderer.GetActiveCamera()
    width, height = (int(v) for v in plotter.window_size)
    return Camera(
        position=cam.GetPosition(),
        focal_point=cam.GetFocalPoint(),
        view_up=cam.GetViewUp(),
        view_angle=cam.GetViewAngle(),
        parallel_projection=bool(cam.GetParallelProjection()),
        parallel_scale=cam.GetParallelScale(),
        width=width,
        height=height,
    )


def apply_camera(vtk_camera, camera: Camera) -> None:
    """Copy ``camera``'s view (not its image size) onto a ``vtkCamera``."""
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    vtk_camera.SetPosition(*camera.position)
    vtk_camera.SetFocalPoint(*camera.focal_point)
    vtk_camera.SetViewUp(*camera.view_up)
    vtk_camera.SetViewAngle(camera.view_angle)
    vtk_camera.SetParallelProjection(int(camera.parallel_projection))
    vtk_camera.SetParallelScale(camera.parallel_scale)


def set_plotter_camera(plotter, camera: Camera, *, window_size: bool = True) -> None:
    """Show ``camera``'s view in the active renderer and size the window to it.

    Parameters
    ----------
    plotter : pyvista.Plotter
    camera : Camera
    window_size : bool, default: True
        Also set the window size to ``(camera.width, camera.height)``.

    Examples
    --------
    >>> import pyvista as pv
    >>> pl = pv.Plotter(off_screen=True)
    >>> cam = Camera(position=(0, 0, 5), width=40, height=30)
    >>> set_plotter_camera(pl, cam)
    >>> camera_from_plotter(pl) == cam
    True
    >>> pl.close()
    """
    _check_plotter(plotter)
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    if window_size:
        plotter.window_size = (camera.width, camera.height)
    renderer = plotter.renderer
    apply_camera(renderer.GetActiveCamera(), camera)
    renderer.camera_set = True
    renderer.ResetCameraClippingRange()
