"""One-step DVR Perception actions on the active source and view (the toolbar's macros).

Client-side ``paraview.simple`` code: the filters run wherever the pipeline lives (the GUI's
built-in server or a ``pvserver``); this module reads the client's render view, pushes its
camera into the filter, updates it, fetches the small 2-D output and changes the client's
representations.  So it works the same in the GUI, in pvpython and connected to a pvserver::

    import sys; sys.path.insert(0, "/path/to/dvr_perception/paraview")
    import dvr_view
    # the volume selected in the Pipeline Browser, shown as a volume in the active 3D view
    report = dvr_view.optimise_this_view(spec_file="state_files/neghip.json")
    dvr_view.undo()                      # back to the transfer functions before

The actions (each also a macro in ``paraview/macros``, see :func:`install_macros`):

:func:`measure_this_view`
    *Perception Measures* from the active view's camera; the quality maps beside the view.
:func:`optimise_this_view`
    *Optimize Transfer Function* from the active view's camera; on completion the input's
    volume representation in that view gets the optimised colour and opacity transfer
    functions, scalar opacity unit distance, shading and material, the view the spec's
    background; the result is saved and imported as a ParaView preset (*Choose Preset*);
    ParaView's rendering is compared with the engine's (SSIM, the output's field array
    ``paraview_ssim``); the quality maps and the per-structure table open beside the view.
:func:`refine_region`
    The same, with the lens (``Region``) set to the rubber band drawn over the volume in the
    3-D view (*Select Cells Through*), or to the bounding box of the points selected (*Select
    Points On*) in a quality-map view.
:func:`undo`
    Restores the representation, view and filter as they were before the last action.

**One material per representation.**  ParaView's volume representation has one material
(``Ambient``, ``Diffuse``, ``Specular``, ``SpecularPower``); the most important structure's is
used (:func:`apply_result.lighting_structure`).

**The light.**  For a shaded spec the view's light kit is switched off and the view gets one
light of its own (:mod:`view_light`): the headlight or a camera light at the optimised
direction, whichever renders closer to the engine (ParaView's GPU volume mapper drops the
ambient term with any light but a single headlight); the report's ``ssim_by_light`` has the
SSIM of the view's lights before and of each light tried.
"""

import json
import os
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
if HERE not in sys.path:
    sys.path.insert(0, HERE)
import dvr_boot  # noqa: E402

dvr_boot.bind()  # the package holding this folder, its site-packages kept off the path

from dvr_perception._paraview_compat import setup as _setup  # noqa: E402

_setup()  # .pvdeps on sys.path and the numpy/inspect shims (idempotent)

from dvr_quality import (  # noqa: E402
    QUALITY_MAPS,
    QUALITY_PREFIX,
    TABLE_VIEW,
    open_quality_views,
    show_quality,
)
from view_light import apply_light, restore_lights, save_lights  # noqa: E402

__all__ = [
    "QUALITY_MAPS",
    "QUALITY_PREFIX",
    "TABLE_VIEW",
    "install_macros",
    "measure_this_view",
    "optimise_this_view",
    "refine_region",
    "rubber_band_region",
    "run_macro",
    "selected_region",
    "show_quality",
    "undo",
]

OPTIMISER = "DVROptimizeTransferFunction"
MEASURES = "DVRPerceptionMeasures"
PRESET_NAME = "DVR Perception optimised"
#: Keep ParaView's rendering that :func:`paraview_ssim` compares at this path (None: deleted).
SSIM_IMAGE = None
_UNDO = []  # one saved state per action, newest last


def _simple():
    from paraview import simple

    return simple


def _xml_name(proxy):
    return proxy.SMProxy.GetXMLName() if proxy is not None else ""


def _render_view(view):
    view = view or _simple().GetActiveView()
    if view is None or not hasattr(view, "GetActiveCamera"):
        raise ValueError("DVR Perception: click a 3D render view first (no active render view)")
    return view


