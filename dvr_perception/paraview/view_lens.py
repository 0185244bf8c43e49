"""The lens of *Refine region* from a rubber band drawn in the 3-D view.

*Select Cells Through* (or *Select Points Through*; pvpython ``SelectCellsThrough(Rectangle=
[x0, y0, x1, y1], View=view)``) works on any representation, a volume too, and keeps the
rubber band as a frustum: the selection source ``FrustumSelectionSource`` holds its eight
world-space corners in ``Frustum`` (x, y, z, w each; ParaView's order: for the rectangle's
corners (x0, y0), (x0, y1), (x1, y0), (x1, y1) the near-plane point, then the far-plane one).
:func:`view_frustum` reads them from the volume's selection; :func:`lens_from_frustum`
projects the near-plane corners through the filter's camera (the view's, at the filter's
``Width`` x ``Height``) back to image pixels: the lens in the optimiser's output pixels
(x right, y down), whatever the view's size in pixels.
"""

import math

__all__ = ["lens_from_frustum", "view_frustum"]

_NEAR = (0, 2, 4, 6)  # the near-plane corners among the frustum's eight


def _inputs(proxy):
    prop = proxy.GetProperty("Input")
    if prop is None:
        return []
    return [prop.GetProxy(i) for i in range(prop.GetNumberOfProxies())]


def view_frustum(source, port=0):
    """The frustums selected on ``source`` (a proxy): a list of 8-corner lists, or ``[]``.

    The selection is ParaView's ``AppendSelections`` proxy (what both the GUI and
    ``paraview.simple`` set, possibly nested by the Add/Subtract modifiers) over selection
    sources; each ``FrustumSelectionSource`` among them gives one frustum, its corners as
    ``(x, y, z)`` world points.
    """
    selection = source.SMProxy.GetSelectionInput(port)
    found, todo, seen = [], [selection] if selection is not None else [], set()
    while todo:
        proxy = todo.pop()
        if id(proxy) in seen:
            continue
        seen.add(id(proxy))
        if proxy.GetXMLName() == "FrustumSelectionSource":
            prop = proxy.GetProperty("Frustum")
            values = [prop.GetElement(i) for i in range(prop.GetNumberOfElements())]
            if len(values) == 32:
                found.append([_point(values[4 * i : 4 * i + 4]) for i in range(8)])
        todo.extend(_inputs(proxy))
    return found


def _point(xyzw):
    x, y, z, w = (float(v) for v in xyzw)
    return (x, y, z) if w in (0.0, 1.0) else (x / w, y / w, z / w)


def lens_from_frustum(frustum, camera):
    """The lens ``(x0, y0, x1, y1)`` (integer pixels, y down) of a rubber-band frustum.

    Parameters
    ----------
    frustum : sequence of 8 (x, y, z)
        The corners (:func:`view_frustum`; several frustums: pass each and take the union).
    camera : dvr_perception.rays.camera.Camera
        The filter's camera and image size.

    Returns
    -------
    tuple of int
        The bounding box of the projected near-plane corners, rounded to the nearest pixel
        edge and clipped to the image.

    Raises
    ------
    ValueError
        If a corner lies behind the camera (the camera turned away since the selection) or
        the box covers no pixel of the image.
    """
    import numpy as np

    fwd, right, up = camera.basis()
    w, h = camera.width, camera.height
    pos = np.asarray(camera.position, float)
    xs, ys = [], []
    for index in _NEAR:
        d = np.asarray(frustum[index], float) - pos
        if camera.parallel_projection:
            half_h = camera.parallel_scale
            sx, sy = float(d @ right) / (half_h * w / h), float(d @ up) / half_h
        else:
            depth = float(d @ fwd)
            if not depth > 0:
                raise ValueError(
                    "DVR Perception: the selected region is behind the camera (the view turned "
                    "since the rubber band was drawn); select the region again"
                )
            t = math.tan(math.radians(camera.view_angle) / 2.0)
            sx, sy = float(d @ right) / (depth * t * w / h), float(d @ up) / (depth * t)
        xs.append((sx + 1.0) / 2.0 * w)  # normalised device x -> pixel edges, left to right
        ys.append((1.0 - sy) / 2.0 * h)  # ... y up -> rows from the top
    x0, x1 = max(0, round(min(xs))), min(w, round(max(xs)))
    y0, y1 = max(0, round(min(ys))), min(h, round(max(ys)))
    if x1 <= x0 or y1 <= y0:
        raise ValueError(
            f"DVR Perception: the selected region lies outside the {w} x {h} view of the "
            "filter; drag the rubber band over the volume"
        )
    return int(x0), int(y0), int(x1), int(y1)
