"""The filters measure what the render view shows: ``plugin/view_camera.py`` and its macro.

In pvpython a render view gets a non-default camera (azimuth, elevation, roll, a 24 degree
view angle and a 3:2 view); ``use_active_view_camera`` copies it into *Perception Measures*,
whose E values and image must then equal the library's for that very camera -- and differ from
the filter's default (the spec's view).  The macro file is run as ParaView runs macros (after
the plugin is loaded) on *Optimize Transfer Function*; a parallel projection and a source
without ``CameraJSON`` are checked too.  A plain filter (``FollowView`` on, the default) takes
the camera of the render view showing its input by itself; with ``FollowView=0`` the spec's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dvr_perception.cli.pvbatch import virtual_display
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import load_spec
from dvr_perception.volume import load_volume
from tests.plugin.conftest import CROSS_ENV_ABS

REPO = Path(__file__).resolve().parents[2]
PLUGIN_DIR = REPO / "dvr_perception" / "paraview"
MACRO = PLUGIN_DIR / "macros" / "DVR_Use_View_Camera.py"
SPEC = REPO / "state_files" / "neghip.json"
MARK = "@@RESULT@@ "  # must match conftest.MARK
HEIGHT = 32
VIEW_SIZE = (450, 300)  # 3:2 -> the filter's Width becomes 48

CODE = f"""
import json, runpy, sys
VOLUME = @VOLUME@
sys.path.insert(0, {str(PLUGIN_DIR)!r})
from paraview.simple import *
LoadPlugin({str(PLUGIN_DIR / "dvr_perception_plugin.py")!r}, ns=globals())
from vtkmodules.util.numpy_support import vtk_to_numpy
from view_camera import use_active_view_camera

def run(f):
    f.UpdatePipeline()
    img = servermanager.Fetch(f)
    fd = img.GetFieldData()
    return {{"E": {{k: fd.GetArray(k).GetValue(0) for k in ("E_v", "E_s", "E_t")}},
             "dims": list(img.GetDimensions()),
             "alpha": vtk_to_numpy(img.GetPointData().GetArray("rgba"))[:, 3].tolist()}}

out = {{}}
reader = OpenDataFile(VOLUME)
view = CreateView("RenderView")
view.ViewSize = {list(VIEW_SIZE)}
Show(reader, view)
SetActiveView(view)
ResetCamera(view)
cam = view.GetActiveCamera()
cam.Azimuth(40.0)
cam.Elevation(-25.0)
cam.Roll(15.0)
cam.SetViewAngle(24.0)
cam.Dolly(1.3)
cam.OrthogonalizeViewUp()
# a plain Apply: the filter follows the camera of the render view that shows its input, even
# with another view active (Apply makes the output's spreadsheet view active first)
sheet = CreateView("SpreadSheetView")
SetActiveView(sheet)
plain = PerceptionMeasures(Input=reader, SpecFile={str(SPEC)!r}, Width={HEIGHT}, Height={HEIGHT})
Show(plain, sheet)
out["follow"] = run(plain)
SetActiveView(view)
pm = PerceptionMeasures(Input=reader, SpecFile={str(SPEC)!r}, Width={HEIGHT}, Height={HEIGHT},
                        FollowView=0)
out["default"] = run(pm)
SetActiveSource(pm)
out["camera"] = use_active_view_camera()
m = cam.GetViewTransformMatrix()
out["view_matrix"] = [[m.GetElement(i, j) for j in range(4)] for i in range(3)]
out["width"] = int(pm.GetPropertyValue("Width"))
out["view_camera"] = run(pm)

# the macro, as ParaView runs it: a script in the GUI's interpreter, after LoadPlugin
opt = OptimizeTransferFunction(Input=reader, SpecFile={str(SPEC)!r}, Height=20)
SetActiveSource(opt)
cam.SetParallelProjection(True)
cam.SetParallelScale(37.5)
runpy.run_path({str(MACRO)!r}, run_name="__main__")
out["macro"] = json.loads(opt.CameraJSON)
out["macro_width"] = int(opt.GetPropertyValue("Width"))

# a source without CameraJSON: a clear error, nothing changed
SetActiveSource(reader)
try:
    use_active_view_camera()
    out["error"] = None
