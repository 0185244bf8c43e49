"""Quality-map overlay and the matplotlib charts."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import visibility
from dvr_perception.plotting import (
    add_quality_map,
    add_structures,
    plot_convergence,
    plot_visibility_histograms,
    set_plotter_camera,
)
from dvr_perception.plotting.overlay import colourize
from dvr_perception.rays.engine import analyze


def test_quality_map_overlays_only_defined_pixels(vtk_can_render, phantom):
    import pyvista as pv

    from dvr_perception import _vtk

    vol, spec, cam = phantom
    _vtk.rendering()
    measure = np.full((cam.height, cam.width), np.nan)
    measure[:, : cam.width // 2] = 1.0  # left half defined, right half not
    pl = pv.Plotter(off_screen=True, window_size=[cam.width, cam.height])
    try:
        add_structures(pl, vol, spec)
        set_plotter_camera(pl, cam)
        plain = np.asarray(pl.screenshot(return_img=True), np.float32) / 255
        ov = add_quality_map(pl, measure, title="delta_v", clim=(0.0, 2.0))
        ov.scalar_bar.SetVisibility(0)  # compare the image overlay alone
        pl.render()
        shown = np.asarray(pl.screenshot(return_img=True), np.float32) / 255
        assert ov.scalar_bar.GetTitle() == "delta_v"
        assert pl.renderer.HasViewProp(ov.image_actor)
        assert pl.renderer.HasViewProp(ov.scalar_bar)
    finally:
        pl.close()
    half = cam.width // 2
    assert np.abs(shown[:, half + 1 :] - plain[:, half + 1 :]).max() < 1e-6
    expected = colourize(measure, clim=(0.0, 2.0))[0, 0, :3] / 255.0
    blend = 0.6 * expected + 0.4 * plain[:, :half]
    assert np.abs(shown[:, :half] - blend).max() < 0.02


def test_quality_map_errors():
    import pyvista as pv

    pl = pv.Plotter(off_screen=True)
    try:
        with pytest.raises(DVRInputError, match="measure_image"):
            add_quality_map(pl, np.zeros(5), title="x")
        with pytest.raises(DVRInputError, match="clim"):
            add_quality_map(pl, np.zeros((4, 4)), title="x", clim=(1, 0))
        with pytest.raises(DVRInputError, match="cmap"):
            add_quality_map(pl, np.zeros((4, 4)), title="x", cmap="no-such-map")
    finally:
        pl.close()


def test_visibility_histograms_one_axes_per_structure(phantom):
    vol, spec, cam = phantom
    vis = visibility(analyze(vol, spec, cam.with_size(48, 48), build_cache=False), spec)
    fig = plot_visibility_histograms(vis)
    assert len(fig.axes) == len(spec.structures)
    assert [ax.get_title() for ax in fig.axes] == list(spec.names)
    with pytest.raises(DVRInputError, match="vis_result"):
        plot_visibility_histograms(object())


def test_convergence_from_stage_records():
    class Stage:
        def __init__(self, name, values):
            self.name = name
            self.history = tuple(
                {"E": v, "E_v": v / 2, "iteration": i} for i, v in enumerate(values)
            )

    result = type("Result", (), {"stages": (Stage("opacity", [3, 2]), Stage("light", [1.5]))})()
    fig = plot_convergence(result)
    lines = {line.get_label(): line for line in fig.axes[0].get_lines()}
    assert list(lines["E"].get_ydata()) == [3.0, 2.0, 1.5]
    assert list(lines["E_v"].get_ydata()) == [1.5, 1.0, 0.75]
    with pytest.raises(DVRInputError, match="history"):
        plot_convergence([])
    with pytest.raises(DVRInputError, match="history"):
        plot_convergence([1, 2])


def test_colorize_old_spelling_warns_and_still_works():
    from dvr_perception.plotting import overlay

    img = np.array([[0.0, np.nan], [0.5, 1.0]])
    with pytest.warns(DeprecationWarning, match=r"colorize is deprecated; use .*colourize"):
        old = overlay.colorize(img, clim=(0, 1))
    np.testing.assert_array_equal(old, colourize(img, clim=(0, 1)))
