"""Give a DVR Perception filter the camera of a ParaView render view ("optimise what you see").

*Perception Measures* and *Optimize Transfer Function* take their camera from the property
``CameraJSON`` (``Camera.to_dict`` JSON: position, focal point, view-up, view angle, parallel
projection and scale).  :func:`use_active_view_camera` fills it from the active render view's
camera, so the filter measures or optimises exactly the view on the screen::

    import sys; sys.path.insert(0, "/path/to/dvr_perception/paraview")
    from view_camera import use_active_view_camera
    pm = PerceptionMeasures(Input=reader, SpecFile="state_files/neghip.json")
    SetActiveSource(pm)            # the GUI: select the filter in the Pipeline Browser
    use_active_view_camera()       # copies GetActiveView().GetActiveCamera() into pm

The copy is a snapshot: move the camera again and call it again (the filter re-executes only
when the camera changed).  The view's aspect ratio is kept by default: ``Height`` stays and
``Width`` becomes ``Height`` x view width / view height (clamped to 16-4096), so the filter
sees the same field of view as the screen.  ``paraview/macros/DVR_Use_View_Camera.py`` runs it
as a ParaView macro (*Macros > Import new macro...*; then select the filter and click it).
"""

import json

__all__ = ["camera_from_view", "matched_width", "use_active_view_camera"]

_MIN_SIZE, _MAX_SIZE = 16, 4096  # the Width/Height domain of the filters


def camera_from_view(view=None):
    """The camera of a render view (default: the active view) as a ``Camera.to_dict`` dict.

    ``width``/``height`` are left out, so the filter's ``Width``/``Height`` properties apply.
    """
    from paraview import simple

    view = view or simple.GetActiveView()
    if view is None or not hasattr(view, "GetActiveCamera"):
        raise ValueError("use_active_view_camera: no active render view (click a 3D view first)")
    cam = view.GetActiveCamera()
    return {
        "position": [float(c) for c in cam.GetPosition()],
        "focal_point": [float(c) for c in cam.GetFocalPoint()],
        "view_up": [float(c) for c in cam.GetViewUp()],
        "view_angle": float(cam.GetViewAngle()),
        "parallel_projection": bool(cam.GetParallelProjection()),
        "parallel_scale": float(cam.GetParallelScale()),
    }


def use_active_view_camera(proxy=None, view=None, *, match_aspect=True):
    """Copy the camera of ``view`` (default: active view) into ``proxy``'s ``CameraJSON``.

    ``proxy`` defaults to the active source and must be a *Perception Measures* or *Optimize
    Transfer Function* filter.  With ``match_aspect`` (default) its ``Width`` is set to keep
    the view's aspect ratio at the current ``Height``.  Returns the camera dict that was set.
    """
    from paraview import simple

    proxy = proxy or simple.GetActiveSource()
    if proxy is None or proxy.GetProperty("CameraJSON") is None:
        name = "nothing"
        if proxy is not None:
            names = [key[0] for key, value in simple.GetSources().items() if value == proxy]
            name = f"{names[0] if names else '?'!r} ({proxy.SMProxy.GetXMLLabel()})"
        raise ValueError(
            "use_active_view_camera: select a Perception Measures or Optimize Transfer "
            f"Function filter (the active source is {name}, which has no CameraJSON)"
        )
    view = view or simple.GetActiveView()
    camera = camera_from_view(view)
    if match_aspect:
        proxy.SetPropertyWithName("Width", matched_width(proxy, view))
    proxy.SetPropertyWithName("CameraJSON", json.dumps(camera))
    return camera


def matched_width(proxy, view, *, height=None):
    """The ``Width`` that gives ``proxy`` the aspect ratio of ``view`` at ``height``.

    ``height`` defaults to the filter's ``Height``; the result is clamped to 16-4096 (the
    filter's current ``Width`` when the view has no size yet).
    """
    height = int(proxy.GetPropertyValue("Height")) if height is None else int(height)
    vw, vh = (int(v) for v in view.ViewSize)
    if vw <= 0 or vh <= 0:
        return int(proxy.GetPropertyValue("Width"))
    return min(_MAX_SIZE, max(_MIN_SIZE, round(height * vw / vh)))
