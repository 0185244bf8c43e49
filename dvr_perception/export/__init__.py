"""Export a structure spec to other tools' transfer-function files.

:mod:`~.paraview` writes a ParaView colour-map/opacity preset (*Choose Preset -> Import*) and
:mod:`~.slicer` a 3D Slicer volume-property ``.vp.json`` file.  Both carry exactly the nodes of
:func:`dvr_perception.structures.transfer.to_vtk_transfer_functions`, so the structures'
trapezoids render the same there.  Both are intensity-based: label structures are refused.
The spec itself is saved with :func:`dvr_perception.structures.save_spec`.
"""

from dvr_perception.export.paraview import paraview_preset, save_paraview_preset
from dvr_perception.export.slicer import save_slicer_vp, slicer_volume_property

__all__ = ["paraview_preset", "save_paraview_preset", "save_slicer_vp", "slicer_volume_property"]
