"""The optimiser's terms and the measures of one engine rendering share the shape measure."""

from dataclasses import replace

import pytest

from dvr_perception.measures import shape
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom


@pytest.fixture(scope="module")
def rendering():
    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=24, height=24)
    return analyze(vol, spec, cam, build_cache=True), spec


def test_shape_is_made_once_per_rendering_names_and_background(rendering):
    analysis, spec = rendering
    first = shape(analysis, spec)
    assert shape(analysis, spec) is first
    assert not first.deviation.flags.writeable
    assert not first.v_i.flags.writeable
    recoloured = replace(spec, structures=tuple(replace(s, colour=(0.1, 0.2, 0.3))
                                                for s in spec.structures))  # fmt: skip
    assert shape(analysis, recoloured) is first  # the colours come from the rendering
    grey = replace(spec, background=(0.5, 0.5, 0.5))
    behind = shape(analysis, grey)
    assert behind is not first
    assert behind.E_s != first.E_s
    assert shape(analysis, spec, steepness=0.1) is not first
