"""The app's 3D view: an off-screen PyVista plotter the browser can rotate, and spec updates."""

from __future__ import annotations

from dvr_perception.errors import DVRInputError

__all__ = ["new_plotter", "show_spec"]


def new_plotter(size=(800, 600)):
    """Create an off-screen plotter with an interactor, so the browser can rotate the view."""
    from dvr_perception import _vtk

    ok, why = _vtk.can_render()
    if not ok:
        raise DVRInputError(f"VTK cannot render here: {why}")
    _vtk.rendering()  # selects EGL when there is no display
    import pyvista as pv
    from vtkmodules.vtkInteractionStyle import vtkInteractorStyleTrackballCamera
    from vtkmodules.vtkRenderingCore import vtkRenderWindowInteractor

    plotter = pv.Plotter(off_screen=True, window_size=list(size), border=False)
    iren = vtkRenderWindowInteractor()
    iren.SetRenderWindow(plotter.ren_win)
    iren.SetInteractorStyle(vtkInteractorStyleTrackballCamera())
    plotter._dvr_interactor = iren  # keep it alive with the plotter
    return plotter


def show_spec(plotter, handle, volume, spec):
    """Show ``spec`` in ``plotter`` without rendering; return the (possibly new) handle.

    :func:`~dvr_perception.plotting.apply` updates ``handle`` in place (also when the number of
    material groups changes); without a handle the volume is added.
    """
    from dvr_perception.plotting import add_structures, apply

    if handle is not None:
        return apply(handle, spec, render=False)
    return add_structures(plotter, volume, spec)
