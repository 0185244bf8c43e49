"""VTK-style shading: encoded normals, shading tables and re-evaluation after a change of light."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dvr_perception.rays import _grid
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume


def _case():
    z, y, x = np.mgrid[:30, :34, :38].astype(float)
    d = np.sqrt((x - 18) ** 2 + (y - 16) ** 2 + (z - 14) ** 2)
    vol = Volume(np.clip(230 - 11 * d, 0, 255).astype(np.uint8))
    spec = StructureSpec(
        (
            Structure("outer", 0.5, (1.0, 0.3, 0.1), range=(40, 120)),
            Structure("inner", 0.9, (0.1, 0.9, 0.3), range=(120, 235)),
        ),
        rendering=RenderSettings(shade=True),
    )
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=28, height=24)
    return vol, spec, cam


def _assert_same(a, b):
    for field in ("rgba", "image", "visible", "assigned", "present", "curvature"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-6, err_msg=field)


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_light_changes_back_and_forth_equal_fresh_analyses(backend):
    vol, spec, cam = _case()
    base = analyze(vol, spec, cam, backend=backend, build_cache=True)
    mats = [Lighting(0.2, 0.6, 0.5, 5.0), Lighting(0.3, 0.5, 0.4, 40.0)]
    for light, lighting, ops in (
        ((0.5, -0.4, 0.8), None, None),
        ((0.0, 0.0, 1.0), mats, [0.2, 0.4]),
        (None, None, [0.1, 0.3]),
        ((0.5, -0.4, 0.8), mats, None),
    ):
        rs = spec.rendering
        structs = spec.structures
        if lighting is not None:
            structs = tuple(replace(s, lighting=m) for s, m in zip(structs, mats, strict=True))
        fresh_spec = replace(
            spec,
            structures=structs,
            rendering=replace(rs, light_direction=light or rs.light_direction),
        )
        fresh = analyze(vol, fresh_spec, cam, opacities=ops, backend=backend, build_cache=True)
        again = reevaluate(base.cache, light_direction=light, lighting=lighting, opacities=ops)
        _assert_same(again, fresh)


def test_normal_codes_follow_vtk_spherical_encoding():
    x = np.arange(12, dtype=np.uint8)
    ramp_x = np.broadcast_to(x * 10, (6, 7, 12)).copy()  # value grows with x
    codes = _grid.normal_codes(Volume(ramp_x))
    # negative gradient along -x: theta = 180 deg, phi = 0
    assert codes[3, 3, 5] == int(180 * 255 / 359 + 0.5) + 256 * int(90 * 254 / 180 + 0.5)
    flat = _grid.normal_codes(Volume(np.full((4, 4, 4), 7, np.uint8)))
    assert np.all(flat == _grid.ZERO_CODE)
    d = _grid.code_directions()
    np.testing.assert_allclose(d[codes[3, 3, 5]], [-1, 0, 0], atol=0.02)
    assert not d[_grid.ZERO_CODE].any()
