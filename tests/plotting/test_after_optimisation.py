"""The PyVista display against our engine after optimising (opacity, lighting and colour).

The optimiser gives each structure its own lighting and colour; the display must still show
what our engine computes, before and after, on the phantom and on two shared datasets.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

from dvr_perception.errors import DVRWarning
from dvr_perception.optimize import optimize
from dvr_perception.plotting import material_groups, render_plotter
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.rays.vtk_reference import compare_images
from dvr_perception.structures import load_spec, make_phantom
from dvr_perception.volume import load_volume

STATE_FILES = Path(__file__).resolve().parents[2] / "state_files"
SSIM_MIN = 0.93

#: (case, image size, does the lighting stage move at max_iter=2, seed=0, coverage_keep,
#: optimisation resolution).  cthead runs with a user floor of 80 % of the starting coverage.
#: The engine optimises at its image size, 128 px: at 48 px its opacity step only half holds
#: at 128 px and the later stages are undone; at the default 96 px (with issue 32's E_s and
#: E_t) neither its lighting nor its colour stage finds a step in two iterations.
CASES = [
    pytest.param(("phantom", 96, True, None, 48), id="phantom"),
    pytest.param(("engine", 128, True, None, 128), id="engine", marks=pytest.mark.shared_data),
    pytest.param(("cthead", 128, True, 0.8, 48), id="cthead", marks=pytest.mark.shared_data),
]


def _camera(vol, spec, size: int) -> Camera:
    azimuth, elevation, zoom = spec.view or (0.0, 0.0, 1.0)
    return Camera.from_view(
        vol.bounds, azimuth=azimuth, elevation=elevation, zoom=zoom, width=size, height=size
    )


@pytest.fixture(scope="module", params=CASES)
def optimised(request, vtk_can_render):
    """``(name, volume, initial spec, optimised spec, camera, lighting_moves)``."""
    name, size, lighting_moves, keep, resolution = request.param
    if name == "phantom":
        vol, spec = make_phantom(size=48)
    else:
        data = request.getfixturevalue("shared_data")
        vol = load_volume(data / f"{name}.nhdr")
        spec = load_spec(STATE_FILES / f"{name}.json")
    cam = _camera(vol, spec, size)
    result = optimize(vol, spec, cam, max_iter=2, resolution=resolution, seed=0,
                      coverage_keep=keep)  # fmt: skip
    return name, vol, spec, result.spec, cam, lighting_moves


def _ssim(vol, spec, cam) -> float:
    # Beyond 4 distinct materials VTK merges the closest ones and says so.
    merged = material_groups(spec)[2]
    ctx = pytest.warns(DVRWarning, match="materials") if merged else contextlib.nullcontext()
    with ctx:
        image = render_plotter(vol, spec, cam)
    assert image.shape == (cam.height, cam.width, 3)
    ours = analyze(vol, spec, cam, build_cache=False).image
    return compare_images(image, ours)["ssim"]


def test_optimisation_changes_materials_per_structure(optimised):
    _, _, before, after, _, lighting_moves = optimised
    assert len(after.structures) == len(before.structures)
    colours = [
        a.colour != b.colour for a, b in zip(after.structures, before.structures, strict=True)
    ]
    assert sum(colours) >= 2  # the colour stage moved several structures
    lightings = {s.lighting for s in after.structures}
    changed = [
        a.lighting != b.lighting for a, b in zip(after.structures, before.structures, strict=True)
    ]
    if lighting_moves:
        assert any(changed)
        assert len(lightings) >= 2  # really per structure, not one shared material
        assert len(lightings) > len({s.lighting for s in before.structures})
        assert len(material_groups(after)[0]) >= 2  # and the display uses them
    else:
        assert not any(changed)  # documented above; update CASES if this starts to move


def test_display_matches_engine_before_optimisation(optimised):
    _, vol, before, _, cam, _ = optimised
    assert _ssim(vol, before, cam) >= SSIM_MIN


def test_display_matches_engine_after_optimisation(optimised):
    _, vol, _, after, cam, _ = optimised
    assert _ssim(vol, after, cam) >= SSIM_MIN