def _filter_for(source, kind, *, spec_file=None, spec_json=None):
    """``(volume, filter)``: the DVR filter ``kind`` on ``source``'s volume (reused or new).

    ``source`` is the volume or a DVR filter on it; an existing ``kind`` filter on that volume
    is reused, else one is created with the spec given, or the spec of another DVR filter on
    the volume.
    """
    simple = _simple()
    source = source or simple.GetActiveSource()
    if source is None:
        raise ValueError("DVR Perception: select the volume in the Pipeline Browser first")
    volume = source.Input if _xml_name(source) in (OPTIMISER, MEASURES) else source
    found = [
        p
        for p in simple.GetSources().values()
        if _xml_name(p) in (OPTIMISER, MEASURES) and p.Input == volume
    ]
    same = [p for p in found if _xml_name(p) == kind]
    if source is not volume and _xml_name(source) == kind:
        same.insert(0, source)
    proxy = same[0] if same else None
    if proxy is None:
        if not (spec_file or spec_json) and found:
            spec_file, spec_json = found[0].SpecFile, found[0].SpecJSON
        if not (spec_file or spec_json):
            raise ValueError(
                "DVR Perception: no structure spec for this volume; add a DVR Perception "
                "filter with a SpecFile once (Filters > DVR Perception) or pass spec_file"
            )
        proxy = _constructor(kind)(Input=volume, SpecFile=spec_file or "", SpecJSON=spec_json or "")
    elif spec_file or spec_json:
        proxy.SpecFile, proxy.SpecJSON = spec_file or "", spec_json or ""
    return volume, proxy


def _constructor(kind):
    """``paraview.simple``'s creation function of a plugin filter (the plugin must be loaded)."""
    simple = _simple()
    label = "OptimizeTransferFunction" if kind == OPTIMISER else "PerceptionMeasures"
    found = {}
    simple._add_functions(found)  # the constructors of every proxy the session knows now
    if label not in found:
        raise ValueError(
            "DVR Perception: load dvr_perception_plugin.py first (Tools > Manage Plugins)"
        )
    return found[label]


def _volume_display(volume, view):
    """The representation of ``volume`` in ``view``, shown as a volume coloured by scalars."""
    simple = _simple()
    display = simple.GetDisplayProperties(volume, view)
    if display is None or display.Representation != "Volume":
        display = simple.Show(volume, view)
        display.SetRepresentationType("Volume")
    array = display.ColorArrayName[1]
    if not array:
        names = volume.PointData.keys()
        if not names:
            raise ValueError("DVR Perception: the volume has no point array to render")
        simple.ColorBy(display, ("POINTS", names[0]))
    simple.Show(volume, view)
    return display


def _save_state(display, view, proxy):
    simple = _simple()
    array = display.ColorArrayName[1]
    lut, pwf = simple.GetColorTransferFunction(array), simple.GetOpacityTransferFunction(array)
    state = {
        "display": display,
        "view": view,
        "proxy": proxy,
        "lut": (lut, {k: lut.GetPropertyValue(k) for k in _LUT_KEYS}),
        "pwf": (pwf, {"Points": list(pwf.Points)}),
        "display_values": {k: display.GetPropertyValue(k) for k in _DISPLAY_KEYS},
        "view_values": {k: view.GetPropertyValue(k) for k in _VIEW_KEYS},
        "lights": save_lights(view),
        "proxy_values": {k: proxy.GetPropertyValue(k) for k in _PROXY_KEYS if proxy is not None},
    }
    for key, value in list(state["lut"][1].items()):
        state["lut"][1][key] = list(value) if key == "RGBPoints" else value
    _UNDO.append(state)


_LUT_KEYS = ("RGBPoints", "ColorSpace", "AutomaticRescaleRangeMode")
_DISPLAY_KEYS = ("Ambient", "Diffuse", "Specular", "SpecularPower", "Shade",
                 "ScalarOpacityUnitDistance")  # fmt: skip
_VIEW_KEYS = ("Background", "UseColorPaletteForBackground")
_PROXY_KEYS = ("CameraJSON", "UseSpecView", "Width", "Region")


