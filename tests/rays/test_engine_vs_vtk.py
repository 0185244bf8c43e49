"""Our engine's image against vtkFixedPointVolumeRayCastMapper's (SSIM bounds of the brief)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.rays.vtk_reference import compare_images, render_vtk
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.volume.io import load_volume

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]

SSIM_MIN = {False: 0.97, True: 0.93}

# ranges from shared/data/MANIFEST.md
DATASETS = {
    "engine": (
        Structure("block", 0.3, (0.8, 0.6, 0.4), range=(90, 170)),
        Structure("insert", 0.9, (0.9, 0.9, 1.0), range=(190, 255)),
    ),
    "cthead": (
        Structure("skin", 0.15, (0.9, 0.7, 0.6), range=(300, 650)),
        Structure("bone", 0.8, (1.0, 1.0, 0.9), range=(1650, 2600)),
    ),
    "tooth": (
        Structure("dentin", 0.3, (0.9, 0.8, 0.6), range=(140, 185)),
        Structure("enamel", 0.9, (1.0, 1.0, 1.0), range=(195, 255)),
    ),
}


def _ssim(volume, spec, camera) -> float:
    ours = analyze(volume, spec, camera, build_cache=False)
    ref = render_vtk(volume, spec, camera, mapper="fixed_point")
    return compare_images(ours.image, ref.image)["ssim"]


@pytest.mark.parametrize("shade", [False, True])
@pytest.mark.parametrize(("azimuth", "elevation"), [(0, 0), (40, 30), (120, 0)])
def test_phantom_matches_vtk(vtk_can_render, shade, azimuth, elevation):
    vol, spec = make_phantom(size=64)
    spec = replace(spec, rendering=replace(spec.rendering, shade=shade))
    cam = Camera.from_view(vol.bounds, azimuth=azimuth, elevation=elevation, width=128, height=128)
    assert _ssim(vol, spec, cam) >= SSIM_MIN[shade]


@pytest.mark.shared_data
@pytest.mark.parametrize("shade", [False, True])
@pytest.mark.parametrize("name", sorted(DATASETS))
def test_shared_volumes_match_vtk(vtk_can_render, shared_data, name, shade):
    vol = load_volume(shared_data / f"{name}.nhdr")
    spec = StructureSpec(DATASETS[name], rendering=RenderSettings(shade=shade))
    for azimuth, elevation in ((0, 0), (40, 30)):
        cam = Camera.from_view(
            vol.bounds, azimuth=azimuth, elevation=elevation, width=256, height=256
        )
        ssim = _ssim(vol, spec, cam)
        assert ssim >= SSIM_MIN[shade], (name, azimuth, elevation, ssim)
