"""ParaView macro (DVR Perception toolbar). Optimise this view: *Optimize Transfer Function* with
the active 3D view's camera; the volume in that view then carries the optimised transfer
functions, material and shading, the result is saved as the preset "DVR Perception optimised"
and the quality maps open beside the view.

Installed into ParaView's macro folder by ``make paraview-macros`` (or ``dvr-perception
paraview-plugin --install-macros``); the plugin must be loaded.  Acts in one step on the active
source (the volume, or a DVR Perception filter on it) and the active view.
"""

import sys

plugin = sys.modules.get("dvr_perception_plugin")
if plugin is None:
    raise RuntimeError(
        "DVR_Optimise_View: load dvr_perception_plugin.py first (Tools > Manage Plugins)"
    )
plugin.run_macro("optimise")
