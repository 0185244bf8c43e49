"""D7 without a cache: the view without an enclosing layer is walked again, the same E_t.

An enclosing layer's transparency is read against what it covers re-composited without it.
An analysis with the re-evaluation cache re-composites it from the cache; one without
(``analyze``'s default) walks the affected rays again with that layer's opacity 0
(:func:`~dvr_perception.rays.engine.rewalk`).  Both must give the same luminance and the same
``E_t`` (DECISIONS D7: "E_t never depends on how it was computed").
"""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import all_measures, transparency
from dvr_perception.measures.covered import covered_transmittance
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, can_rewalk, reevaluate, rewalk
from dvr_perception.structures.phantom import make_phantom

TERMS = ("E_v", "E_s", "E_t")


@pytest.mark.parametrize("shade", [False, True])
def test_e_t_is_the_same_with_and_without_the_cache(shade, shell_scene):
    vol, spec = shell_scene(shade)
    cam = Camera.from_view(vol.bounds, width=40, height=36)
    cached = analyze(vol, spec, cam, build_cache=True)
    plain = analyze(vol, spec, cam)  # the default: no cache
    assert cached.cache is not None
    assert plain.cache is None
    with_cache = transparency(cached, spec)
    without = transparency(plain, spec)
    assert with_cache.E_t == pytest.approx(without.E_t, abs=1e-6)
    # the encloser was read against the re-composite (else the test shows nothing): that
    # reading differs from the paper's plain one here
    assert not any("plain view" in n for n in without.notes), without.notes
    assert abs(transparency(plain, spec, enclosure="plain").E_t - without.E_t) > 1e-3
    for a, b in zip(all_measures(cached, spec), all_measures(plain, spec), strict=True):
        for term in TERMS:
            if hasattr(a, term):
                assert getattr(a, term) == pytest.approx(getattr(b, term), abs=1e-6), term


def test_the_phantom_reads_the_same_e_t_without_the_cache():
    vol, spec = make_phantom(size=32)
    cam = Camera.from_view(vol.bounds, width=48, height=48)
    a = transparency(analyze(vol, spec, cam, build_cache=True), spec)
    b = transparency(analyze(vol, spec, cam), spec)
    assert a.E_t == pytest.approx(b.E_t, abs=1e-6)
    assert b.E_t != pytest.approx(
        transparency(analyze(vol, spec, cam), spec, enclosure="plain").E_t, abs=1e-3
    )


def test_covered_transmittance_works_without_the_cache(shell_scene):
    vol, spec = shell_scene(False)
    cam = Camera.from_view(vol.bounds, width=32, height=32)
    a = covered_transmittance(analyze(vol, spec, cam, build_cache=True), spec, "shell")
    b = covered_transmittance(analyze(vol, spec, cam), spec, "shell")
    assert a.pixels == b.pixels > 0
    assert a.alpha == pytest.approx(b.alpha, abs=1e-9)


def test_rewalk_equals_the_cache_re_composite_on_its_rays(shell_scene):
    vol, spec = shell_scene(True)
    cam = Camera.from_view(vol.bounds, width=20, height=18)
    cached = analyze(vol, spec, cam, build_cache=True)
    plain = analyze(vol, spec, cam)
    ops = [0.0, 0.6, 0.9]
    rays = np.array([5, 100, 181, 190, 250, 359])
    a = reevaluate(cached.cache, opacities=ops, rays=rays)
    b = rewalk(plain, opacities=ops, rays=rays)
    pix = np.unravel_index(rays, (cam.height, cam.width))
    assert np.abs(a.image[pix] - b.image[pix]).max() <= 1e-6
    assert np.abs(a.accumulated[pix] - b.accumulated[pix]).max() <= 1e-6
    # the other rays are not walked: the background, nothing accumulated
    others = np.ones(cam.height * cam.width, bool)
    others[rays] = False
    assert not b.accumulated.ravel()[others].any()
    bg = np.asarray(spec.background, np.float32)
    assert np.allclose(b.image.reshape(-1, 3)[others], np.clip(bg, 0, 1))


def test_analyze_rays_equals_the_whole_image_on_those_rays():
    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=16, height=12)
    whole = analyze(vol, spec, cam)
    rays = np.arange(3, 190, 7)
    part = analyze(vol, spec, cam, rays=rays)
    for name in ("image", "accumulated", "curvature"):
        assert np.array_equal(getattr(part, name).reshape(-1, *getattr(part, name).shape[2:])
                              [rays], getattr(whole, name).reshape(
                                  -1, *getattr(whole, name).shape[2:])[rays]), name  # fmt: skip
    assert np.array_equal(part.visible.reshape(len(spec.structures), -1)[:, rays],
                          whole.visible.reshape(len(spec.structures), -1)[:, rays])  # fmt: skip
    assert part.stats["rays_hit"] < whole.stats["rays_hit"]


def test_analyze_rays_bricked_equals_whole():
    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=12, height=12)
    rays = np.arange(0, 144, 5)
    whole = analyze(vol, spec, cam, rays=rays, occlusion_free=False)
    bricked = analyze(vol, spec, cam, rays=rays, occlusion_free=False, brick=(7, 9, 11))
    assert bricked.stats.get("bricks", 0) > 1
    assert np.array_equal(whole.image, bricked.image)


@pytest.mark.parametrize("rays", [[-1], [10_000], [1.5], "all"])
def test_bad_rays_name_the_parameter(rays):
    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    with pytest.raises(DVRInputError, match="rays"):
        analyze(vol, spec, cam, rays=rays)


def test_rewalk_needs_an_engine_analysis_without_cache():
    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    cached = analyze(vol, spec, cam, build_cache=True)
    assert not can_rewalk(cached)
    assert can_rewalk(analyze(vol, spec, cam))
    with pytest.raises(DVRInputError, match="analysis"):
        rewalk(cached, opacities=[0.5] * len(spec.structures))


@pytest.mark.parametrize("shade", [False, True])
def test_a_few_rays_walked_alone_equal_the_whole_image_there(shade, shell_scene):
    """Image-only walks of a subset (the re-walk's path) are the whole image's to the bit."""
    vol, spec = shell_scene(shade)
    cam = Camera.from_view(vol.bounds, width=30, height=26, azimuth=20, elevation=10)
    whole = analyze(vol, spec, cam, occlusion_free=False)
    rays = np.array([0, 31, 200, 201, 202, 390, 399, 500, 779])
    part = analyze(vol, spec, cam, occlusion_free=False, rays=rays[::-1])  # any order
    flat = {n: getattr(part, n).reshape(-1, *getattr(part, n).shape[2:]) for n in
            ("rgba", "image", "accumulated", "curvature", "present")}  # fmt: skip
    for name, got in flat.items():
        want = getattr(whole, name).reshape(-1, *getattr(whole, name).shape[2:])
        assert np.array_equal(got[rays], want[rays]), name
    others = np.setdiff1d(np.arange(cam.width * cam.height), rays)
    assert not flat["accumulated"][others].any()
    k = len(spec.structures)
    assert np.array_equal(
        part.visible.reshape(k, -1)[:, rays], whole.visible.reshape(k, -1)[:, rays]
    )
    assert whole.accumulated.reshape(-1)[rays].any()  # rays that see something
