"""The optimiser's terms and the measures of one engine rendering share their work (once)."""

import sys
from dataclasses import replace

import numpy as np
import pytest

from dvr_perception.measures import shape, transparency
from dvr_perception.measures.transparency import transparency_table
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom

TRANSPARENCY = sys.modules["dvr_perception.measures.transparency"]


@pytest.fixture(scope="module")
def rendering():
    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=24, height=24)
    return analyze(vol, spec, cam, build_cache=True), spec


def test_transparency_after_its_table_reuses_the_layers_and_estimates(rendering, monkeypatch):
    analysis, spec = rendering
    calls = []
    core = TRANSPARENCY._core
    monkeypatch.setattr(TRANSPARENCY, "_core", lambda *a: calls.append(1) or core(*a))
    region_id, deltas, _, _empty = transparency_table(analysis, spec)
    res = transparency(analysis, spec)
    assert len(calls) == 1
    assert np.array_equal(res.region_id, region_id)
    assert np.array_equal(res.deviation, deltas[region_id].astype(np.float32))
    again = transparency(analysis, spec)  # the notes are not added to twice
    assert again.notes == res.notes
    assert again.E_t == res.E_t
    assert len(calls) == 1
    other = replace(spec, structures=(replace(spec.structures[0], importance=0.55),
                                      *spec.structures[1:]))  # fmt: skip
    transparency(analysis, other)  # another importance: made again
    assert len(calls) == 2
    transparency(analysis, spec, calibration=([0.0, 1.0], [0.0, 1.0]))  # not kept
    assert len(calls) == 3


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
