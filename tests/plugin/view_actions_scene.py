"""The scene of ``test_view_actions.py``: run by ``paraview --script`` (GUI) or pvpython.

Environment: ``DVR_REPO`` (the repository), ``DVR_VOLUME``, ``DVR_OUT`` (a folder for the
screenshots and ``result.json``), ``DVR_SPEC`` (a spec file), optional ``DVR_SERVER_PORT``
(connect to a pvserver on 127.0.0.1 first) and ``DVR_DOC_IMAGES`` (also save the layout).
Opens the volume in a 3-D view, sets a camera, runs *Optimise this view*
(``dvr_view.optimise_this_view``), reads back what the view's volume representation carries,
saves both views' screenshots, then *Undo* and reads back again.  Writes ``result.json`` to
``DVR_OUT``; the test compares it with the library.
"""

import json
import os
import sys
import time
from pathlib import Path

from paraview import servermanager
from paraview import simple as pvs

T0 = time.time()

REPO = os.environ["DVR_REPO"]
OUT = os.environ["DVR_OUT"]
PORT = os.environ.get("DVR_SERVER_PORT")
sys.path.insert(0, os.path.join(REPO, "dvr_perception", "paraview"))

if PORT:
    pvs.Connect("127.0.0.1", int(PORT))
pvs.LoadPlugin(
    os.path.join(REPO, "dvr_perception", "paraview", "dvr_perception_plugin.py"), remote=True
)

import dvr_view  # noqa: E402
from view_camera import matched_width  # noqa: E402

dvr_view.SSIM_IMAGE = os.path.join(OUT, "paraview_capture.png")  # for the test's own SSIM

reader = pvs.OpenDataFile(os.environ["DVR_VOLUME"])
view = pvs.GetActiveViewOrCreate("RenderView")
if PORT:
    view.ViewSize = [480, 320]
else:
    pvs.GetLayout(view).PreviewMode = [720, 400]  # the GUI's views at a small, fixed size
display = pvs.Show(reader, view)
display.SetRepresentationType("Volume")
array = display.ColorArrayName[1]
lut, pwf = pvs.GetColorTransferFunction(array), pvs.GetOpacityTransferFunction(array)
before = {"RGBPoints": list(lut.RGBPoints), "Points": list(pwf.Points)}
pvs.ResetCamera(view)
camera = view.GetActiveCamera()
camera.Azimuth(35.0)
camera.Elevation(25.0)
camera.Dolly(1.2)
pvs.Render(view)
view_camera = {
    "position": list(camera.GetPosition()),
    "focal_point": list(camera.GetFocalPoint()),
    "view_up": list(camera.GetViewUp()),
    "view_angle": camera.GetViewAngle(),
}
pvs.SetActiveSource(reader)
pvs.SetActiveView(view)


def terms(proxy):
    """The E terms of a DVR filter's output."""
    fd = servermanager.Fetch(proxy).GetFieldData()
    return [fd.GetArray(k).GetValue(0) for k in ("E_v", "E_s", "E_t")]


# a plain Apply of Perception Measures (FollowView, the default) vs the view's camera given
size = {"Width": 32, "Height": 32}
plain = pvs.PerceptionMeasures(Input=reader, SpecFile=os.environ["DVR_SPEC"], **size)
given = pvs.PerceptionMeasures(Input=reader, SpecFile=os.environ["DVR_SPEC"], UseSpecView=0,
                               CameraJSON=json.dumps(view_camera), **size)  # fmt: skip
plain_terms = {"plain": terms(plain), "given": terms(given)}
for proxy in (plain, given):
    pvs.Delete(proxy)
pvs.SetActiveSource(reader)


def rubber_band(v):
    """A rubber band (display pixels, y up) over the middle of the view: x 30-65 %, y 25-70 %."""
    vw, vh = (int(c) for c in v.ViewSize)
    return [round(0.30 * vw), round(0.25 * vh), round(0.65 * vw), round(0.70 * vh)]


print("@@T setup", time.time() - T0, flush=True)
SETTINGS = {"Stages": "opacity", "MaxIterations": 2, "Resolution": 32, "Height": 32}
if PORT:  # pvpython on a pvserver: the Python API
    report = dvr_view.optimise_this_view(spec_file=os.environ["DVR_SPEC"], **SETTINGS)