except ValueError as exc:
    out["error"] = str(exc)
print({MARK!r} + json.dumps(out), flush=True)
"""


def _library(volume, camera):
    vol, spec = load_volume(volume), load_spec(SPEC)
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    result = analyze(vol, spec, camera, curvature=curv, build_cache=True)
    return {
        "E_v": visibility(result, spec).E_v,
        "E_s": shape(result, spec).E_s,
        "E_t": transparency(result, spec).E_t,
        "alpha": np.asarray(result.accumulated)[::-1].reshape(-1),  # VTK rows start at the bottom
    }


def test_filter_uses_the_active_view_camera(paraview, tmp_path, shared_data):
    volume = shared_data / "neghip.nhdr"
    with virtual_display() as display:
        env = dict(paraview.env, DISPLAY=display)
        proc = paraview.run(CODE.replace("@VOLUME@", repr(str(volume))), tmp_path, env=env)
    got = paraview.result(proc)

    cam = got["camera"]
    assert set(cam) == {
        "position",
        "focal_point",
        "view_up",
        "view_angle",
        "parallel_projection",
        "parallel_scale",
    }
    assert cam["view_angle"] == pytest.approx(24.0)
    assert cam["parallel_projection"] is False
    # the view's 3:2 aspect ratio at the filter's height
    width = round(HEIGHT * VIEW_SIZE[0] / VIEW_SIZE[1])
    assert got["width"] == width
    assert got["view_camera"]["dims"] == [width, HEIGHT, 1]

    # the filter's numbers are the library's for exactly that camera ...
    camera = Camera.from_dict({**cam, "width": width, "height": HEIGHT})
    fwd = np.subtract(camera.focal_point, camera.position)
    assert abs(np.dot(fwd, [0, 0, 1])) / np.linalg.norm(fwd) < 0.9  # really not the default
    # VTK's view matrix has the rows right, up, -forward: the library's basis of that camera
    f, r, u = camera.basis()
    rows = np.asarray(got["view_matrix"])[:, :3]
    np.testing.assert_allclose(rows, [r, u, -f], atol=1e-9)
    expected = _library(volume, camera)
    for k in ("E_v", "E_s", "E_t"):
        assert got["view_camera"]["E"][k] == pytest.approx(expected[k], abs=CROSS_ENV_ABS), k
    np.testing.assert_allclose(got["view_camera"]["alpha"], expected["alpha"], atol=1e-6)
    # a plain Apply (FollowView, the default) measured that camera at the filter's own size
    square = _library(volume, camera.with_size(HEIGHT, HEIGHT))
    for k in ("E_v", "E_s", "E_t"):
        assert got["follow"]["E"][k] == pytest.approx(square[k], abs=CROSS_ENV_ABS), k
    assert got["follow"]["dims"] == [HEIGHT, HEIGHT, 1]
    # ... and with FollowView off, not the view's but the spec's
    spec_view = load_spec(SPEC).view or (0.0, 0.0, 1.0)
    vol = load_volume(volume)
    az, el, zoom = spec_view
    default = Camera.from_view(
        vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=HEIGHT, height=HEIGHT
    )
    base = _library(volume, default)
    for k in ("E_v", "E_s", "E_t"):
        assert got["default"]["E"][k] == pytest.approx(base[k], abs=CROSS_ENV_ABS), k
    diffs = [abs(got["view_camera"]["E"][k] - got["default"]["E"][k]) for k in base if k != "alpha"]
    assert max(diffs) > 1e-3

    # the macro copied the (now parallel) camera into the optimiser, keeping the aspect ratio
    macro = got["macro"]
    assert macro["parallel_projection"] is True
    assert macro["parallel_scale"] == pytest.approx(37.5)
    assert macro["position"] == pytest.approx(cam["position"])
    assert got["macro_width"] == round(20 * VIEW_SIZE[0] / VIEW_SIZE[1])

    assert "no CameraJSON" in got["error"]
    # the Pipeline Browser's name: OpenDataFile picks the plugin's reader once it is loaded
    assert "'DVRPerceptionvolume1' (DVR Perception volume)" in got["error"]
