"""ParaView macro (DVR Perception toolbar). Measure this view: *Perception Measures* with the
active 3D view's camera; the quality maps and the per-structure table open beside the view.

Installed into ParaView's macro folder by ``make paraview-macros`` (or ``dvr-perception
paraview-plugin --install-macros``); the plugin must be loaded.  Acts in one step on the active
source (the volume, or a DVR Perception filter on it) and the active view.
"""

import sys

plugin = sys.modules.get("dvr_perception_plugin")
if plugin is None:
    raise RuntimeError(
        "DVR_Measure_View: load dvr_perception_plugin.py first (Tools > Manage Plugins)"
    )
plugin.run_macro("measure")
