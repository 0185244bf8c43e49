"""Perceptual measures: luminance, psychophysical transmittance models and layer regions.

Pure functions on numpy arrays (paper, Sec. 4.3): :mod:`~.luminance` turns rendered colour
into linear-light luminance, :mod:`~.psychophysics` estimates a layer's perceived
transmittance (Metelli, Eq. 5 and 9; TAP, Eq. 6-7; their blend, Eq. 8; calibration), and
:mod:`~.regions` finds the structural layers' footprints, sub-regions and relations.

The three quality measures read a ray analysis: :func:`~.visibility.visibility` (Sec. 4.1,
Eq. 1-2), :func:`~.shape.shape` (Sec. 4.2, Eq. 3-4) and :func:`~.transparency.transparency`
(Sec. 4.3, Eq. 5-11); their results are the dataclasses of :mod:`~.results`, and
:func:`~.combined.all_measures` computes the three together (transparency in a worker thread).
:func:`~.covered.covered_transmittance` is the TAP of one layer over what it covers, seen
with and without it (the paper's Fig. 9 reading).
"""

from dvr_perception.measures.combined import MeasureSet, all_measures
from dvr_perception.measures.covered import CoveredTransmittance, covered_transmittance
from dvr_perception.measures.luminance import composite_luminance, luminance
from dvr_perception.measures.psychophysics import (
    blended_transmittance,
    calibrate,
    generalized_metelli,
    luminance_range,
    metelli_transmittance,
    tap_transmittance,
)
from dvr_perception.measures.regions import (
    Region,
    RegionMap,
    Relation,
    layer_footprints,
    layer_relations,
    subregions,
)
from dvr_perception.measures.results import ShapeResult, TransparencyResult, VisibilityResult
from dvr_perception.measures.shape import shape
from dvr_perception.measures.transparency import transparency
from dvr_perception.measures.visibility import visibility

__all__ = [
    "CoveredTransmittance",
    "MeasureSet",
    "Region",
    "RegionMap",
    "Relation",
    "ShapeResult",
    "TransparencyResult",
    "VisibilityResult",
    "all_measures",
    "blended_transmittance",
    "calibrate",
    "composite_luminance",
    "covered_transmittance",
    "generalized_metelli",
    "layer_footprints",
    "layer_relations",
    "luminance",
    "luminance_range",
    "metelli_transmittance",
    "shape",
    "subregions",
    "tap_transmittance",
    "transparency",
    "visibility",
]