def undo():
    """Restore the representation, view and filter as before the last action.

    Returns
    -------
    bool
        False when there is nothing to undo.
    """
    if not _UNDO:
        return False
    state = _UNDO.pop()
    lut, values = state["lut"]
    for key in ("AutomaticRescaleRangeMode", "ColorSpace", "RGBPoints"):
        lut.SetPropertyWithName(key, values[key])
    pwf, values = state["pwf"]
    pwf.Points = values["Points"]
    for target, values in (
        (state["display"], state["display_values"]),
        (state["view"], state["view_values"]),
        (state["proxy"], state["proxy_values"]),
    ):
        for key, value in values.items():
            target.SetPropertyWithName(key, list(value) if isinstance(value, tuple) else value)
    restore_lights(state["view"], state["lights"])
    _simple().Render(state["view"])
    return True


def _field(data, name):
    arr = data.GetFieldData().GetAbstractArray(name)
    if arr is None:
        return None
    n, c = arr.GetNumberOfTuples(), arr.GetNumberOfComponents()
    if c > 1:
        return [list(arr.GetTuple(i)) for i in range(n)]
    return [arr.GetValue(i) for i in range(n)]


def _tick(what):
    if os.environ.get("DVR_TIMING"):
        import time

        print(f"@@T {what} {time.time():.2f}", flush=True)


def _fetch(proxy, what):
    from paraview import servermanager

    proxy.UpdatePipeline()
    data = servermanager.Fetch(proxy)
    if data is None or data.GetFieldData().GetAbstractArray("E_v") is None:
        raise RuntimeError(f"DVR Perception: {what} failed (see Output Messages for the reason)")
    return data


def _use_view_camera(proxy, view, height):
    from view_camera import use_active_view_camera

    if height is not None:
        proxy.Height = int(height)
    proxy.UseSpecView = 0
    return use_active_view_camera(proxy, view)


def measure_this_view(source=None, view=None, *, spec_file=None, spec_json=None, height=None,
                      quality=True):  # fmt: skip
    """Measure the active view: *Perception Measures* with the view's camera.

    Parameters
    ----------
    source : proxy, optional
        The volume or a DVR filter on it (default: the active source).
    view : proxy, optional
        The 3-D render view (default: the active view).
    spec_file, spec_json : str, optional
        The structure spec (default: that of a DVR filter already on the volume).
    height : int, optional
        The filter's image height (its width follows the view's aspect ratio).
    quality : bool
        Open the quality maps and the table beside the view (default True).

    Returns
    -------
    dict
        ``{"E_v", "E_s", "E_t", "camera", "filter"}``.
    """
    view = _render_view(view)
    volume, proxy = _filter_for(source, MEASURES, spec_file=spec_file, spec_json=spec_json)
    _volume_display(volume, view)
    if quality:  # the maps' views first: the split changes the view's aspect ratio
        open_quality_views(view)
    camera = _use_view_camera(proxy, view, height)
    data = _fetch(proxy, "Perception Measures")
    if quality:
        show_quality(proxy, view, data)
    _simple().SetActiveView(view)
    report = {k: _field(data, k)[0] for k in ("E_v", "E_s", "E_t")}
    return dict(report, camera=camera, filter=proxy)


