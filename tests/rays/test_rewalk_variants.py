"""Walks of a few rays, several opacity sets at once (DECISIONS D7 without a cache).

The view without an enclosing layer is walked again on the pixels it covers.  A few rays are
set up alone (``segments_at``) and all the enclosers' views are walked together
(:func:`~dvr_perception.rays.engine.rewalk_rgba`, the ``walk_variants`` kernel): each must be
what :func:`~dvr_perception.rays.engine.rewalk` gives for that layer, to the bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import transparency
from dvr_perception.measures.covered import _without, _without_many
from dvr_perception.rays import _grid, engine
from dvr_perception.rays._walk_setup import _numba_kernels
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, rewalk, rewalk_rgba
from dvr_perception.structures.phantom import make_phantom


def _rewalked(analysis, ops, rays) -> np.ndarray:
    """:func:`rewalk`'s rgba on ``rays`` (sorted, unique), one variant at a time."""
    return rewalk(analysis, opacities=ops, rays=rays).rgba.reshape(-1, 4)[np.unique(rays)]


@pytest.mark.parametrize("parallel", [False, True])
def test_segments_of_a_few_rays_are_the_whole_images_rows(parallel):
    nk = _numba_kernels()
    vol, _ = make_phantom(size=20)
    cam = Camera.from_view(vol.bounds, width=23, height=17, azimuth=35, elevation=-20)
    if parallel:
        cam = Camera(cam.position, cam.focal_point, cam.view_up, parallel_projection=True,
                     parallel_scale=14.0, width=23, height=17)  # fmt: skip
    pack = _grid.camera_pack(cam, vol, 0.7)
    n = cam.width * cam.height
    whole = {"a": np.empty((n, 3)), "b": np.empty((n, 3)), "t": np.empty(n),
             "n": np.empty(n, np.int32)}  # fmt: skip
    nk.segments(pack, whole["a"], whole["b"], whole["t"], whole["n"])
    rays = np.array([0, 1, 22, 23, 200, 201, 390, n - 1], np.int64)
    part = {"a": np.empty((8, 3)), "b": np.empty((8, 3)), "t": np.empty(8),
            "n": np.empty(8, np.int32)}  # fmt: skip
    nk.segments_at(pack, rays, part["a"], part["b"], part["t"], part["n"])
    for q in ("a", "b", "t", "n"):
        assert np.array_equal(part[q], whole[q][rays]), q
    assert whole["n"][rays].any()  # rays in and out of the box
    assert not whole["n"][rays].all()


