"""Label structures in the PyVista display: VTK's label-map mask against our engine."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from dvr_perception.errors import DVRWarning
from dvr_perception.plotting import add_structures, apply, render_plotter, set_plotter_camera
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.rays.vtk_reference import compare_images
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume

#: Unshaded, VTK's label-map path agrees with the engine as its fixed-point mapper does
#: (0.967 here); shaded 0.948 (the GPU mapper's lighting is not quite the fixed-point mapper's
#: that the engine reproduces; see dvr_perception/plotting/_structure_volume.py).
SSIM_MIN = {False: 0.95, True: 0.93}


def _scene(*, shade: bool):
    """A 24^3 intensity ramp along x with a labelled box (label 4) in its dark, empty half."""
    x = np.mgrid[:24, :24, :24][2]
    data = (60 + 8 * x).astype(np.uint8)
    labels = np.zeros(data.shape, np.uint8)
    labels[6:16, 7:17, 2:10] = 4
    vol = Volume(data, labels=labels)
    spec = StructureSpec(
        (
            Structure("ramp", 0.4, (1, 1, 1), range=(150, 250)),
            Structure("cube", 0.9, (1, 0, 0), label=4),
        ),
        background=(0, 0, 0),
        rendering=RenderSettings(shade=shade),
    )
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, zoom=1.3, width=64, height=64)
    return vol, spec, cam


def _red(img):
    return (img[..., 0] > 0.3) & (img[..., 0] > 2 * img[..., 1] + 0.1)


@pytest.mark.parametrize("shade", [False, True])
def test_label_structure_matches_engine(vtk_can_render, shade):
    vol, spec, cam = _scene(shade=shade)
    ours = analyze(vol, spec, cam).image
    vtk = render_plotter(vol, spec, cam)
    ssim = compare_images(ours, vtk)["ssim"]
    print(f"label cube, shade={shade}: SSIM {ssim:.3f}")
    assert ssim >= SSIM_MIN[shade]
    # the cube's red is where the engine puts it: its data values (76..132) lie below the
    # ramp's range, so without the label there is no red at all
    red_ours, red_vtk = _red(ours), _red(vtk)
    assert red_ours.sum() > 30
    assert red_vtk.sum() > 30
    centre_ours, centre_vtk = np.argwhere(red_ours).mean(0), np.argwhere(red_vtk).mean(0)
    assert np.abs(centre_ours - centre_vtk).max() < 1.5, (centre_ours, centre_vtk)
    redness = [(im[..., 0] - im[..., 1]).ravel() for im in (ours, vtk)]
    assert np.corrcoef(*redness)[0, 1] > 0.9
    # no grey wash over the label's colour (the GPU mapper's uncoloured ambient term)
    cube = red_ours & red_vtk
    assert vtk[cube][:, 1].mean() < 0.1 * vtk[cube][:, 0].mean() + 0.02
    without = replace(spec, structures=spec.structures[:1])
    assert _red(render_plotter(vol, without, cam)).sum() == 0


def test_apply_changes_label_opacity_and_back_to_ranges(vtk_can_render):
    import pyvista as pv

    vol, spec, cam = _scene(shade=False)
    pl = pv.Plotter(off_screen=True, window_size=[cam.width, cam.height])
    try:
        handle = add_structures(pl, vol, spec)
        set_plotter_camera(pl, cam)
        assert handle.labelled
        shown = np.asarray(pl.screenshot(return_img=True)[..., :3], np.float32) / 255
        assert _red(shown).sum() > 30
        apply(handle, spec, opacities=[0.4, 0.0])  # the cube invisible: no red left
        hidden = np.asarray(pl.screenshot(return_img=True)[..., :3], np.float32) / 255
        assert _red(hidden).sum() == 0
        assert hidden.mean() > 0.02  # the ramp is still there
        mats = replace(
            spec,
            rendering=RenderSettings(shade=True),
            structures=(spec.structures[0], replace(spec.structures[1], lighting=Lighting(0.5))),
        )
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            apply(handle, mats)
        assert any(
            issubclass(w.category, DVRWarning) and "one material" in str(w.message) for w in caught
        )
    finally:
        pl.close()
