"""``apply`` with a spec whose number of material groups differs from the one shown."""

from __future__ import annotations

import numpy as np

from dvr_perception.plotting import (
    add_structures,
    apply,
    material_groups,
    render_plotter,
    set_plotter_camera,
)
from dvr_perception.rays.vtk_reference import compare_images
from tests.plotting.conftest import with_materials


def _shot(pl) -> np.ndarray:
    pl.render()
    return np.asarray(pl.screenshot(return_img=True)[..., :3], np.float32) / 255.0


def test_apply_changes_number_of_material_groups(vtk_can_render, phantom):
    import pyvista as pv

    from dvr_perception import _vtk

    vol, spec4, cam = phantom
    specs = [with_materials(spec4, n) for n in (1, 2, 4, 3)]
    assert [len(material_groups(s)[0]) for s in specs] == [1, 2, 4, 3]
    _vtk.rendering()
    pl = pv.Plotter(off_screen=True, window_size=[cam.width, cam.height])
    shots = []
    try:
        handle = add_structures(pl, vol, specs[-1])  # start from another count than 1
        set_plotter_camera(pl, cam)
        _shot(pl)
        for spec in specs:
            apply(handle, spec)
            assert len(handle.groups) == len(material_groups(spec)[0])
            assert pl.renderer.GetVolumes().GetNumberOfItems() == 1
            shots.append(_shot(pl))
    finally:
        pl.close()
    for spec, shot in zip(specs, shots, strict=True):
        assert compare_images(shot, render_plotter(vol, spec, cam))["ssim"] >= 0.99
    assert compare_images(shots[0], shots[2])["mean_abs_diff"] > 1e-3  # materials differ
