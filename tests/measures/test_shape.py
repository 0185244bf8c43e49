"""Tests for dvr_perception.measures.shape on hand-built ray analyses."""

import importlib
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


def _shape_on_the_whole_image(analysis, steepness=0.05, percentile=None):
    """The measure as written before it worked on the filters' window: scipy, whole images."""
    mod = importlib.import_module("dvr_perception.measures.shape")
    acc = np.asarray(analysis.accumulated, float)
    y = np.clip(np.asarray(analysis.image, float) @ np.array([0.2126, 0.7152, 0.0722]), 0, 1)
    nonempty = acc > mod.NONEMPTY_OPACITY
    sigma = mod.image_scale(acc.shape)
    curv = np.asarray(analysis.curvature, float)
    curv = np.where(curv < mod.CURVATURE_FLOOR, 0.0, curv)
    log_y = np.log(y + mod.DARK_LUMINANCE)
    weight = nonempty.astype(float)
    num = ndimage.gaussian_filter(curv * weight, sigma, mode="nearest")
    den = ndimage.gaussian_filter(weight, sigma, mode="nearest")
    smooth = np.divide(num, den, out=np.zeros_like(num), where=nonempty & (den > 0))
    smooth[smooth < mod.CURVATURE_FLOOR] = 0.0
    grad = ndimage.gaussian_gradient_magnitude(log_y, sigma, mode="nearest") * sigma
    grad[grad < mod.GRADIENT_FLOOR] = 0.0

    def normalise(v):
        if not nonempty.any():
            return np.zeros_like(v)
        if percentile is None:
            scale = mod.MEAN_FACTOR * float(v[nonempty].mean())
        else:
            scale = float(np.percentile(v[nonempty], percentile))
        return np.zeros_like(v) if scale <= 0 else np.clip(v / scale, 0.0, 1.0)

    v_s, v_i = normalise(smooth), normalise(grad)
    delta = np.where(nonempty, -np.expm1(-((v_s - v_i) ** 2) / steepness), 0.0)
    e_s = float(delta[nonempty].mean()) if nonempty.any() else 0.0
    return e_s, delta.astype(np.float32), v_s.astype(np.float32), v_i.astype(np.float32)


@pytest.mark.parametrize("percentile", [None, 95.0])
@pytest.mark.parametrize(
    "box", [(20, 50, 30, 70), (0, 12, 0, 15), (40, 64, 60, 96), (0, 64, 0, 96), None]
)
def test_shape_read_on_the_filters_window_equals_the_whole_image(box, percentile):
    """Only the window around the rendering is worked on: the same bits as the whole image."""
    rng = np.random.default_rng(11)
    acc = np.zeros((64, 96))
    grey = np.full((64, 96), 0.3)  # a uniform background
    if box is not None:
        y0, y1, x0, x1 = box
        acc[y0:y1, x0:x1] = rng.random((y1 - y0, x1 - x0))
        grey[y0:y1, x0:x1] = rng.random((y1 - y0, x1 - x0))
    scene = SimpleNamespace(accumulated=acc, curvature=rng.random((64, 96)) * 0.2,
                            image=np.repeat(grey[..., None], 3, axis=-1))  # fmt: skip
    got = shape(scene, percentile=percentile)
    e_s, delta, v_s, v_i = _shape_on_the_whole_image(scene, percentile=percentile)
    assert got.E_s == e_s
    np.testing.assert_array_equal(got.deviation, delta)
    np.testing.assert_array_equal(got.v_s, v_s)
    np.testing.assert_array_equal(got.v_i, v_i)
    for image in (got.deviation, got.v_s, got.v_i):
        assert image.dtype == np.float32
        assert image.shape == (64, 96)
    if box is not None:
        assert 0.0 < got.E_s < 1.0
