"""The scene of ``plugin/screenshot_gui.sh``, run by the GUI (``paraview --script=...``).

Opens ``$DVR_SCREENSHOT_VOLUME`` (default ``<repo>/../shared/data/neghip.nhdr``), shows it as
a ray-cast volume with the transfer functions of ``state_files/neghip.json``, adds the
plugin's *Optimize Transfer Function* filter with non-default stages, weights, seed and
iterations (not applied: the panel shows the properties, nothing is optimised) and selects it,
so its *Properties* panel is the one on screen.  Then it touches ``$DVR_SCREENSHOT_READY``
for the shell script, which waits for that file before it captures the screen.
"""

import os
import sys

import paraview.simple as pvs
from paraview.simple import (
    ColorBy,
    GetActiveViewOrCreate,
    OpenDataFile,
    RenameSource,
    Render,
    ResetCamera,
    SetActiveSource,
    Show,
)

PLUGIN_DIR = os.environ["DVR_SCREENSHOT_PLUGIN_DIR"]  # set by screenshot_gui.sh
ROOT = os.path.dirname(PLUGIN_DIR)
sys.path.insert(0, PLUGIN_DIR)

from batch_measure import set_transfer_functions  # noqa: E402  (also sets up dvr_perception)

from dvr_perception.structures.io import load_spec  # noqa: E402

volume = os.environ.get("DVR_SCREENSHOT_VOLUME") or os.path.join(
    os.path.dirname(ROOT), "shared", "data", "neghip.nhdr"
)
spec_file = os.path.join(ROOT, "state_files", "neghip.json")
spec = load_spec(spec_file)

reader = OpenDataFile(volume)
RenameSource(os.path.basename(volume), reader)
array = reader.PointData.keys()[0]
view = GetActiveViewOrCreate("RenderView")
view.OrientationAxesVisibility = 1
display = Show(reader, view)
display.SetRepresentationType("Volume")
ColorBy(display, ("POINTS", array))
set_transfer_functions(pvs, display, array, spec)
display.Shade = 1
ResetCamera(view)
camera = view.GetActiveCamera()
camera.Azimuth(30.0)
camera.Elevation(20.0)
camera.Dolly(0.9)

opt = pvs.OptimizeTransferFunction(  # the plugin is on PV_PLUGIN_PATH
    registrationName="OptimizeTransferFunction1",
    Input=reader,
    SpecFile=spec_file,
    Stages="opacity,lighting",
    Weights=[1.0, 2.0, 1.0],
    Seed=7,
    MaxIterations=5,
)
SetActiveSource(opt)
Render(view)

ready = os.environ.get("DVR_SCREENSHOT_READY")
if ready:
    with open(ready, "w", encoding="utf-8") as f:
        f.write("ready\n")