else:  # the GUI: the toolbar's macros, installed and run as ParaView runs a macro
    import runpy

    import install_macros

    macros = install_macros.install(os.path.join(OUT, "config", "ParaView", "Macros"))
    MACROS = {os.path.basename(p)[: -len(".py")]: p for p in macros}
    # as in the GUI: Filters > DVR Perception > Optimize Transfer Function (spec, settings)
    # on the selected volume, then the volume selected again and the macro clicked
    pvs.OptimizeTransferFunction(Input=reader, SpecFile=os.environ["DVR_SPEC"], **SETTINGS)
    pvs.SetActiveSource(reader)
    pvs.SetActiveView(view)
    runpy.run_path(MACROS["DVR_Optimise_View"], run_name="__main__")
    report = dvr_view.last_report["optimise"]
opt = report["filter"]
optimise_view_size = [int(v) for v in view.ViewSize]  # (a layout screenshot resizes it)
print("@@T optimised", time.time() - T0, flush=True)
fetched = servermanager.Fetch(opt)


def plain(value):
    """A property value as JSON: text, a number or a list of numbers."""
    if isinstance(value, (int, float)):
        return value
    try:
        return [float(c) for c in value]
    except (TypeError, ValueError):  # text, or an enumeration's value
        return str(value).strip("'")


def lights(v):
    """The view's light set-up: the light kit's switch and the extra lights."""
    keys = ("Name", "Enable", "Coords", "Position", "FocalPoint", "Intensity")
    extra = [{k: plain(light.GetPropertyValue(k)) for k in keys} for light in v.AdditionalLights]
    return {"use_light": int(v.UseLight), "extra": extra}


applied_lights = lights(view)
ssim_field = fetched.GetFieldData().GetArray("paraview_ssim")
presets = servermanager.vtkSMTransferFunctionPresets.GetInstance()
CONTROLLER = servermanager.vtkSMParaViewPipelineControllerWithRendering()
quality = {}
for _, title in dvr_view.QUALITY_MAPS:
    qview = pvs.FindView(dvr_view.QUALITY_PREFIX + title)
    rep = pvs.GetDisplayProperties(opt, qview)
    bar = pvs.GetScalarBar(pvs.GetColorTransferFunction(rep.ColorArrayName[1]), qview)
    quality[title] = {
        "in_layout": qview in pvs.GetViewsInLayout(pvs.GetLayout(view)),
        "visible": bool(rep.Visibility),
        "array": rep.ColorArrayName[1],
        "bar": bool(bar.Visibility),
        "bar_title": bar.Title,
        "2d": qview.InteractionMode == "2D",
    }
    if title.startswith("Visibility"):
        pvs.SaveScreenshot(
            os.path.join(OUT, "quality_map.png"),
            qview,
            ImageResolution=[480, 320],
            FontScaling="Do not scale fonts",
        )
table = pvs.FindView(dvr_view.TABLE_VIEW)
pvs.SaveScreenshot(os.path.join(OUT, "view_3d.png"), view, ImageResolution=[480, 320])
if os.environ.get("DVR_DOC_IMAGES"):
    pvs.SaveScreenshot(
        os.path.join(OUT, "layout.png"), pvs.GetLayout(view), ImageResolution=[1200, 640]
    )
