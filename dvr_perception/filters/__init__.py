"""VTK filters (``VTKPythonAlgorithmBase``) wrapping the library for VTK pipelines and ParaView.

:class:`StructuralLayers` adds structure ids, the boundary mask and boundary curvature to a
volume; :class:`PerceptionMeasures` renders the volume with the engine and outputs the image
with the per-pixel deviations and, in field data, ``E_v``, ``E_s``, ``E_t`` and per-structure
values; :class:`VolumeReader` reads a volume file in patient LPS (the CLI's reader);
:class:`TransferFunctionOptimizer` optimises opacity, lighting and colour
(:func:`dvr_perception.optimize.optimize`) and outputs the optimised rendering like
:class:`PerceptionMeasures`, with the optimised parameters as field data.  All need only the
VTK modules of :mod:`dvr_perception._vtk` (they run in ParaView's ``pvpython``); bad
input is reported as a VTK error (``ErrorEvent`` / output window) and the update fails, the
process never crashes.
"""

from dvr_perception.filters.optimizer import TransferFunctionOptimizer
from dvr_perception.filters.perception_measures import PerceptionMeasures
from dvr_perception.filters.structural_layers import StructuralLayers
from dvr_perception.filters.volume_reader import VolumeReader

__all__ = ["PerceptionMeasures", "StructuralLayers", "TransferFunctionOptimizer", "VolumeReader"]