def optimise_this_view(source=None, view=None, *, spec_file=None, spec_json=None, height=None,
                       quality=True, preset_name=PRESET_NAME, preset_dir=None,
                       **properties):  # fmt: skip
    """Optimise the active view's volume with its camera and apply the result to it.

    Parameters
    ----------
    source, view, spec_file, spec_json, height, quality
        As :func:`measure_this_view` (the filter is *Optimize Transfer Function*).
    preset_name : str
        Name of the preset imported into ParaView's presets (*Choose Preset*).
    preset_dir : str, optional
        Folder of the preset file (default: a ``dvr_perception_presets`` folder in the
        temporary directory).
    **properties
        Other properties of the filter (``Stages``, ``MaxIterations``...); ``Region`` (the
        lens) is reset to the whole image unless given (:func:`refine_region` gives it).

    Returns
    -------
    dict
        ``camera`` (the view's, as set in the filter), ``spec`` (the optimised spec as a
        dict), ``E``/``initial_E`` (dicts of the terms), ``ssim`` (ParaView's rendering vs the
        engine's), ``light`` (the light kept, None unshaded) and ``ssim_by_light``,
        ``preset`` (name), ``preset_file``, ``filter`` and ``display``.
    """
    from apply_result import apply_optimized

    simple = _simple()
    view = _render_view(view)
    volume, proxy = _filter_for(source, OPTIMISER, spec_file=spec_file, spec_json=spec_json)
    display = _volume_display(volume, view)
    _save_state(display, view, proxy)
    properties.setdefault("Region", "")  # the whole view unless a lens is given (refine)
    for key, value in properties.items():
        proxy.SetPropertyWithName(key, value)
    if quality:  # the maps' views first: the split changes the view's aspect ratio
        open_quality_views(view)
    camera = _use_view_camera(proxy, view, height)
    proxy.ParaViewSSIM = -1.0
    data = _fetch(proxy, "Optimize Transfer Function")
    _tick("fetched")
    spec_text = _field(data, "optimized_spec_json")[0]
    folder = preset_dir or os.path.join(tempfile.gettempdir(), "dvr_perception_presets")
    os.makedirs(folder, exist_ok=True)
    preset_file = os.path.join(folder, _file_name(preset_name) + ".json")
    spec = apply_optimized(spec_text, display, preset_path=preset_file, preset_name=preset_name)
    display.ScalarOpacityUnitDistance = float(_field(data, "opacity_unit_distance")[0])
    view.UseColorPaletteForBackground = 0
    view.Background = [float(c) for c in spec.background]
    _import_preset(preset_file, preset_name)
    simple.Hide(proxy, view)  # the output image is a 2-D map: never a slab in the 3-D view
    _tick("applied")
    lights = {"view's lights": paraview_ssim(view, data, spec.background)}
    light = None
    if spec.rendering.shade:  # the engine's light (unshaded: no light acts)
        light, tried = apply_light(view, spec, lambda: paraview_ssim(view, data, spec.background))
        lights.update(tried)
        if SSIM_IMAGE and light != list(tried)[-1]:  # keep the capture of the kept light
            tried[light] = paraview_ssim(view, data, spec.background)
    ssim = lights[light] if light else lights["view's lights"]
    _tick("ssim")
    proxy.ParaViewSSIM = ssim
    proxy.UpdatePipeline()
    _tick("ssim field")
    if quality:
        show_quality(proxy, view, data)
    _tick("quality")
    simple.SetActiveView(view)
    simple.Render(view)
    terms = ("E_v", "E_s", "E_t", "E")
    lens = {}
    if _field(data, "lens_E") is not None:  # a Region: the optimiser's terms inside the lens
        lens = {
            "lens_E": {k: _field(data, f"lens_{k}")[0] for k in terms},
            "lens_initial_E": {k: _field(data, f"lens_initial_{k}")[0] for k in terms},
            "lens_region": _field(data, "lens_region")[0],
        }
    return {
        **lens,
        "camera": camera,
        "spec": json.loads(spec_text),
        "E": {k: _field(data, k)[0] for k in terms},
        "initial_E": {k: _field(data, f"initial_{k}")[0] for k in terms},
        "ssim": ssim,
        "light": light,
        "ssim_by_light": lights,
        "preset": preset_name,
        "preset_file": preset_file,
        "filter": proxy,
        "display": display,
    }


