"""Lazily computed cache entries and negative curvature input."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume


def _case():
    z, y, x = np.mgrid[:40, :36, :44].astype(float)
    d = np.sqrt((x - 20) ** 2 + (y - 18) ** 2 + (z - 21) ** 2)
    vol = Volume(np.clip(230 - 12 * d, 0, 255).astype(np.uint8))
    spec = StructureSpec(
        (
            Structure("outer", 0.9, (1.0, 0.2, 0.1), range=(40, 120)),
            Structure("inner", 0.95, (0.1, 0.9, 0.3), range=(120, 235)),
        ),
        rendering=RenderSettings(shade=True),
    )
    cam = Camera.from_view(vol.bounds, azimuth=40, elevation=25, width=30, height=26)
    curv = np.linspace(-1, 1, vol.data.size, dtype=np.float32).reshape(vol.data.shape)
    return vol, spec, cam, curv


def _assert_same(a, b):
    for field in ("rgba", "image", "visible", "assigned", "present", "curvature"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-6, err_msg=field)


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_deeper_reevaluations_equal_fresh_analyses(backend):
    # built with near-opaque structures: deeper entries are only reached (and their normals
    # computed) by later re-evaluations with lower opacities
    vol, spec, cam, curv = _case()
    base = analyze(vol, spec, cam, curvature=curv, backend=backend, build_cache=True)
    for ops in ([0.2, 0.95], [0.02, 0.1], [0.9, 0.0], [0.02, 0.1]):
        fresh = analyze(
            vol, spec, cam, opacities=ops, curvature=curv, backend=backend, build_cache=True
        )
        _assert_same(reevaluate(base.cache, opacities=ops), fresh)
    _assert_same(reevaluate(base.cache), base)


def test_negative_curvature_input_is_used_as_its_absolute_value():
    vol, spec, cam, curv = _case()
    a = analyze(vol, spec, cam, curvature=curv, backend="numba", build_cache=True)
    b = analyze(vol, spec, cam, curvature=np.abs(curv), backend="numba", build_cache=True)
    _assert_same(a, b)
    assert curv.min() < 0  # the caller's array is not modified


@pytest.mark.parametrize("light", [None, (0.4, -0.3, 1.0)])
def test_reevaluating_some_rays_equals_the_whole_image_there(light):
    # a fresh cache per call: the subset's rays fill their own shading and curvature
    vol, spec, cam, curv = _case()
    ops = [0.1, 0.7]
    fresh = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    whole = reevaluate(fresh, opacities=ops, light_direction=light)
    cache = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    mask = np.zeros((cam.height, cam.width), bool)
    mask[3:17, 5:21] = True
    mask[20, ::3] = True
    part = reevaluate(cache, opacities=ops, light_direction=light, rays=np.flatnonzero(mask))
    assert part.stats["partial"]
    assert part.stats["rays"] == mask.sum()
    for field in ("rgba", "image", "accumulated", "curvature"):
        a, b = np.asarray(getattr(part, field)), np.asarray(getattr(whole, field))
        assert np.array_equal(a[mask], b[mask]), field  # bit for bit
    assert np.array_equal(np.asarray(part.visible)[:, mask], np.asarray(whole.visible)[:, mask])
    assert not np.asarray(part.rgba)[~mask].any()  # nothing composited elsewhere
    bg = np.asarray(spec.background, np.float32)
    assert np.array_equal(np.asarray(part.image)[~mask], np.broadcast_to(bg, ((~mask).sum(), 3)))
    shuffled = np.flatnonzero(mask)[::-1].repeat(2)  # any order, repeats: the same rays
    again = reevaluate(cache, opacities=ops, light_direction=light, rays=shuffled)
    assert np.array_equal(np.asarray(again.rgba), np.asarray(part.rgba))
    # the whole image afterwards (entries partly filled by the subset) is unchanged
    again = reevaluate(cache, opacities=ops, light_direction=light)
    assert np.array_equal(np.asarray(again.rgba), np.asarray(whole.rgba))


def test_reevaluating_rays_outside_the_image_is_one_clear_error():
    vol, spec, cam, curv = _case()
    cache = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    with pytest.raises(DVRInputError, match="rays"):
        reevaluate(cache, rays=[0, cam.width * cam.height])


def test_a_change_of_specular_powers_alone_recomputes_only_those_structures(monkeypatch):
    from dvr_perception.rays import _numba_kernels as nk

    vol, spec, cam, curv = _case()
    mats = [Lighting(0.2, 0.7, 0.5, 10.0), Lighting(0.3, 0.6, 0.4, 40.0)]
    shiny = [mats[0], Lighting(0.3, 0.6, 0.4, 3.0)]  # the inner structure's power only
    cache = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    reevaluate(cache, lighting=mats, opacities=[0.3, 0.9])
    calls = []
    for name in ("invalidate", "invalidate_structures"):
        real = getattr(nk, name)
        monkeypatch.setattr(nk, name, lambda *a, _r=real, _n=name: calls.append(_n) or _r(*a))
    got = reevaluate(cache, lighting=shiny, opacities=[0.3, 0.9])
    assert calls == ["invalidate_structures"]
    other = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    fresh = reevaluate(other, lighting=shiny, opacities=[0.3, 0.9])
    for field in ("rgba", "image", "visible", "curvature"):
        assert np.array_equal(np.asarray(getattr(got, field)), np.asarray(getattr(fresh, field)))
    assert not np.array_equal(np.asarray(got.rgba), np.asarray(reevaluate(cache).rgba))
    reevaluate(cache, lighting=shiny, light_direction=(0.3, 0.2, 1.0))  # a new light: all
    assert calls[-1] == "invalidate"