print("@@T screenshots", time.time() - T0, flush=True)
result = {
    "remote": bool(servermanager.ActiveConnection.IsRemote()),
    "volume": os.environ["DVR_VOLUME"],
    "view_camera": view_camera,
    "filter_camera": json.loads(opt.CameraJSON),
    "filter_size": [int(opt.Width), int(opt.Height)],
    "optimise_view_size": optimise_view_size,
    "use_spec_view": int(opt.UseSpecView),
    "spec": report["spec"],
    "E": report["E"],
    "initial_E": report["initial_E"],
    "ssim": report["ssim"],
    "light": report["light"],
    "ssim_by_light": report["ssim_by_light"],
    "lights": applied_lights,
    "ssim_field": ssim_field.GetValue(0) if ssim_field is not None else None,
    "preset": report["preset"],
    "preset_file": report["preset_file"],
    "preset_saved": json.loads(Path(report["preset_file"]).read_text(encoding="utf-8")),
    "preset_known": bool(presets.HasPreset(report["preset"])),
    "array": array,
    "data_range": list(reader.PointData[array].GetRange()),
    "lut_range_mode": str(lut.AutomaticRescaleRangeMode).strip("'"),
    "RGBPoints": list(lut.RGBPoints),
    "Points": list(pwf.Points),
    "material": [display.Ambient, display.Diffuse, display.Specular, display.SpecularPower],
    "shade": int(display.Shade),
    "unit_distance": display.ScalarOpacityUnitDistance,
    "background": list(view.Background),
    "preferred_view": CONTROLLER.GetPreferredViewType(opt.SMProxy, 0),
    "output_in_3d_view": bool(getattr(servermanager.GetRepresentation(opt, view), "Visibility", 0)),
    "quality": quality,
    "table": {
        "in_layout": table in pvs.GetViewsInLayout(pvs.GetLayout(view)),
        "field_data": table.FieldAssociation == "Field Data",
        "visible": bool(pvs.GetDisplayProperties(opt, table).Visibility),
    },
    "why": [
        fetched.GetFieldData().GetAbstractArray("why").GetValue(i)
        for i in range(fetched.GetFieldData().GetAbstractArray("why").GetNumberOfValues())
    ],
    "before": before,
    "plain_apply": plain_terms,
}
if PORT:
    # Measure this view, then Refine region on a selection of the quality map's pixels
    dvr_view.SSIM_IMAGE = None  # keep the capture of the first optimisation for the test
    measured = dvr_view.measure_this_view()
    result["measured"] = {k: measured[k] for k in ("E_v", "E_s", "E_t")}
    result["measure_camera"] = json.loads(measured["filter"].CameraJSON)
    width = int(opt.Width)
    ids = [y * width + x for y in range(10, 20) for x in range(12, 30)]  # VTK rows go up
    pvs.SelectIDs(IDs=[i for p in ids for i in (0, p)], FieldType="POINT", Source=opt)
    print("@@T measured", time.time() - T0, flush=True)
    refined = dvr_view.refine_region(opt, view)
    print("@@T refined", time.time() - T0, flush=True)
    result["region"] = list(refined["region"])
    result["region_from"] = refined["region_from"]
    result["region_property"] = opt.Region
    result["refined_E"] = refined["E"]
    result["refined_lens"] = refined["lens_region"]
    result["undone"] = dvr_view.undo() and dvr_view.undo()
    # a rubber band in the 3-D view, read back through the server: the lens without optimising
    pvs.ClearSelection(opt)
    result["rubber_band"] = rubber_band(view)
    pvs.SelectCellsThrough(Rectangle=result["rubber_band"], View=view)
    result["band_lens"] = list(dvr_view.rubber_band_region(reader, opt, view))
    result["band_size"] = [matched_width(opt, view), int(opt.Height)]
    # nothing selected: one clear error, nothing optimised
    pvs.ClearSelection(reader)
    try:
        dvr_view.refine_region(opt, view)
        result["no_selection_error"] = None
    except ValueError as exc:
        result["no_selection_error"] = str(exc)
else:
    result["macros"] = sorted(MACROS)
    # Refine region from a rubber band drawn over the volume in the 3-D view (the macro)
    dvr_view.SSIM_IMAGE = None  # keep the capture of the first optimisation for the test
    result["rubber_band"] = rubber_band(view)
    pvs.SetActiveSource(reader)
    pvs.SelectCellsThrough(Rectangle=result["rubber_band"], View=view)
    pvs.SetActiveView(view)
    runpy.run_path(MACROS["DVR_Refine_Region"], run_name="__main__")
    print("@@T refined", time.time() - T0, flush=True)
    refined = dvr_view.last_report["refine"]
    result["band_lens"] = list(refined["region"])
    result["band_size"] = [int(opt.Width), int(opt.Height)]
    result["region_from"] = refined["region_from"]
    result["region_property"] = opt.Region
    result["refined_E"] = refined["E"]
    result["refined_initial_E"] = refined["initial_E"]
    result["refined_lens"] = refined["lens_region"]
    result["lens_E"] = refined["lens_E"]
    result["lens_initial_E"] = refined["lens_initial_E"]
    runpy.run_path(MACROS["DVR_Undo"], run_name="__main__")
    runpy.run_path(MACROS["DVR_Undo"], run_name="__main__")
    result["undone"] = True
result["view_size"] = [int(v) for v in view.ViewSize]
result["after_undo"] = {"RGBPoints": list(lut.RGBPoints), "Points": list(pwf.Points)}
result["lights_after_undo"] = lights(view)
result["undo_again"] = dvr_view.undo()
print("@@T done", time.time() - T0, flush=True)
with open(os.path.join(OUT, "result.json"), "w", encoding="utf-8") as f:
    json.dump(result, f)
print("@@DONE@@", flush=True)
if PORT:
    pvs.Disconnect()
