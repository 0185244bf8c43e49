"""The optimiser's terms and the measures of one engine rendering share their work (once)."""

import sys
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


def test_transparency_reuses_what_its_kept_table_made(rendering, monkeypatch):
    import numpy as np

    from dvr_perception.measures import transparency
    from dvr_perception.measures.transparency import transparency_table

    module = sys.modules["dvr_perception.measures.transparency"]
    analysis, spec = rendering
    assert analysis.stats.get("params") is not None  # the rendering says its own parameters
    calls = []
    core = module._core
    monkeypatch.setattr(module, "_core", lambda *a: calls.append(1) or core(*a))
    fresh = transparency(analysis, spec)  # nothing kept yet: made, and not stored
    transparency(analysis, spec)
    assert len(calls) == 2
    region_id, deltas, _, _ = transparency_table(analysis, spec, keep=True)
    assert len(calls) == 3
    res = transparency(analysis, spec)
    assert len(calls) == 3
    assert np.array_equal(res.region_id, fresh.region_id)
    assert res.E_t == fresh.E_t
    assert np.array_equal(res.deviation, deltas[region_id].astype(np.float32))
    assert res.notes == fresh.notes
    assert transparency(analysis, spec).notes == res.notes  # the kept notes are not added to
    # the optimiser's result spec: other opacities, colours and materials, same rendering
    tuned = replace(spec, structures=tuple(replace(s, opacity=0.3, colour=(0.1, 0.2, 0.3))
                                           for s in spec.structures))  # fmt: skip
    assert transparency(analysis, tuned).E_t == res.E_t
    assert len(calls) == 3
    other = replace(spec, structures=(replace(spec.structures[0], importance=0.55),
                                      *spec.structures[1:]))  # fmt: skip
    transparency(analysis, other)  # another importance: made again
    transparency(analysis, replace(spec, background=(0.5, 0.5, 0.5)))  # another background
    transparency(analysis, spec, calibration=([0.0, 1.0], [0.0, 1.0]))  # a curve: not kept
    transparency(analysis, spec, threshold=0.1)  # another option
    assert len(calls) == 7
