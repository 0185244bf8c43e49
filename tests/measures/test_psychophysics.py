"""Tests for dvr_perception.measures.psychophysics (Eq. 5-9, calibration)."""

import itertools

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import (
    blended_transmittance,
    calibrate,
    generalized_metelli,
    luminance_range,
    metelli_transmittance,
    tap_transmittance,
)


def over(alpha, t, behind):
    """Over-compositing of a layer (transmittance alpha, luminance t) on a luminance."""
    return alpha * behind + (1 - alpha) * t


def composite(layers, subset, background):
    """Luminance where exactly ``subset`` of ``layers`` (front to back) is present."""
    lum = background
    for k in reversed(range(len(layers))):
        if k in subset:
            lum = over(*layers[k], lum)
    return lum


# -- Metelli, Eq. 5 -------------------------------------------------------------------------
def test_metelli_recovers_alpha_arrays():
    rng = np.random.default_rng(0)
    alpha, t = rng.random(50), rng.random(50)
    a, b = rng.uniform(0.6, 1.0, 50), rng.uniform(0.0, 0.4, 50)
    got = metelli_transmittance(over(alpha, t, a), over(alpha, t, b), a, b)
    np.testing.assert_allclose(got, alpha, atol=1e-9)


def test_metelli_scalar_and_undetermined():
    got = metelli_transmittance(0.62, 0.26, 0.8, 0.2)
    assert isinstance(got, float)
    assert got == pytest.approx(0.6)
    out = metelli_transmittance([0.5, 0.62], [0.4, 0.26], [0.3, 0.8], [0.3, 0.2])
    assert np.isnan(out[0])
    assert out[1] == pytest.approx(0.6)


def test_metelli_rejects_bad_input():
    with pytest.raises(DVRInputError, match=r"^q "):
        metelli_transmittance(0.5, np.inf, 0.3, 0.1)
    with pytest.raises(DVRInputError, match="broadcastable"):
        metelli_transmittance([0.1, 0.2], [0.1, 0.2, 0.3], 0.5, 0.1)


# -- generalised Metelli, Eq. 9 ---------------------------------------------------------------
BG = 0.1


def test_generalized_metelli_common_luminance_any_order():
    alphas = (0.3, 0.5, 0.7)
    for order in itertools.permutations(range(3)):
        layers = [(alphas[k], 0.8) for k in order]  # front to back, same t
        everyone = {0, 1, 2}
        for i in range(3):
            got = generalized_metelli(
                composite(layers, everyone, BG),
                composite(layers, {i}, BG),
                composite(layers, everyone - {i}, BG),
                BG,
            )
            assert got == pytest.approx(layers[i][0], abs=1e-9)


def test_generalized_metelli_front_layer_exact_with_distinct_luminances():
    layers = [(0.3, 0.9), (0.5, 0.2), (0.7, 0.6)]  # front to back
    everyone = {0, 1, 2}
    i_all = composite(layers, everyone, BG)
    front = generalized_metelli(
        i_all, composite(layers, {0}, BG), composite(layers, {1, 2}, BG), BG
    )
    assert front == pytest.approx(0.3, abs=1e-9)
    # middle layer: the front layer acts as the medium (documented substitution)
    middle = generalized_metelli(
        i_all,
        composite(layers, {0, 1}, BG),
        composite(layers, {0, 2}, BG),
        composite(layers, {0}, BG),
    )
    assert middle == pytest.approx(0.5, abs=1e-9)
    # the plain Eq. 9 is only an approximation for a back layer with distinct luminances
    back = generalized_metelli(i_all, composite(layers, {2}, BG), composite(layers, {0, 1}, BG), BG)
    assert abs(back - 0.7) > 0.05


def test_generalized_metelli_undetermined():
    assert np.isnan(generalized_metelli(0.5, 0.4, 0.3, 0.3))


# -- TAP, Eq. 6 and 7 -------------------------------------------------------------------------
def test_luminance_range_known_values():
    lo, hi = luminance_range([0.4, 0.6])
    assert (lo, hi) == pytest.approx((0.3, 0.7))
    assert luminance_range([0.0, 1.0]) == (0.0, 1.0)  # mu +- 2 sigma = -0.5, 1.5 clipped
    assert luminance_range([0.0, 2.0], i_max=2.0) == (0.0, 2.0)


def textured_background(n=200_000, seed=3):
    return np.random.default_rng(seed).uniform(0.3, 0.7, n)  # mu 0.5, sigma 0.115: no clipping


@pytest.mark.parametrize(("alpha", "t"), [(0.2, 0.9), (0.5, 0.1), (0.8, 0.5), (0.35, 0.0)])
def test_tap_range_recovers_alpha(alpha, t):
    a = textured_background()
    got = tap_transmittance(over(alpha, t, a), a, contrast="range")
    assert got == pytest.approx(alpha, abs=0.02)


