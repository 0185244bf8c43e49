"""Tests for dvr_perception.measures.shape on hand-built ray analyses."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import ndimage

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import ShapeResult, shape
from dvr_perception.structures.spec import Structure, StructureSpec


def grey_analysis(grey, curvature, accumulated=None):
    grey = np.asarray(grey, float)
    acc = np.ones_like(grey) if accumulated is None else accumulated
    rgba = np.stack([grey * acc] * 3 + [acc], axis=-1)
    return SimpleNamespace(
        rgba=rgba,
        image=np.repeat(grey[..., None], 3, axis=-1),
        accumulated=acc,
        curvature=np.asarray(curvature, float),
        names=("s",),
    )


def test_a_log_luminance_ramp_over_a_uniformly_curved_structure_matches():
    """Constant Weber contrast (an exponential ramp) shows a constant curvature: v_i = v_s = 1
    away from the image border, where the deviation vanishes."""
    cc = np.mgrid[:9, :21][1]
    grey = 0.05 * np.exp(0.07 * cc) - 0.01  # log(Y + 0.01) rises linearly along the columns
    res = shape(grey_analysis(grey, np.full(grey.shape, 2.0)), percentile=99.0)
    assert isinstance(res, ShapeResult)
    np.testing.assert_allclose(res.v_s, 1.0)
    np.testing.assert_allclose(res.v_i[:, 2:-2], 1.0, atol=1e-6)
    np.testing.assert_allclose(res.deviation[:, 2:-2], 0.0, atol=1e-6)
    assert res.v_i[:, 0].max() < 1.0  # at the border the gradient is read one-sided
    assert res.E_s < 0.5


def test_the_image_variation_is_the_smoothed_log_luminance_gradient():
    """v_i by its definition (D9): |grad G_sigma log(Y + 0.01)| * sigma, normalised."""
    rng = np.random.default_rng(3)
    grey = ndimage.gaussian_filter(rng.random((30, 40)), 2.0)
    curvature = rng.random((30, 40))
    res = shape(grey_analysis(grey, curvature))
    sigma = max(40 / 48, 0.5)
    g = ndimage.gaussian_gradient_magnitude(np.log(grey + 0.01), sigma, mode="nearest")
    np.testing.assert_allclose(res.v_i, np.clip(g / (3 * g.mean()), 0, 1), atol=1e-5)
    c = ndimage.gaussian_filter(curvature, sigma, mode="nearest")
    np.testing.assert_allclose(res.v_s, np.clip(c / (3 * c.mean()), 0, 1), atol=1e-5)
    p99 = shape(grey_analysis(grey, curvature), percentile=99.0)  # the robust maximum instead
    np.testing.assert_allclose(p99.v_i, np.clip(g / np.percentile(g, 99), 0, 1), atol=1e-5)


def test_flat_image_over_curved_structure_is_maximal():
    res = shape(grey_analysis(np.full((5, 5), 0.5), np.full((5, 5), 2.0)), percentile=99.0)
    assert not res.v_i.any()
    np.testing.assert_allclose(res.v_s, 1.0)
    assert res.E_s == pytest.approx(1.0 - np.exp(-1.0 / 0.05))


def test_constant_volume_and_flat_image_is_zero():
    res = shape(grey_analysis(np.full((4, 6), 0.3), np.zeros((4, 6))))
    assert res.E_s == 0.0
    assert not res.deviation.any()


def test_steepness_sets_the_cost_of_a_difference():
    # curvature normalised to 1 everywhere; image gradient 0 -> difference 1
    ana = grey_analysis(np.full((3, 3), 0.5), np.ones((3, 3)))
    assert shape(ana, steepness=1.0, percentile=99.0).E_s == pytest.approx(1.0 - np.exp(-1.0))
    # by default a uniform field is scaled to 1/3 (3 x its mean is 1)
    assert shape(ana, steepness=1.0).E_s == pytest.approx(1.0 - np.exp(-1.0 / 9.0))
    with pytest.raises(DVRInputError, match="steepness"):
        shape(ana, steepness=0.0)
    with pytest.raises(DVRInputError, match="percentile"):
        shape(ana, percentile=0.0)


def test_robust_maximum_ignores_an_outlier():
    curvature = np.ones((60, 60))
    curvature[0, 0] = 1000.0  # one spike among 3600 pixels: smoothed, still above the 99th pct
    res = shape(grey_analysis(np.full((60, 60), 0.5), curvature), percentile=99.0)
    np.testing.assert_allclose(res.v_s[10:, 10:], 1.0, atol=1e-6)
    res = shape(grey_analysis(np.full((60, 60), 0.5), curvature), percentile=100.0)
    assert res.v_s[30, 30] < 0.01


def test_only_nonempty_pixels_count():
    acc = np.zeros((4, 4))
    acc[:, :2] = 1.0
    curvature = np.zeros((4, 4))
    curvature[:, 2:] = 5.0  # curvature on empty rays is ignored
    res = shape(grey_analysis(np.zeros((4, 4)), curvature, accumulated=acc))
    np.testing.assert_array_equal(res.nonempty, acc > 0)
    assert res.E_s == 0.0
    assert not res.deviation[:, 2:].any()


def test_empty_image_gives_zero_with_note():
    res = shape(grey_analysis(np.zeros((3, 3)), np.zeros((3, 3)), accumulated=np.zeros((3, 3))))
    assert res.E_s == 0.0
    assert any("E_s = 0" in n for n in res.notes)


def test_background_enters_the_luminance():
    acc = np.zeros((6, 6))
    acc[:, :3] = 1.0
    ana = grey_analysis(np.full((6, 6), 0.5), np.zeros((6, 6)), accumulated=acc)
    black = StructureSpec(
        structures=(Structure(name="s", importance=1.0, colour=(0.5, 0.5, 0.5), range=(0, 1)),)
    )
    grey = StructureSpec(structures=black.structures, background=(0.5, 0.5, 0.5))
    assert shape(ana, black, percentile=99.0).v_i.max() == pytest.approx(1.0)  # silhouette edge
    assert not shape(ana, grey).v_i.any()  # the structure matches the background


def test_negative_curvature_is_rejected():
    with pytest.raises(DVRInputError, match="curvature"):
        shape(grey_analysis(np.zeros((2, 2)), -np.ones((2, 2))))
    with pytest.raises(DVRInputError, match="curvature"):
        shape(grey_analysis(np.zeros((2, 2)), np.ones((3, 2))))