def refine_region(source=None, view=None, *, region=None, **kwargs):
    """Optimise again with the lens on the selected region.

    Parameters
    ----------
    source, view
        As :func:`optimise_this_view`.
    region : (x0, y0, x1, y1), optional
        The lens in output pixels (x right, y down).  Default: the rubber band drawn in the 3-D
        view (*Select Cells Through* or *Select Points Through* on the volume,
        :func:`rubber_band_region`), else the bounding box of the points selected on the
        optimiser's output in a quality-map view (*Select Points On*, :func:`selected_region`).
    **kwargs
        Passed to :func:`optimise_this_view`.

    Returns
    -------
    dict
        :func:`optimise_this_view`'s report plus ``region`` and ``region_from`` (``"given"``,
        ``"3d view"`` or ``"quality map"``).
    """
    view = _render_view(view)
    volume, proxy = _filter_for(source, OPTIMISER, spec_file=kwargs.pop("spec_file", None))
    where = "given"
    if region is None:
        region = rubber_band_region(volume, proxy, view, height=kwargs.get("height"))
        where = "3d view"
    if region is None:
        region, where = selected_region(proxy), "quality map"
    x0, y0, x1, y1 = (int(v) for v in region)
    report = optimise_this_view(proxy, view, Region=f"rect,{x0},{y0},{x1},{y1}", **kwargs)
    report["region"] = (x0, y0, x1, y1)
    report["region_from"] = where
    return report


def rubber_band_region(volume, proxy, view, *, height=None):
    """The lens of the rubber band drawn on ``volume`` in the 3-D ``view`` (None: none drawn).

    The frustum of *Select Cells/Points Through* (:func:`view_lens.view_frustum`) projected
    through the camera ``proxy`` will use: ``view``'s, at ``height`` (default: the filter's
    ``Height``) and the width of the view's aspect ratio (:func:`view_lens.lens_from_frustum`).
    Several frustums (the *Add* modifier) give the bounding box of their lenses.
    """
    from view_camera import camera_from_view, matched_width
    from view_lens import lens_from_frustum, view_frustum

    from dvr_perception.rays.camera import Camera

    frustums = view_frustum(volume)
    if not frustums:
        return None
    h = int(proxy.Height) if height is None else int(height)
    camera = Camera.from_dict(
        dict(camera_from_view(view), width=matched_width(proxy, view, height=h), height=h)
    )
    boxes = [lens_from_frustum(f, camera) for f in frustums]
    return (min(b[0] for b in boxes), min(b[1] for b in boxes),
            max(b[2] for b in boxes), max(b[3] for b in boxes))  # fmt: skip