@pytest.mark.parametrize("shade", [False, True])
def test_every_variant_equals_its_own_rewalk_to_the_bit(shade, shell_scene):
    vol, spec = shell_scene(shade, inner=6.5)
    cam = Camera.from_view(vol.bounds, width=36, height=30, azimuth=25, elevation=15)
    res = analyze(vol, spec, cam)
    n = cam.width * cam.height
    hit = np.flatnonzero(res.accumulated.ravel() > 0)
    rng = np.random.default_rng(3)
    variants = [
        ([0.0, 1.0, 1.0], rng.choice(n, 400)),  # the shell left out: what it covers
        ([0.3, 0.0, 1.0], rng.choice(n, 250)),
        ([0.3, 1.0, 1.0], np.arange(n)),  # as rendered: the analysis's own image
        ([0.0, 0.0, 0.0], hit[:2]),  # nothing to see
        ([0.3, 0.4, 0.0], hit[len(hit) // 2 :][:1]),
    ]
    got = rewalk_rgba(res, variants)
    assert len(got) == len(variants)
    for (ops, rays), rgba in zip(variants, got, strict=True):
        assert rgba.dtype == np.float32
        assert rgba.shape == (len(np.unique(rays)), 4)
        assert np.array_equal(rgba, _rewalked(res, ops, rays))
    assert np.array_equal(got[2], res.rgba.reshape(-1, 4))
    assert not got[3].any()
    assert got[0][:, 3].any()
    assert got[1][:, 3].any()


def test_intensity_structures_each_left_out_in_turn():
    vol, spec = make_phantom(size=32)
    cam = Camera.from_view(vol.bounds, width=40, height=40, azimuth=-30)
    res = analyze(vol, spec, cam)
    base = [s.render_opacity for s in spec.structures]
    variants = []
    for e in range(len(spec.structures)):
        ops = list(base)
        ops[e] = 0.0
        variants.append((ops, np.arange(e, 1600, e + 2)))
    got = rewalk_rgba(res, variants)
    for (ops, rays), rgba in zip(variants, got, strict=True):
        assert np.array_equal(rgba, _rewalked(res, ops, rays))
    # leaving a structure out changes what is seen somewhere (else the test shows nothing)
    whole = res.rgba.reshape(-1, 4)
    assert any(
        not np.array_equal(rgba, whole[r]) for (_, r), rgba in zip(variants, got, strict=True)
    )


def test_numpy_and_bricked_analyses_walk_each_variant_alone():
    vol, spec = make_phantom(size=64)
    cam = Camera.from_view(vol.bounds, width=16, height=16, azimuth=30.0)
    base = [s.render_opacity for s in spec.structures]
    variants = [([0.0, *base[1:]], np.arange(0, 256, 3)), (base, [17, 18, 100])]
    want = rewalk_rgba(analyze(vol, spec, cam), variants)
    for made in (analyze(vol, spec, cam, backend="numpy"),
                 analyze(vol, spec, cam, memory_limit="2M")):  # fmt: skip
        got = rewalk_rgba(made, variants)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    assert analyze(vol, spec, cam, memory_limit="2M").stats["bricks"] >= 1


def test_bad_variants_name_the_parameter():
    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    res = analyze(vol, spec, cam)
    ok = [s.render_opacity for s in spec.structures]
    with pytest.raises(DVRInputError, match="rays"):
        rewalk_rgba(res, [(ok, [64])])
    with pytest.raises(DVRInputError, match="opacities"):
        rewalk_rgba(res, [([2.0] * len(ok), [3])])
    with pytest.raises(DVRInputError, match="analysis"):
        rewalk_rgba(analyze(vol, spec, cam, build_cache=True), [(ok, [3])])
    assert rewalk_rgba(res, []) == []


def _many_and_one_at_a_time(shell_scene, build_cache):
    """Scene, masks and ``_without_many``'s luminances, checked against one layer at a time."""
    vol, spec = shell_scene(True, inner=6.5)
    cam = Camera.from_view(vol.bounds, width=32, height=28, azimuth=10)
    res = analyze(vol, spec, cam, build_cache=build_cache)
    rng = np.random.default_rng(5)
    masks = {e: rng.random((cam.height, cam.width)) < 0.4 for e in range(3)}
    many = _without_many(res, spec, masks)
    for e, mask in masks.items():
        assert np.array_equal(many[e][mask], _without(res, spec, e, mask)[mask])
        assert not many[e][~mask].any()
    return vol, spec, cam, masks, many


def test_many_layers_luminance_equals_one_layer_at_a_time(shell_scene):
    _many_and_one_at_a_time(shell_scene, False)


def test_transparency_walks_all_its_enclosers_once(monkeypatch):
    vol, spec = make_phantom(size=32)
    cam = Camera.from_view(vol.bounds, width=48, height=48)
    calls = []
    original = engine.rewalk_rgba

    def counting(analysis, variants):
        calls.append(len(variants))
        return original(analysis, variants)

    monkeypatch.setattr(engine, "rewalk_rgba", counting)
    plain = transparency(analyze(vol, spec, cam), spec)
    cached = transparency(analyze(vol, spec, cam, build_cache=True), spec)
    assert len(calls) == 1  # the phantom's nested shells: one walk for all
    assert calls[0] >= 2
    assert plain.E_t == pytest.approx(cached.E_t, abs=1e-6)


def test_the_walks_without_layers_are_recorded_per_analysis():
    from dvr_perception.rays.engine import recomposites, rewalk_rgba

    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    res = analyze(vol, spec, cam)
    assert recomposites(res) == []
    ops = [s.render_opacity for s in spec.structures]
    rewalk_rgba(res, [(ops, [28, 27]), ([0.0, *ops[1:]], [27])])
    (rec,) = recomposites(res)
    assert (rec["layers"], rec["rays"], rec["bytes"]) == (2, 3, 3 * 4 * 4)
    assert rec["seconds"] > 0
    assert recomposites(analyze(vol, spec, cam)) == []  # another analysis: its own record


@pytest.mark.parametrize("shade", [False, True])
def test_cached_variants_equal_their_own_reevaluation_to_the_bit(shade, shell_scene):
    from dvr_perception.rays.engine import reevaluate, reevaluate_rgba
    from dvr_perception.structures.spec import Lighting

    vol, spec = shell_scene(shade, inner=6.5)
    cam = Camera.from_view(vol.bounds, width=34, height=26, azimuth=25, elevation=15)
    cache = analyze(vol, spec, cam, build_cache=True).cache
    n = cam.width * cam.height
    rng = np.random.default_rng(7)
    mats = [Lighting(0.2, 0.7, 0.5, 30.0), Lighting(0.1, 0.9, 0.2, 8.0), Lighting()]
    look = {"colours": [(1.0, 0.2, 0.1), (0.1, 0.8, 0.3), (0.9, 0.9, 0.2)], "lighting": mats,
            "light_direction": (0.3, 0.2, 1.0)}  # fmt: skip
    variants = [([0.0, 1.0, 1.0], rng.choice(n, 300)), ([0.3, 0.0, 0.8], rng.choice(n, 200)),
                ([0.3, 1.0, 1.0], np.arange(n)), ([0.0, 0.0, 0.0], [5])]  # fmt: skip
    reevaluate(cache, opacities=[0.5, 0.5, 0.5])  # another light set up last: shaded again
    got = reevaluate_rgba(cache, variants, **look)
    for (ops, rays), rgba in zip(variants, got, strict=True):
        want = reevaluate(cache, opacities=ops, rays=rays, **look).rgba.reshape(-1, 4)
        assert rgba.dtype == np.float32
        assert np.array_equal(rgba, want[np.unique(rays)])
    assert np.array_equal(
        got[2], reevaluate(cache, opacities=[0.3, 1.0, 1.0], **look).rgba.reshape(-1, 4)
    )
    assert not got[3].any()
    assert not np.array_equal(got[0][:, :3], got[2][np.unique(variants[0][1]), :3])
    with pytest.raises(DVRInputError, match="cache"):
        reevaluate_rgba(analyze(vol, spec, cam), variants)
    with pytest.raises(DVRInputError, match="rays"):
        reevaluate_rgba(cache, [([0.3, 1.0, 1.0], [n])])


def test_cached_many_layers_luminance_equals_one_layer_at_a_time(shell_scene):
    vol, spec, cam, masks, many = _many_and_one_at_a_time(shell_scene, True)
    walked = _without_many(analyze(vol, spec, cam), spec, masks)  # no cache: walked again
    for e in masks:
        np.testing.assert_allclose(many[e], walked[e], rtol=0, atol=1e-6)
