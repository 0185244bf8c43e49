"""Tests for dvr_perception.measures.luminance."""

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.measures import composite_luminance, luminance


def test_luminance_primaries_and_white():
    img = np.array([[[1, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 1, 1]]], dtype=float)
    np.testing.assert_allclose(luminance(img), [[0.2126, 0.7152], [0.0722, 1.0]], atol=1e-12)


def test_luminance_is_linear():
    rng = np.random.default_rng(0)
    a, b = rng.random((5, 3)), rng.random((5, 3))
    np.testing.assert_allclose(
        luminance(0.3 * a + 0.7 * b), 0.3 * luminance(a) + 0.7 * luminance(b)
    )


def test_luminance_rejects_rgba_with_hint():
    with pytest.raises(DVRInputError, match=r"rgb.*3 channels.*composite_luminance"):
        luminance(np.zeros((2, 2, 4)))


def test_luminance_rejects_nan():
    with pytest.raises(DVRInputError, match="rgb"):
        luminance([0.1, np.nan, 0.2])


def test_composite_over_black_and_coloured_background():
    # premultiplied red at 40 % opacity
    px = np.array([0.4, 0.0, 0.0, 0.4])
    assert composite_luminance(px) == pytest.approx(0.4 * 0.2126)
    # over green: 0.4*0.2126 + 0.6*0.7152
    expected = 0.4 * 0.2126 + 0.6 * 0.7152
    assert composite_luminance(px, background=(0, 1, 0)) == pytest.approx(expected)


def test_composite_opaque_ignores_background_and_empty_shows_it():
    img = np.array([[[0.2, 0.5, 0.1, 1.0], [0.0, 0.0, 0.0, 0.0]]])
    out = composite_luminance(img, background=(1.0, 1.0, 1.0))
    assert out.shape == (1, 2)
    assert out[0, 0] == pytest.approx(luminance([0.2, 0.5, 0.1]))
    assert out[0, 1] == pytest.approx(1.0)


def test_composite_rejects_bad_alpha_and_background():
    with pytest.raises(DVRInputError, match=r"rgba_premultiplied.*\[0, 1\]"):
        composite_luminance([0.1, 0.1, 0.1, 1.5])
    with pytest.raises(DVRInputError, match="background"):
        composite_luminance([0.1, 0.1, 0.1, 0.5], background=(1.0, 1.0))
    with pytest.raises(DVRInputError, match="background"):
        composite_luminance([0.1, 0.1, 0.1, 0.5], background=(-1.0, 0.0, 0.0))


def test_composite_warns_when_not_premultiplied():
    with pytest.warns(DVRWarning, match="premultiplied"):
        composite_luminance([0.9, 0.9, 0.9, 0.2])
