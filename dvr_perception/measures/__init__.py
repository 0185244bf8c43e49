"""Perceptual measures: luminance, psychophysical transmittance models and layer regions.

Pure functions on numpy arrays (paper, Sec. 4.3): :mod:`~.luminance` turns rendered colour
into linear-light luminance, :mod:`~.psychophysics` estimates a layer's perceived
transmittance (Metelli, Eq. 5 and 9; TAP, Eq. 6-7; their blend, Eq. 8; calibration), and
:mod:`~.regions` finds the structural layers' footprints, sub-regions and relations.
"""

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

__all__ = [
    "Region",
    "RegionMap",
    "Relation",
    "blended_transmittance",
    "calibrate",
    "composite_luminance",
    "generalized_metelli",
    "layer_footprints",
    "layer_relations",
    "luminance",
    "luminance_range",
    "metelli_transmittance",
    "subregions",
    "tap_transmittance",
]