def selected_region(proxy):
    """Bounding box ``(x0, y0, x1, y1)`` (pixels, y down) of the points selected on ``proxy``."""
    from paraview import servermanager

    simple = _simple()
    selection = proxy.SMProxy.GetSelectionInput(0)
    if selection is None:
        raise ValueError(
            "DVR Perception: select a region first: drag a rubber band over the volume in the "
            "3D view (Select Cells Through), or over a quality map (Select Points On)"
        )
    extract = simple.ExtractSelection(Input=proxy, Selection=servermanager._getPyProxy(selection))
    try:
        data = servermanager.Fetch(extract)
        ids = data.GetPointData().GetArray("vtkOriginalPointIds") if data else None
        if ids is None or ids.GetNumberOfTuples() == 0:
            raise ValueError("DVR Perception: the selection holds no point of the quality map")
        width, height = (int(v) for v in (proxy.Width, proxy.Height))
        pixels = [int(ids.GetValue(i)) for i in range(ids.GetNumberOfTuples())]
    finally:
        simple.Delete(extract)
    xs = [p % width for p in pixels]
    ys = [height - 1 - p // width for p in pixels]  # VTK rows go up, the lens's go down
    return min(xs), min(ys), max(xs) + 1, max(ys) + 1


def _file_name(name):
    keep = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
    return keep or "dvr_perception"


def _import_preset(path, name):
    """Import the preset file into ParaView's presets, replacing an older one of that name."""
    from paraview import servermanager

    presets = servermanager.vtkSMTransferFunctionPresets.GetInstance()
    while presets.HasPreset(name):
        _remove_by_scan(presets, name)
    if not _simple().ImportPresets(path):
        raise RuntimeError(f"DVR Perception: ParaView could not import the preset {path}")


def _remove_by_scan(presets, name):
    for i in range(presets.GetNumberOfPresets()):
        if presets.GetPresetName(i) == name:
            presets.RemovePreset(i)
            return
    raise RuntimeError(f"DVR Perception: cannot replace the preset {name!r}")


def paraview_ssim(view, data, background):
    """SSIM of ParaView's rendering of ``view`` vs the engine's image in ``data`` (``rgba``).

    ParaView renders the view at the filter's image size (the camera is the filter's), with
    the orientation axes and the other sources hidden; the engine's premultiplied ``rgba`` is
    composited over ``background``.  ParaView's image is kept at :data:`SSIM_IMAGE` if set.
    """
    import numpy as np
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOImage import vtkPNGReader

    from dvr_perception.rays.vtk_reference import compare_images

    simple = _simple()
    w, h, _ = data.GetDimensions()
    rgba = vtk_to_numpy(data.GetPointData().GetArray("rgba")).reshape(h, w, 4).astype(float)
    engine = rgba[..., :3] + (1.0 - rgba[..., 3:]) * np.asarray(background, float)
    axes = view.OrientationAxesVisibility
    view.OrientationAxesVisibility = 0
    volume_reps = [r for r in view.Representations if _is_shown_volume(r)]
    others = [r for r in view.Representations if r not in volume_reps and _visible(r)]
    for rep in others:
        rep.Visibility = 0
    path = os.path.join(tempfile.mkdtemp(prefix="dvr_ssim_"), "paraview.png")
    try:
        simple.SaveScreenshot(path, view, ImageResolution=[w, h])
        reader = vtkPNGReader()
        reader.SetFileName(path)
        reader.Update()
        img = reader.GetOutput()
        comps = img.GetPointData().GetScalars().GetNumberOfComponents()
        shot = vtk_to_numpy(img.GetPointData().GetScalars()).reshape(h, w, comps)[..., :3]
    finally:
        view.OrientationAxesVisibility = axes
        for rep in others:
            rep.Visibility = 1
        if os.path.exists(path):
            if SSIM_IMAGE:
                import shutil

                shutil.move(path, SSIM_IMAGE)
            else:
                os.remove(path)
        os.rmdir(os.path.dirname(path))
    return compare_images(shot / 255.0, np.clip(engine, 0.0, 1.0))["ssim"]


def _visible(rep):
    try:
        return bool(rep.Visibility)
    except AttributeError:
        return False


def _is_shown_volume(rep):
    try:
        return bool(rep.Visibility) and rep.Representation == "Volume"
    except AttributeError:
        return False


#: The last report of each action (``run_macro``), for the Python Shell.
last_report = {}


def run_macro(action):
    """Run one toolbar action (``"measure"``, ``"optimise"``, ``"refine"``, ``"undo"``).

    Prints one summary line (ParaView's *Output Messages*) and keeps the report in
    :data:`last_report`.
    """
    if action == "undo":
        done = undo()
        print("DVR Perception: undone" if done else "DVR Perception: nothing to undo")
        return done
    run = {"measure": measure_this_view, "optimise": optimise_this_view, "refine": refine_region}
    report = run[action]()
    last_report[action] = report
    if action == "measure":
        terms = ", ".join(f"{k} {report[k]:.4f}" for k in ("E_v", "E_s", "E_t"))
        print(f"DVR Perception: measured {terms}")
    else:
        where = ""
        if "lens_E" in report:
            where = (
                f" in region {report['region']} (from the {report['region_from']}; lens E "
                f"{report['lens_initial_E']['E']:.4f} -> {report['lens_E']['E']:.4f})"
            )
        light = f" ({report['light']})" if report["light"] else ""
        print(
            f"DVR Perception: optimised{where}: E {report['initial_E']['E']:.4f} -> "
            f"{report['E']['E']:.4f}; ParaView vs engine SSIM {report['ssim']:.3f}{light}; "
            f"preset {report['preset']!r}"
        )
    return report


def install_macros(folder=None):
    """Copy the DVR Perception macros into ParaView's user macro folder (see ``install_macros``).

    ParaView lists every ``.py`` file of ``~/.config/ParaView/Macros`` (``$XDG_CONFIG_HOME``)
    in the *Macros* menu and on the *Macro Toolbar* at start-up.  Returns the written paths.
    """
    import install_macros

    return install_macros.install(folder)
