"""pvpython script: (re)write the ParaView state files of presets in ``state_files/``.

Usage (from the repository root, with an X display -- e.g. under ``xvfb-run``)::

    PYTHONPATH=dvr_perception/paraview/pvsite pvpython plugin/make_state_files.py \
        [--data DIR] [NAME ...]

For each NAME (default: neghip tooth) the pipeline is built in ParaView -- NRRD reader of
``DIR/NAME.nhdr`` (default ``../shared/data``), the plugin's *Perception Measures* filter with
the preset ``state_files/NAME.json`` embedded as ``SpecJSON`` (so the state needs no spec
file), a volume representation with the preset's colour/opacity transfer functions, material
and view, the filter's image and a spreadsheet of its field data (E_v, E_s, E_t) -- and saved
twice, by ParaView itself:

``state_files/NAME.pvsm``
    ``SaveState``; load it with ``LoadState(path, data_directory=DIR)`` (GUI: *File > Load
    State*, *Search files under specified directory*) after loading the plugin.
``state_files/NAME_state.py``
    ParaView's Python state (``paraview.smstate.get_state``) behind a short header that loads
    the plugin and takes the data folder from ``data_directory`` (a global set by the caller),
    ``$DVR_SHARED_DATA`` or ``<repo>/../shared/data``.

The data folder stored in the ``.pvsm`` is the placeholder :data:`PLACEHOLDER` (the state is
saved against a temporary copy of the volume), so loading always relocates the reader.
"""

import json
import os
import shutil
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
PLUGIN = os.path.join(ROOT, "dvr_perception", "paraview", "dvr_perception_plugin.py")
STATE_DIR = os.path.join(ROOT, "state_files")
PLACEHOLDER = "/path/to/shared/data"
IMAGE_SIZE = 256

PY_HEADER = '''"""ParaView Python state: {name} with the dvr_perception Perception Measures filter.

Written by plugin/make_state_files.py (ParaView {version}); the body below is ParaView's own
Python state.  Run it in pvpython (``PYTHONPATH=dvr_perception/paraview/pvsite``),
with ``exec``/``runpy`` and a global ``data_directory``, or load it in the GUI (*File > Load
State*, Python state).  The volume is looked up in ``data_directory``, else
``$DVR_SHARED_DATA``, else ``<repo>/../shared/data``.
"""

import os

import paraview
from paraview.simple import *

paraview.compatibility.major = {major}
paraview.compatibility.minor = {minor}

try:
    _repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
except NameError:  # run without a file name (e.g. pasted into the Python shell)
    _repo = os.getcwd()
data_directory = (
    globals().get("data_directory")
    or os.environ.get("DVR_SHARED_DATA")
    or os.path.join(os.path.dirname(_repo), "shared", "data")
)
if "PerceptionMeasures" not in globals():
    LoadPlugin(os.path.join(_repo, "dvr_perception", "paraview", "dvr_perception_plugin.py"),
               ns=globals())

#### disable automatic camera reset on 'Show'
paraview.simple._DisableFirstRenderCameraReset()
'''


