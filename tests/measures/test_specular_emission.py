"""A shaded engine rendering whose lit colour exceeds its opacity is not "straight alpha"."""

from __future__ import annotations

import warnings

import numpy as np

from dvr_perception.errors import DVRWarning
from dvr_perception.measures import shape, transparency
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume


def test_glossy_white_sphere_measures_without_a_premultiplied_warning():
    z, y, x = np.mgrid[:24, :24, :24].astype(float)
    d = np.sqrt((x - 11.5) ** 2 + (y - 11.5) ** 2 + (z - 11.5) ** 2)
    vol = Volume(np.clip(200 - 20 * np.maximum(d - 7, 0), 0, 255).astype(np.uint8))
    glossy = Lighting(ambient=0.5, diffuse=0.5, specular=1.0, specular_power=1.0)
    spec = StructureSpec(
        (Structure("ball", 0.3, (1.0, 1.0, 1.0), range=(100, 255), lighting=glossy),),
        rendering=RenderSettings(shade=True),
    )
    res = analyze(vol, spec, Camera.from_view(vol.bounds, width=32, height=32))
    rgba = res.rgba
    covered = rgba[..., 3] > 1e-5
    over = np.any(rgba[..., :3] > rgba[..., 3:] + 1e-5, axis=-1)
    assert over.sum() > 0.05 * covered.sum()  # would trip the straight-alpha heuristic
    with warnings.catch_warnings():
        warnings.simplefilter("error", DVRWarning)
        s_out = shape(res, spec)
        t_out = transparency(res, spec)
    assert np.isfinite(s_out.E_s)
    assert np.isfinite(t_out.E_t)
    assert any("more light than their opacity" in n for n in s_out.notes)
