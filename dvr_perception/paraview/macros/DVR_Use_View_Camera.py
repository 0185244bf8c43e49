"""ParaView macro: give the selected DVR Perception filter the camera of the active 3D view.

Import once with *Macros > Import new macro...* (ParaView copies it into its macro folder).
Then select *Perception Measures* or *Optimize Transfer Function* in the Pipeline Browser,
click the render view whose camera you want, and run *Macros > DVR_Use_View_Camera*: the
filter's ``CameraJSON`` (and ``Width``, for the view's aspect ratio) change at once and the
filter re-executes on its next update (*Apply*, or a render of a view that shows it).  The
plugin must be loaded: the macro finds ``view_camera.py`` next to it.
"""

import os
import sys

plugin = sys.modules.get("dvr_perception_plugin")
if plugin is None:
    raise RuntimeError("DVR_Use_View_Camera: load dvr_perception_plugin.py first")
folder = os.path.dirname(os.path.abspath(plugin.__file__))
if folder not in sys.path:
    sys.path.insert(0, folder)

from view_camera import use_active_view_camera  # noqa: E402

camera = use_active_view_camera()
print("DVR Perception: camera of the active view ->", camera)