def build(pvs, name, data_dir):
    """Build the pipeline and views of preset ``name`` reading ``data_dir/name.nhdr``."""
    import argparse

    from batch_measure import set_camera, set_transfer_functions

    from dvr_perception.inputs import load_inputs

    nhdr = os.path.join(data_dir, f"{name}.nhdr")
    spec_path = os.path.join(STATE_DIR, f"{name}.json")
    args = argparse.Namespace(
        volume=nhdr, structures=spec_path, view=None, camera=None, size=str(IMAGE_SIZE), shade=None
    )
    inputs = load_inputs(args)
    spec, camera = inputs.spec, inputs.camera
    with open(spec_path, encoding="utf-8") as f:
        spec_json = json.dumps(json.load(f), separators=(",", ":"))

    reader = pvs.NrrdReader(registrationName=f"{name}.nhdr", FileName=nhdr)
    reader.UpdatePipelineInformation()
    array = reader.PointData.keys()[0] if reader.PointData.keys() else "ImageFile"
    measures = pvs.PerceptionMeasures(
        registrationName="Perception Measures",
        Input=reader,
        ScalarArray=array,
        SpecJSON=spec_json,
        UseSpecView=1,
        Width=IMAGE_SIZE,
        Height=IMAGE_SIZE,
    )
    layout = pvs.CreateLayout(name)
    # left: the volume with the preset's transfer functions, seen by the preset's camera
    view = pvs.CreateView("RenderView")
    pvs.AssignViewToLayout(view=view, layout=layout, hint=0)
    view.OrientationAxesVisibility = 0
    view.UseColorPaletteForBackground = 0
    view.Background = [float(c) for c in spec.background]
    display = pvs.Show(reader, view)
    display.SetRepresentationType("Volume")
    pvs.ColorBy(display, ("POINTS", array))
    set_transfer_functions(pvs, display, array, spec)
    display.VolumeRenderingMode = "Ray Cast Only"
    unit = spec.rendering.opacity_unit_distance
    display.ScalarOpacityUnitDistance = float(min(inputs.volume.spacing) if unit is None else unit)
    display.Shade = int(bool(spec.rendering.shade))
    light = spec.structures[0].lighting
    display.Ambient, display.Diffuse = light.ambient, light.diffuse
    display.Specular, display.SpecularPower = light.specular, light.specular_power
    set_camera(view, camera)
    # right: the filter's image (RGBA as colours) above its field data (E_v, E_s, E_t, ...)
    layout.SplitHorizontal(0, 0.5)
    image_view = pvs.CreateView("RenderView")
    pvs.AssignViewToLayout(view=image_view, layout=layout, hint=2)
    image_view.OrientationAxesVisibility = 0
    image_view.InteractionMode = "2D"
    image_display = pvs.Show(measures, image_view)
    image_display.SetRepresentationType("Slice")
    pvs.ColorBy(image_display, ("POINTS", "rgba"))
    image_display.MapScalars = 0
    pvs.ResetCamera(image_view)
    layout.SplitVertical(2, 0.6)
    sheet = pvs.CreateView("SpreadSheetView")
    pvs.AssignViewToLayout(view=sheet, layout=layout, hint=6)
    sheet_display = pvs.Show(measures, sheet)
    sheet.FieldAssociation = "Field Data"
    sheet_display.Assembly = ""
    pvs.SetActiveView(view)
    pvs.SetActiveSource(measures)
    return measures


def python_state(name, pvsm_text, version):
    """ParaView's Python state of the current session, with the header above."""
    from paraview import smstate

    body = smstate.get_state()
    major, minor = version.split(".")[:2]
    lines = body.splitlines()
    # drop ParaView's own preamble (imports, compatibility, camera reset): the header has it
    start = next(i for i, ln in enumerate(lines) if ln.startswith("# Create a new"))
    body = "\n".join(lines[start:]) + "\n"
    return PY_HEADER.format(name=name, version=version, major=major, minor=minor) + "\n" + body


def main(argv):
    data = os.path.join(os.path.dirname(ROOT), "shared", "data")
    if argv[:1] == ["--data"]:
        data, argv = argv[1], argv[2:]
    names = argv or ["neghip", "tooth"]
    sys.path.insert(0, HERE)
    sys.path.insert(0, ROOT)
    from dvr_perception._paraview_compat import setup

    setup()
    from paraview import servermanager
    from paraview import simple as pvs

    pvs.LoadPlugin(PLUGIN, ns=globals())
    version = servermanager.vtkSMProxyManager.GetParaViewSourceVersion().split()[-1]
    for name in names:
        pvs.ResetSession()
        pvs.LoadPlugin(PLUGIN, ns=globals())
        tmp = tempfile.mkdtemp(prefix="dvr_state_")
        try:
            with open(os.path.join(data, f"{name}.nhdr"), encoding="ascii") as f:
                header = f.read()
            raw = next(
                ln.split(":", 1)[1].strip()
                for ln in header.splitlines()
                if ln.startswith("data file")
            )
            shutil.copy(os.path.join(data, f"{name}.nhdr"), tmp)
            shutil.copy(os.path.join(data, raw), tmp)
            build(pvs, name, tmp)
            pvsm = os.path.join(STATE_DIR, f"{name}.pvsm")
            pvs.SaveState(pvsm)
            with open(pvsm, encoding="utf-8") as f:
                text = f.read().replace(tmp, PLACEHOLDER)
            with open(pvsm, "w", encoding="utf-8") as f:
                f.write(text)
            py = python_state(name, text, version).replace(
                repr(os.path.join(tmp, f"{name}.nhdr")),
                f"os.path.join(data_directory, {name + '.nhdr'!r})",
            )
            if tmp in py:
                raise RuntimeError(f"{name}: the Python state still names {tmp}")
            with open(os.path.join(STATE_DIR, f"{name}_state.py"), "w", encoding="utf-8") as f:
                f.write(py)
            print(f"wrote state_files/{name}.pvsm and state_files/{name}_state.py")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    status = main(sys.argv[1:])
    # leave without interpreter teardown: it destroys the OpenGL contexts in the wrong order
    # (an X "GLXBadContext" abort, as in batch_measure.py)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
