"""``plugin/view_lens.py``: a rubber band's frustum back to the optimiser's lens pixels.

The frustum is built here as ParaView builds it (``vtkSMRenderViewProxy``: each corner of the
display rectangle unprojected at the near and the far plane, in the order (x0, y0), (x0, y1),
(x1, y0), (x1, y1)), from the library camera's own rays, so a known rectangle must come back
as itself -- at the view's size and, scaled, at the filter's smaller image.  ParaView's real
frustum is checked against it in ``test_view_actions.py`` (GUI and pvserver).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from dvr_perception.rays.camera import Camera

PLUGIN = Path(__file__).resolve().parents[2] / "dvr_perception" / "paraview"


def _module():
    spec = importlib.util.spec_from_file_location("view_lens", PLUGIN / "view_lens.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _frustum(camera: Camera, rect, *, near=2.0, far=40.0):
    """ParaView's 8 corners of a display rectangle (pixels, y up from the bottom)."""
    fwd, right, up = camera.basis()
    w, h = camera.width, camera.height
    t = np.tan(np.radians(camera.view_angle) / 2.0)
    pos = np.asarray(camera.position, float)
    x0, y0, x1, y1 = rect
    corners = []
    for x, y in ((x0, y0), (x0, y1), (x1, y0), (x1, y1)):
        sx, sy = 2.0 * x / w - 1.0, 2.0 * y / h - 1.0
        for depth in (near, far):
            if camera.parallel_projection:
                s = camera.parallel_scale
                p = pos + sx * s * w / h * right + sy * s * up + depth * fwd
            else:
                p = pos + depth * (fwd + sx * t * w / h * right + sy * t * up)
            corners.append(tuple(p))
    return corners


CAMERA = Camera(position=(30.0, 20.0, 50.0), focal_point=(1.0, -2.0, 3.0),
                view_up=(0.1, 1.0, 0.0), view_angle=24.0, width=480, height=320)  # fmt: skip


@pytest.mark.parametrize("parallel", [False, True])
def test_a_rectangle_comes_back_as_itself_and_scaled(parallel):
    lens = _module().lens_from_frustum
    cam = Camera.from_dict(dict(CAMERA.to_dict(), parallel_projection=parallel,
                                parallel_scale=7.5))  # fmt: skip
    frustum = _frustum(cam, (120, 50, 300, 200))
    # at the view's size: x as drawn, rows from the top (320 - 200 = 120, 320 - 50 = 270)
    assert lens(frustum, cam) == (120, 120, 300, 270)
    # the filter's 48 x 32 image of the same camera: the rectangle scaled by 1/10
    assert lens(frustum, cam.with_size(48, 32)) == (12, 12, 30, 27)


def test_a_band_over_the_edge_is_clipped_and_one_outside_refused():
    lens = _module().lens_from_frustum
    assert lens(_frustum(CAMERA, (-50, -20, 100, 80)), CAMERA) == (0, 240, 100, 320)
    with pytest.raises(ValueError, match=r"outside the 480 x 320 view"):
        lens(_frustum(CAMERA, (500, 10, 600, 80)), CAMERA)


def test_a_camera_turned_away_is_refused():
    lens = _module().lens_from_frustum
    frustum = _frustum(CAMERA, (120, 50, 300, 200))
    back = Camera.from_dict(dict(CAMERA.to_dict(), focal_point=(59.0, 42.0, 97.0)))
    with pytest.raises(ValueError, match="behind the camera"):
        lens(frustum, back)
