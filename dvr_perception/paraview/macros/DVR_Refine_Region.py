"""ParaView macro (DVR Perception toolbar). Refine region: optimise again with the lens on the
rubber band dragged over the volume in the 3D view (*Select Cells Through*), or else on the
points selected in a quality-map view (*Select Points On*, then a rubber band).

Installed into ParaView's macro folder by ``make paraview-macros`` (or ``dvr-perception
paraview-plugin --install-macros``); the plugin must be loaded.  Acts in one step on the active
source (the volume, or a DVR Perception filter on it) and the active view.
"""

import sys

plugin = sys.modules.get("dvr_perception_plugin")
if plugin is None:
    raise RuntimeError(
        "DVR_Refine_Region: load dvr_perception_plugin.py first (Tools > Manage Plugins)"
    )
plugin.run_macro("refine")
