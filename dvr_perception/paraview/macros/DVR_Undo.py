"""ParaView macro (DVR Perception toolbar). Undo: the volume's transfer functions, material, the
view's background and lights and the filter's camera as before the last DVR Perception action.

Installed into ParaView's macro folder by ``make paraview-macros`` (or ``dvr-perception
paraview-plugin --install-macros``); the plugin must be loaded.  Acts in one step on the active
source (the volume, or a DVR Perception filter on it) and the active view.
"""

import sys

plugin = sys.modules.get("dvr_perception_plugin")
if plugin is None:
    raise RuntimeError("DVR_Undo: load dvr_perception_plugin.py first (Tools > Manage Plugins)")
plugin.run_macro("undo")
