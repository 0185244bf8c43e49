"""Known answers, re-evaluation and input checking of the ray-analysis engine."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.measures import visibility
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume


def _spec(*structures, shade=False, **render):
    return StructureSpec(tuple(structures), rendering=RenderSettings(shade=shade, **render))


def _top_camera(vol: Volume, size: int = 12, scale: float = 0.3) -> Camera:
    """Parallel camera looking down -z; every ray enters through the top (high-z) face."""
    cx, cy, cz = vol.center
    extent = min(vol.bounds[1] - vol.bounds[0], vol.bounds[3] - vol.bounds[2])
    return Camera(
        position=(cx, cy, cz + 100.0),
        focal_point=(cx, cy, cz),
        parallel_projection=True,
        parallel_scale=scale * extent,
        width=size,
        height=size,
    )


def _two_slabs() -> Volume:
    data = np.full((24, 16, 16), 100, np.uint8)
    data[12:] = 220  # front slab (the camera looks down -z)
    return Volume(data)


def _blob(dtype=np.uint8, scale=1.0) -> Volume:
    z, y, x = np.mgrid[:18, :20, :22].astype(float)
    d = np.sqrt((x - 11) ** 2 + (y - 10) ** 2 + (z - 9) ** 2)
    data = np.clip(220 - 18 * d, 0, 255)
    return Volume((data * scale).astype(dtype))


BLOB_STRUCTURES = (
    Structure("outer", 0.3, (1.0, 0.2, 0.1), range=(40, 120)),
    Structure("inner", 0.8, (0.1, 0.9, 0.3), range=(120, 230)),
)


def test_opaque_front_slab_hides_everything_behind_it():
    vol = _two_slabs()
    front = Structure("front", 1.0, (1, 1, 1), range=(180, 255), edge=0.0)
    back = Structure("back", 0.5, (1, 0, 0), range=(50, 150), edge=0.0)
    res = analyze(vol, _spec(back, front), _top_camera(vol), build_cache=True)
    assert np.allclose(res.accumulated, 1.0)
    assert np.allclose(res.visible[1], res.accumulated)
    assert np.all(res.visible_share[0] == 0.0)
    # the hidden slab is still on every ray and has assigned opacity
    assert np.all(res.present & 1)
    assert np.all(res.assigned[0] > 1.0)
    assert np.allclose(res.image, 1.0)


def test_single_structure_has_full_visible_and_assigned_share():
    vol = _two_slabs()
    only = Structure("front", 0.4, (0, 1, 0), range=(180, 255))
    res = analyze(vol, _spec(only), _top_camera(vol), build_cache=True)
    assert np.all(res.present == 1)
    assert np.allclose(res.visible_share[0], 1.0)
    assert np.allclose(res.assigned_share[0], 1.0)


@pytest.mark.parametrize("sample_distance", [1.0, 0.5])
def test_homogeneous_slab_follows_the_opacity_law(sample_distance):
    data = np.full((21, 10, 10), 100, np.uint8)  # box of voxel centres: 20 units thick
    vol = Volume(data)
    o = 0.1
    spec = _spec(
        Structure("slab", o, (1, 1, 1), range=(50, 150), edge=0.0),
        sample_distance=sample_distance,
        opacity_unit_distance=1.0,
    )
    res = analyze(vol, spec, _top_camera(vol, size=8), build_cache=True)
    length = 20.0
    expect = 1 - (1 - o) ** length
    one_step = o * (1 - o) ** (length - 1) * sample_distance  # one sample more or less
    assert np.all(np.abs(res.accumulated - expect) <= one_step + 1e-3)
    assert np.allclose(res.visible[0], res.accumulated)


def test_camera_that_sees_nothing_warns_and_returns_background():
    vol = _blob()
    spec = replace(_spec(*BLOB_STRUCTURES), background=(0.2, 0.3, 0.4))
    cam = Camera(position=(500, 500, 500), focal_point=(1000, 1000, 1000), width=9, height=7)
    with pytest.warns(DVRWarning, match="sees none"):
        res = analyze(vol, spec, cam, build_cache=True)
    assert res.image.shape == (7, 9, 3)
    assert np.allclose(res.image, (0.2, 0.3, 0.4))
    assert not res.accumulated.any()
    assert not res.present.any()
    assert not res.assigned.any()
    again = reevaluate(res.cache, opacities=[1.0, 1.0])
    assert not again.accumulated.any()


def _shaded_case():
    vol = _blob()
    spec = _spec(*BLOB_STRUCTURES, shade=True)
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=24, height=20)
    curv = np.linspace(0, 1, vol.data.size, dtype=np.float32).reshape(vol.data.shape)
    return vol, spec, cam, curv


def _assert_same(a, b):
    for field in ("rgba", "image", "visible", "assigned", "present", "curvature"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-6, err_msg=field)


def test_reevaluate_opacities_equals_fresh_analysis():
    vol, spec, cam, curv = _shaded_case()
    base = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    new = [0.9, 0.05]
    _assert_same(
        reevaluate(base.cache, opacities=new),
        analyze(vol, spec, cam, opacities=new, curvature=curv, build_cache=True),
    )
    assert not np.allclose(base.rgba, reevaluate(base.cache, opacities=new).rgba)


def test_reevaluate_colours_lighting_light_and_background():
    vol, spec, cam, _ = _shaded_case()
    base = analyze(vol, spec, cam, build_cache=True)
    cols = [(0.0, 0.0, 1.0), (1.0, 1.0, 0.0)]
    mats = [Lighting(0.5, 0.4, 0.6, 8.0), Lighting(0.1, 0.9, 0.0, 30.0)]
    new_structs = tuple(
        replace(s, colour=c, lighting=m)
        for s, c, m in zip(spec.structures, cols, mats, strict=True)
    )
    light = (0.6, 0.3, 0.7)
    fresh_spec = replace(
        spec,
        structures=new_structs,
        background=(0.1, 0.2, 0.3),
        rendering=replace(spec.rendering, light_direction=light),
    )
    fresh = analyze(vol, fresh_spec, cam, build_cache=True)
    again = reevaluate(
        base.cache, colours=cols, lighting=mats, light_direction=light, background=(0.1, 0.2, 0.3)
    )
    _assert_same(again, fresh)
    assert np.abs(again.image - base.image).max() > 0.1


def test_numba_and_numpy_backends_agree():
    pytest.importorskip("numba")
    vol, spec, cam, curv = _shaded_case()
    a = analyze(vol, spec, cam, curvature=curv, backend="numba", build_cache=True)
    b = analyze(vol, spec, cam, curvature=curv, backend="numpy", build_cache=True)
    c = analyze(vol, spec, cam, curvature=curv, backend="numba", build_cache=False, exact=True)
    _assert_same(a, b)
    _assert_same(a, c)
    # without the cache the walk behind termination skips by default: assigned stops at 1.0
    for backend in ("numba", "numpy"):
        d = analyze(vol, spec, cam, curvature=curv, backend=backend, build_cache=False)
        assert d.stats["assigned_cap"] == 1.0
        assert c.stats["assigned_cap"] is None
        np.testing.assert_array_equal(d.assigned, np.minimum(c.assigned, 1.0))
        for field in ("rgba", "image", "visible", "present", "curvature",
                      "importance_accumulated"):  # fmt: skip
            np.testing.assert_array_equal(getattr(d, field), getattr(c, field), err_msg=field)
    assert a.stats["backend"] == "numba"
    assert b.stats["backend"] == "numpy"
    assert c.cache is None
    assert a.cache.nbytes > 0
    assert a.accumulated.max() > 0.5
    assert a.curvature.max() > 0


def test_env_variable_forces_numpy(monkeypatch):
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    vol = _blob()
    res = analyze(vol, _spec(*BLOB_STRUCTURES), _top_camera(vol, size=6), build_cache=True)
    assert res.stats["backend"] == "numpy"
    with pytest.raises(DVRInputError, match="backend"):
        analyze(
            vol,
            _spec(*BLOB_STRUCTURES),
            _top_camera(vol, size=6),
            backend="numba",
            build_cache=True,
        )


def test_assigned_and_present_do_not_depend_on_opacities():
    vol, spec, cam, _ = _shaded_case()
    a = analyze(vol, spec, cam, opacities=[1.0, 1.0], build_cache=True)
    b = analyze(vol, spec, cam, opacities=[0.0, 0.2], build_cache=True)
    np.testing.assert_array_equal(a.assigned, b.assigned)
    np.testing.assert_array_equal(a.present, b.present)
    assert np.all(b.visible[0] == 0.0)  # zero opacity: never visible
    # visible sums to accumulated; assigned comes from importance
    np.testing.assert_allclose(a.visible.sum(0), a.accumulated, atol=1e-5)


def test_constant_curvature_is_reported_where_visible():
    vol = _blob()
    curv = np.full(vol.data.shape, 0.25, np.float32)
    res = analyze(vol, _spec(*BLOB_STRUCTURES), _top_camera(vol), curvature=curv, build_cache=True)
    seen = res.accumulated > 0
    assert seen.any()
    np.testing.assert_allclose(res.curvature[seen], 0.25, rtol=1e-6)
    assert np.all(res.curvature[~seen] == 0)


@pytest.mark.parametrize(
    ("dtype", "scale"), [(np.uint8, 1.0), (np.uint16, 10.0), (np.float32, 0.01)]
)
def test_volume_dtypes_render_alike(dtype, scale):
    ref = analyze(
        _blob(), _spec(*BLOB_STRUCTURES), _top_camera(_blob(), scale=0.45), build_cache=True
    )
    vol = _blob(dtype, scale)
    structs = tuple(
        replace(s, range=(s.range[0] * scale, s.range[1] * scale)) for s in BLOB_STRUCTURES
    )
    res = analyze(vol, _spec(*structs), _top_camera(vol, scale=0.45), build_cache=True)
    assert res.accumulated.max() > 0.5
    np.testing.assert_allclose(res.accumulated, ref.accumulated, atol=0.03)


def test_bad_inputs_raise_one_clear_error():
    vol = _blob()
    cam = _top_camera(vol, size=4)
    with pytest.raises(DVRInputError, match="structures"):
        analyze(vol, StructureSpec(()), cam, build_cache=True)
    spec = _spec(*BLOB_STRUCTURES)
    for bad in ([0.5], [0.5, 1.5], [0.5, float("nan")], "x"):
        with pytest.raises(DVRInputError, match="opacities"):
            analyze(vol, spec, cam, opacities=bad, build_cache=True)
    with pytest.raises(DVRInputError, match="curvature"):
        analyze(vol, spec, cam, curvature=np.zeros((2, 2, 2)), build_cache=True)
    with pytest.raises(DVRInputError, match="backend"):
        analyze(vol, spec, cam, backend="cuda", build_cache=True)
    with pytest.raises(DVRInputError, match="volume"):
        analyze(vol.data, spec, cam, build_cache=True)
    cache = analyze(vol, spec, cam, build_cache=True).cache
    with pytest.raises(DVRInputError, match="opacities"):
        reevaluate(cache, opacities=[0.1, 0.2, 0.3])
    with pytest.raises(DVRInputError, match="colours"):
        reevaluate(cache, colours=[(2, 0, 0), (0, 0, 0)])
    with pytest.raises(DVRInputError, match="light_direction"):
        reevaluate(cache, light_direction=(0, 0, 0))
    with pytest.raises(DVRInputError, match="lighting"):
        reevaluate(cache, lighting=[Lighting()])
    with pytest.raises(DVRInputError, match="cache"):
        reevaluate(None)


def test_no_warning_for_normal_render():
    vol = _blob()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = analyze(vol, _spec(*BLOB_STRUCTURES), _top_camera(vol, size=6), build_cache=True)
    assert res.stats["samples"] > 0
    assert res.names == ("outer", "inner")


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_render_only_stops_at_early_termination_and_leaves_assigned_undefined(backend):
    """``occlusion_free=False``: the same image, no occlusion-free shares, fewer samples."""
    if backend == "numba":
        pytest.importorskip("numba")
    vol = _two_slabs()
    front = Structure("front", 1.0, (1, 1, 1), range=(180, 255), edge=0.0)
    back = Structure("back", 0.5, (1, 0, 0), range=(50, 150), edge=0.0)
    spec, cam = _spec(back, front, shade=True), _top_camera(vol)
    full = analyze(vol, spec, cam, backend=backend, build_cache=False, exact=True)
    image = analyze(vol, spec, cam, backend=backend, build_cache=False, occlusion_free=False)
    for field in ("rgba", "image", "accumulated", "visible", "curvature"):
        np.testing.assert_array_equal(getattr(image, field), getattr(full, field), err_msg=field)
    assert np.all(np.isnan(image.assigned))
    assert np.all(full.assigned[0] > 1.0)  # the hidden slab: only the full walk reaches it
    assert full.stats["occlusion_free"] is True
    assert image.stats["occlusion_free"] is False
    if backend == "numba":  # the opaque front slab ends every ray: the back one is never met
        assert image.stats["samples_walked"] < full.stats["samples_walked"] / 2
        assert not np.any(image.present & 1)
    with pytest.raises(DVRInputError, match="assigned must be finite"):
        visibility(image, spec)
    with pytest.raises(DVRInputError, match="build_cache=False"):
        analyze(vol, spec, cam, backend=backend, occlusion_free=False, build_cache=True)


def test_importance_accumulated_is_the_rendering_at_the_importances():
    """``A_imp`` (D1): the accumulated opacity with every opacity at its importance, whatever
    the opacities rendered; the same in both back ends, kept by re-evaluation, NaN when the
    rays stop at early termination."""
    vol = _blob()
    spec = _spec(*BLOB_STRUCTURES)
    cam = Camera.from_view(vol.bounds, azimuth=20, elevation=10, width=24, height=20)
    at_importance = analyze(vol, spec, cam, build_cache=True)
    np.testing.assert_array_equal(at_importance.importance_accumulated, at_importance.accumulated)
    faded = analyze(vol, spec, cam, opacities=[0.05, 0.1], build_cache=True)
    assert faded.accumulated.max() < at_importance.accumulated.max() - 0.1
    np.testing.assert_array_equal(faded.importance_accumulated, at_importance.accumulated)
    numpy = analyze(vol, spec, cam, opacities=[0.05, 0.1], backend="numpy", build_cache=True)
    np.testing.assert_allclose(numpy.importance_accumulated, faded.importance_accumulated,
                               atol=1e-6)  # fmt: skip
    again = reevaluate(faded.cache, opacities=[0.9, 0.2])
    np.testing.assert_array_equal(again.importance_accumulated, at_importance.accumulated)
    with pytest.raises(ValueError, match="read-only"):
        faded.importance_accumulated[0, 0] = 0
    render_only = analyze(vol, spec, cam, occlusion_free=False, build_cache=False)
    assert np.isnan(render_only.importance_accumulated).all()