@pytest.mark.parametrize(("alpha", "t"), [(0.2, 0.9), (0.5, 0.1), (0.8, 0.5), (0.35, 0.0)])
def test_tap_michelson_closed_form(alpha, t):
    a = textured_background()
    got = tap_transmittance(over(alpha, t, a), a, contrast="michelson")
    mu_a = 0.5
    assert got == pytest.approx(alpha * mu_a / (alpha * mu_a + (1 - alpha) * t), abs=0.02)


def test_tap_michelson_differs_from_alpha_for_bright_layer():
    a = textured_background()
    got = tap_transmittance(over(0.2, 0.9, a), a)
    assert got == pytest.approx(0.1 / (0.1 + 0.72), abs=0.02)
    assert abs(got - 0.2) > 0.05


def test_tap_hand_values_and_clipping():
    a = [0.4, 0.6]  # range [0.3, 0.7]: 0.4, michelson 0.4
    p = [0.45, 0.55]  # range [0.4, 0.6]: 0.2, michelson 0.2
    assert tap_transmittance(p, a, contrast="range") == pytest.approx(0.5)
    assert tap_transmittance(p, a) == pytest.approx(0.5)
    # A = [0, 1] clips to [0, 1]: range 1, michelson 1
    assert tap_transmittance(p, [0.0, 1.0], contrast="range") == pytest.approx(0.2)


def test_tap_undetermined_for_flat_background_and_opaque_black_overlay():
    assert np.isnan(tap_transmittance([0.2, 0.4], np.full(10, 0.5)))
    assert np.isnan(tap_transmittance([0.2, 0.4], np.zeros(10), contrast="range"))
    assert tap_transmittance(np.zeros(4), [0.4, 0.6]) == 0.0


def test_tap_rejects_bad_input():
    with pytest.raises(DVRInputError, match="contrast"):
        tap_transmittance([0.5], [0.5], contrast="weber")
    with pytest.raises(DVRInputError, match="lum_A"):
        tap_transmittance([0.5], [])
    with pytest.raises(DVRInputError, match=r"lum_P.*\[0, i_max"):
        tap_transmittance([1.5], [0.5, 0.6])
    with pytest.raises(DVRInputError, match="i_max"):
        tap_transmittance([0.5], [0.5], i_max=0)


# -- blend, Eq. 8 ----------------------------------------------------------------------------
def test_blend_weights_by_contrast():
    assert blended_transmittance(0.2, 0.6, 0.0) == pytest.approx(0.2)  # homogeneous: Metelli
    assert blended_transmittance(0.2, 0.6, 1.0) == pytest.approx(0.6)  # full contrast: TAP
    # D2: h = 1 - C with C the Michelson contrast of the region's robust range [0.2, 0.6]
    lo, hi = luminance_range([0.3, 0.5])  # mu 0.4, sigma 0.1
    c = (hi - lo) / (hi + lo)
    assert c == pytest.approx(0.5)
    assert blended_transmittance(0.2, 0.6, c) == pytest.approx(0.5 * 0.2 + 0.5 * 0.6)
    # a luminance range with the largest luminance (the Eq. 6 reading): h = 1 - range / i_max
    assert blended_transmittance(0.2, 0.6, 0.5, i_max=2.0) == pytest.approx(0.75 * 0.2 + 0.25 * 0.6)


def test_blend_nan_handling_arrays():
    out = blended_transmittance([np.nan, 0.3, np.nan, 0.2], [0.6, np.nan, np.nan, 0.6], 0.25)
    np.testing.assert_allclose(out[[0, 1, 3]], [0.6, 0.3, 0.3])
    assert np.isnan(out[2])


def test_blend_rejects_bad_contrast():
    with pytest.raises(DVRInputError, match="contrast"):
        blended_transmittance(0.2, 0.6, 1.2)
    with pytest.raises(DVRInputError, match="contrast"):
        blended_transmittance(0.2, 0.6, np.nan)


# -- calibration -----------------------------------------------------------------------------
def test_calibrate_identity_and_curve():
    assert calibrate(0.37) == pytest.approx(0.37)
    curve = ([0.0, 0.5, 1.0], [0.0, 0.8, 1.0])
    np.testing.assert_allclose(calibrate([0.0, 0.25, 0.75, 1.0], curve), [0.0, 0.4, 0.9, 1.0])
    out = calibrate([np.nan, 0.5], curve)
    assert np.isnan(out[0])
    assert out[1] == pytest.approx(0.8)


@pytest.mark.parametrize(
    "curve",
    [
        ([0.0, 0.6, 0.5], [0.0, 0.5, 1.0]),  # x unsorted
        ([0.0, 0.5, 1.0], [0.0, 0.7, 0.6]),  # y decreasing
        ([0.0, 1.2], [0.0, 1.0]),  # x out of [0, 1]
        ([0.0, 1.0], [-0.1, 1.0]),  # y out of [0, 1]
        ([0.5], [0.5]),  # one knot
        ([0.0, 0.5, 1.0], [0.0, 1.0]),  # length mismatch
    ],
)
def test_calibrate_rejects_bad_curve(curve):
    with pytest.raises(DVRInputError, match="curve"):
        calibrate(0.5, curve)
