"""Tests for the calibration stimuli and their measured transmittance."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.calibration import Stimulus, calibration_stimuli, measured_transmittance
from dvr_perception.calibration.stimuli import BACKGROUNDS
from dvr_perception.errors import DVRInputError
from dvr_perception.measures import luminance

ALPHAS = (0.0, 0.1, 0.35, 0.5, 0.9, 1.0)


def test_count_order_and_metadata():
    stims = calibration_stimuli(transmittances=(0.2, 0.7), size=32)
    assert len(stims) == 2 * 2 * 2
    assert [(s.texture, s.background, s.transmittance) for s in stims[:3]] == [
        ("plain", "light", 0.2),
        ("plain", "light", 0.7),
        ("plain", "dark", 0.2),
    ]
    for s in stims:
        assert isinstance(s, Stimulus)
        assert s.image.shape == (32, 32, 3)
        assert s.image.dtype == np.float64
        assert s.image.min() >= 0.0
        assert s.image.max() <= 1.0
        assert s.layer_luminance == BACKGROUNDS[s.background][2]


def test_plain_pixels_follow_episcotister_model():
    s = calibration_stimuli(transmittances=(0.4,), backgrounds=("light",), textures=("plain",))[0]
    a, b, t = BACKGROUNDS["light"]
    y = luminance(s.image)
    m = s.masks
    np.testing.assert_allclose(y[m["A"]], a)
    np.testing.assert_allclose(y[m["B"]], b)
    np.testing.assert_allclose(y[m["P"]], 0.4 * a + 0.6 * t)
    np.testing.assert_allclose(y[m["Q"]], 0.4 * b + 0.6 * t)
    # the regions tile the image and the layer is the central half
    total = m["A"].astype(int) + m["B"] + m["P"] + m["Q"]
    assert np.all(total == 1)
    assert m["layer"].sum() == 64 * 64
    assert np.array_equal(m["layer"], m["P"] | m["Q"])


@pytest.mark.parametrize("texture", ["plain", "textured"])
@pytest.mark.parametrize("background", ["light", "dark"])
def test_measured_recovers_composited_alpha(texture, background):
    stims = calibration_stimuli(
        transmittances=ALPHAS, backgrounds=(background,), textures=(texture,), size=64, seed=3
    )
    got = [measured_transmittance(s) for s in stims]
    np.testing.assert_allclose(got, ALPHAS, atol=1e-12)


def test_textured_michelson_matches_closed_form():
    (s,) = calibration_stimuli(
        transmittances=(0.5,), backgrounds=("dark",), textures=("textured",), size=64
    )
    a, b, t = BACKGROUNDS["dark"]
    mu = (a + b) / 2  # balanced texture: half a, half b
    expected = 0.5 * mu / (0.5 * mu + 0.5 * t)
    assert measured_transmittance(s, contrast="michelson") == pytest.approx(expected, abs=1e-12)
    assert expected < 0.5  # a light layer lowers the Michelson transmittance


def test_texture_is_seeded_and_balanced():
    kw = {"transmittances": (0.5,), "backgrounds": ("light",), "textures": ("textured",)}
    s1 = calibration_stimuli(seed=7, **kw)[0]
    s2 = calibration_stimuli(seed=7, **kw)[0]
    s3 = calibration_stimuli(seed=8, **kw)[0]
    assert np.array_equal(s1.image, s2.image)
    assert not np.array_equal(s1.image, s3.image)
    a, b, _ = BACKGROUNDS["light"]
    outside = luminance(s1.image)[s1.masks["A"]]
    assert np.isclose(outside, a).sum() == np.isclose(outside, b).sum()


@pytest.mark.parametrize(
    ("kwargs", "word"),
    [
        ({"transmittances": (0.5, 1.2)}, "transmittances"),
        ({"transmittances": ()}, "transmittances"),
        ({"backgrounds": ("grey",)}, "backgrounds"),
        ({"textures": ("noise",)}, "textures"),
        ({"size": 20}, "size"),
        ({"size": 8}, "size"),
    ],
)
def test_bad_options(kwargs, word):
    with pytest.raises(DVRInputError, match=word):
        calibration_stimuli(**kwargs)


def test_measured_bad_input():
    with pytest.raises(DVRInputError, match="stimulus"):
        measured_transmittance(np.zeros((4, 4, 3)))
    s = calibration_stimuli(transmittances=(0.5,), size=16)[0]
    with pytest.raises(DVRInputError, match="contrast"):
        measured_transmittance(s, contrast="weber")
