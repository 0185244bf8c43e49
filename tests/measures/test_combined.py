"""all_measures: the three measures together, in a worker thread or in turn, agree exactly."""

import dataclasses

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import all_measures, shape, transparency, visibility
from dvr_perception.rays import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.phantom import make_phantom


def _scene():
    vol, spec = make_phantom(size=40)  # five nested structures, shaded
    cam = Camera.from_view(vol.bounds, width=56, height=48, azimuth=30.0, elevation=20.0)
    return vol, spec, cam


def _equal(x, y):
    if isinstance(x, np.ndarray):
        return isinstance(y, np.ndarray) and np.array_equal(x, y)
    if isinstance(x, dict):
        return x.keys() == y.keys() and all(_equal(x[k], y[k]) for k in x)
    if isinstance(x, (list, tuple)):
        return len(x) == len(y) and all(_equal(p, q) for p, q in zip(x, y, strict=True))
    return x == y


def _same(a, b):
    for f in dataclasses.fields(a):
        if f.name != "records":
            assert _equal(getattr(a, f.name), getattr(b, f.name)), f.name


@pytest.mark.parametrize(
    ("parallel", "calibration"), [(True, None), (False, None), (True, ([0, 0.5, 1], [0, 0.3, 1]))]
)
def test_all_measures_equal_the_three_measures_in_turn(parallel, calibration):
    vol, spec, cam = _scene()
    alone = analyze(vol, spec, cam, build_cache=False)
    together = analyze(vol, spec, cam, build_cache=False)  # a fresh analysis: nothing remembered
    want = (
        visibility(alone, spec),
        shape(alone, spec),
        transparency(alone, spec, calibration=calibration),
    )
    got = all_measures(together, spec, calibration=calibration, parallel=parallel)
    for g, w in zip(got, want, strict=True):
        _same(g, w)
    assert got.transparency.regions == want[2].regions
    assert 0.0 < got.visibility.E_v <= 2.0
    assert len(got.transparency.regions) > 1


def test_all_measures_raise_the_measures_errors():
    vol, spec, cam = _scene()
    a = analyze(vol, spec, cam, build_cache=False)
    other = dataclasses.replace(spec, structures=spec.structures[::-1])  # names in another order
    with pytest.raises(DVRInputError, match=r"do not match analysis\.names"):
        all_measures(a, other)
    render_only = analyze(vol, spec, cam, build_cache=False, occlusion_free=False)
    with pytest.raises(DVRInputError, match="assigned must be finite"):
        all_measures(render_only, spec)


def test_an_engine_analysis_measures_the_same_without_numba(monkeypatch):
    """The kernels read the engine's float32 fields as they are; numpy reads float64 copies."""
    vol, spec, cam = _scene()
    one, other = (analyze(vol, spec, cam, build_cache=False) for _ in range(2))
    assert one.visible.dtype == np.float32
    fast = all_measures(one, spec)
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    slow = all_measures(other, spec)
    for g, w in zip(fast, slow, strict=True):
        for f in dataclasses.fields(g):
            if f.name in ("records", "per_structure", "E_v"):
                continue  # the kernel's image-wide sums run in chunks: equal to rounding
            assert _equal(getattr(g, f.name), getattr(w, f.name)), f.name
    assert fast.visibility.E_v == pytest.approx(slow.visibility.E_v, rel=1e-12)
    assert fast.transparency.regions == slow.transparency.regions
    assert fast.transparency.per_structure == slow.transparency.per_structure
    assert len(fast.transparency.regions) > 1
