"""Structures: spec data model and JSON, Slicer segmentations, transfer functions, proposal.

Also the built-in data: the phantom with its spec (:func:`make_phantom`) and the presets.
"""

from dvr_perception.structures.io import (
    check_spec_for_volume,
    load_spec,
    save_spec,
    spec_from_dict,
    spec_to_dict,
)
from dvr_perception.structures.phantom import make_phantom, phantom_spec
from dvr_perception.structures.propose import propose_structures
from dvr_perception.structures.slicer import spec_from_segmentation
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec

__all__ = [
    "Lighting",
    "RenderSettings",
    "Structure",
    "StructureSpec",
    "check_spec_for_volume",
    "load_spec",
    "make_phantom",
    "phantom_spec",
    "propose_structures",
    "save_spec",
    "spec_from_dict",
    "spec_from_segmentation",
    "spec_to_dict",
]
