"""Export a structure spec to other tools' transfer functions and transfer-function files.

:mod:`~.vtk` builds VTK transfer functions and volume properties (and reads a spec back from
them), :mod:`~.paraview` writes a ParaView colour-map/opacity preset (*Choose Preset ->
Import*) and :mod:`~.slicer` a 3D Slicer volume-property ``.vp.json`` file.  Both carry
exactly the nodes of :func:`~dvr_perception.export.vtk.to_vtk_transfer_functions`, so the
structures' trapezoids render the same there.  Both are intensity-based: label structures are
refused.  The spec itself is saved with :func:`dvr_perception.structures.save_spec`.
"""

from dvr_perception.export.paraview import paraview_preset, save_paraview_preset
from dvr_perception.export.slicer import save_slicer_vp, slicer_volume_property
from dvr_perception.export.vtk import (
    GPU_TABLE_SAMPLES,
    spec_from_vtk,
    to_vtk_property,
    to_vtk_transfer_functions,
)

__all__ = [
    "GPU_TABLE_SAMPLES",
    "paraview_preset",
    "save_paraview_preset",
    "save_slicer_vp",
    "slicer_volume_property",
    "spec_from_vtk",
    "to_vtk_property",
    "to_vtk_transfer_functions",
]
