"""The PyVista display against our engine: per-structure lighting, apply, cameras, errors."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.plotting import (
    add_structures,
    apply,
    before_after,
    camera_from_plotter,
    material_groups,
    render_plotter,
    set_plotter_camera,
)
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.rays.vtk_reference import compare_images
from dvr_perception.structures.io import load_spec
from dvr_perception.structures.spec import Lighting, Structure, StructureSpec
from dvr_perception.volume.io import load_volume
from tests.plotting.conftest import with_materials

STATE_FILES = __import__("pathlib").Path(__file__).resolve().parents[2] / "state_files"
SSIM_MIN = 0.93


def _plotter(camera):
    import pyvista as pv

    from dvr_perception import _vtk

    _vtk.rendering()
    return pv.Plotter(off_screen=True, window_size=[camera.width, camera.height])


def _shot(pl) -> np.ndarray:
    pl.render()
    return np.asarray(pl.screenshot(return_img=True)[..., :3], np.float32) / 255.0


def test_phantom_per_structure_lighting_matches_engine(vtk_can_render, phantom):
    vol, spec, cam = phantom
    assert len(material_groups(spec)[0]) == 4  # four different materials really in use
    image = render_plotter(vol, spec, cam)
    assert image.shape == (96, 96, 3)
    ours = analyze(vol, spec, cam, build_cache=False).image
    assert compare_images(image, ours)["ssim"] >= SSIM_MIN


@pytest.mark.shared_data
@pytest.mark.parametrize("name", ["engine", "cthead"])
def test_shared_volume_per_structure_lighting_matches_engine(vtk_can_render, shared_data, name):
    vol = load_volume(shared_data / f"{name}.nhdr")
    spec = with_materials(load_spec(STATE_FILES / f"{name}.json"), 4)
    assert len(material_groups(spec)[0]) == len(spec.structures)  # one material each
    cam = Camera.from_view(vol.bounds, azimuth=40, elevation=30, width=256, height=256)
    image = render_plotter(vol, spec, cam)
    ours = analyze(vol, spec, cam, build_cache=False).image
    assert compare_images(image, ours)["ssim"] >= SSIM_MIN


def test_specular_power_changes_only_that_structure(vtk_can_render, phantom):
    vol, spec, cam = phantom
    k = 3  # tumour: alone in its material group
    assert [g for g in material_groups(spec)[0] if k in g] == [(k,)]
    lt = spec.structures[k].lighting
    changed = list(spec.structures)
    changed[k] = replace(changed[k], lighting=replace(lt, specular=1.0, specular_power=2.0))
    spec_b = replace(spec, structures=tuple(changed))
    spec_a = replace(
        spec,
        structures=tuple(
            replace(s, lighting=replace(lt, specular=1.0)) if i == k else s
            for i, s in enumerate(spec.structures)
        ),
    )
    pl = _plotter(cam)
    try:
        handle = add_structures(pl, vol, spec_a)
        set_plotter_camera(pl, cam)
        before = _shot(pl)
        apply(handle, spec_b)  # in place: same actor
        assert pl.renderer.GetVolumes().GetNumberOfItems() == 1
        after = _shot(pl)
    finally:
        pl.close()
    diff = np.abs(after - before).max(axis=-1)
    visible = analyze(vol, spec_a, cam, build_cache=False).visible[k]
    mask = visible > 0.05
    assert mask.sum() > 50
    assert diff[mask].max() > 0.1  # the tumour's highlights really changed
    assert diff[~mask].max() < 0.05  # at most the tumour's faint fringe (visible <= 0.05)
    near = ndimage.binary_dilation(visible > 0)  # 1 pixel of slack for VTK's ray positions
    assert int((diff[~near] > 2.5 / 255).sum()) == 0  # no other structure's pixels changed
    # apply gives the same picture as a fresh plotter with the new spec
    assert compare_images(after, render_plotter(vol, spec_b, cam))["mean_abs_diff"] < 1e-3


def test_apply_accepts_result_and_opacities(vtk_can_render, phantom):
    vol, spec, cam = phantom
    pl = _plotter(cam)
    try:
        add_structures(pl, vol, spec)
        set_plotter_camera(pl, cam)
        first = _shot(pl)
        result = type("Result", (), {"spec": spec.with_opacities([0.0] * 6)})()
        handle = apply(pl, result)
        assert handle.spec.structures[0].opacity == 0.0
        empty = _shot(pl)
        apply(pl, spec, opacities=[s.render_opacity for s in spec.structures])
        again = _shot(pl)
    finally:
        pl.close()
    assert np.abs(empty - np.asarray(spec.background, np.float32)).max() < 1e-6
    assert np.abs(again - first).max() < 1e-6


def test_more_materials_than_components_fall_back_with_warning(vtk_can_render, phantom):
    vol, spec4, cam = phantom
    spec = with_materials(spec4, 6)
    groups, lightings, merged = material_groups(spec)
    assert merged
    assert len(groups) == 4
    import pyvista as pv

    pl = pv.Plotter(off_screen=True)
    try:
        with pytest.warns(DVRWarning, match="share a material"):
            handle = add_structures(pl, vol, spec)
        prop = handle.actor.GetProperty()
        for c, group in enumerate(handle.groups):  # colour and opacity stay per structure
            for k in group:
                s = spec.structures[k]
                mid = 0.5 * sum(s.range)
                color = prop.GetRGBTransferFunction(c).GetColor(mid)
                assert np.allclose(color, s.colour, atol=1e-6)
                assert prop.GetScalarOpacity(c).GetValue(mid) == pytest.approx(s.render_opacity)
            assert prop.GetSpecularPower(c) == lightings[c].specular_power
    finally:
        pl.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DVRWarning)
        image = render_plotter(vol, spec, cam)
    ours = analyze(vol, spec, cam, build_cache=False).image
    assert compare_images(image, ours)["ssim"] >= SSIM_MIN


def test_unshaded_spec_uses_one_component():
    spec = StructureSpec(
        (
            Structure("a", 0.5, (1, 0, 0), range=(0, 10), lighting=Lighting(specular=0.9)),
            Structure("b", 0.5, (0, 1, 0), range=(10, 20)),
        )
    )
    assert len(material_groups(spec)[0]) == 2
    unshaded = replace(spec, rendering=replace(spec.rendering, shade=False))
    assert material_groups(unshaded)[0] == ((0, 1),)


def test_bad_input_errors(phantom):
    import pyvista as pv

    vol, spec, _ = phantom
    pl = pv.Plotter(off_screen=True)
    try:
        labelled = replace(spec, structures=(Structure("x", 0.5, (1, 0, 0), label=1),))
        with pytest.raises(DVRInputError, match=r"volume\.labels: the spec has label structures"):
            add_structures(pl, replace(vol, labels=None), labelled)
        with pytest.raises(DVRInputError, match="opacities: expected 6"):
            add_structures(pl, vol, spec, opacities=[0.5])
        with pytest.raises(DVRInputError, match=r"plotter: expected a pyvista\.Plotter"):
            add_structures(object(), vol, spec)
        with pytest.raises(DVRInputError, match="plotter_or_handle"):
            apply(pl, spec)  # nothing added yet
        handle = add_structures(pl, vol, spec)
        fewer = replace(spec, structures=spec.structures[:2])
        with pytest.raises(DVRInputError, match="result_or_spec: the spec has 2 structures"):
            apply(handle, fewer)
        renamed = replace(
            spec, structures=tuple(replace(s, name=f"other {s.name}") for s in spec.structures)
        )
        with pytest.raises(DVRInputError, match="result_or_spec: its structures"):
            apply(handle, renamed)  # e.g. an optimisation result for another volume
        with pytest.raises(DVRInputError, match="result_or_spec: expected a StructureSpec"):
            apply(handle, 42)
        add_structures(pl, vol, spec, name="second")
        with pytest.raises(DVRInputError, match="name: the plotter holds several"):
            apply(pl, spec)
        with pytest.raises(DVRInputError, match="name: no structure volume 'third'"):
            apply(pl, spec, name="third")
    finally:
        pl.close()


@pytest.mark.parametrize("parallel", [False, True])
def test_camera_round_trip_is_exact(parallel):
    import pyvista as pv

    cam = Camera.from_view((0, 40, 0, 30, 0, 20), azimuth=33, elevation=-21, width=70, height=50)
    cam = replace(cam, parallel_projection=parallel, parallel_scale=12.5, view_angle=22.0)
    pl, pl2 = pv.Plotter(off_screen=True), pv.Plotter(off_screen=True)
    try:
        set_plotter_camera(pl, cam)
        back = camera_from_plotter(pl)
        assert back == cam
        set_plotter_camera(pl2, back)
        assert camera_from_plotter(pl2) == cam
        assert tuple(pl.window_size) == (70, 50)
    finally:
        pl.close()
        pl2.close()


def test_before_after_halves_match_single_views(vtk_can_render, phantom):
    vol, spec, cam = phantom
    after = spec.with_opacities([0.05, 0.05, 0.05, 0.9, 0.9, 0.9])
    both = before_after(vol, spec, after, cam)
    assert both.shape == (96, 192, 3)
    left, right = both[:, :96], both[:, 96:]
    assert compare_images(left, render_plotter(vol, spec, cam))["mean_abs_diff"] < 2e-3
    assert compare_images(right, render_plotter(vol, after, cam))["mean_abs_diff"] < 2e-3
    assert compare_images(left, right)["mean_abs_diff"] > 0.01
