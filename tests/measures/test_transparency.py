"""Tests for dvr_perception.measures.transparency on hand-composited layer images.

Each image is built with the exact over model: layers are listed front to back as
``(mask, opacity, colour)``; a pixel's visible opacity of layer ``s`` is ``a_s T_s`` and its
colour ``sum_s a_s T_s c_s + T background``, so in luminance a layer of transmittance
``alpha = 1 - a`` and luminance ``t`` maps what is behind it, ``I``, to ``alpha I + (1 - alpha) t``.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import (
    TransparencyResult,
    composite_luminance,
    tap_transmittance,
    transparency,
)
from dvr_perception.structures.spec import Structure, StructureSpec


def as_rgb(color, shape):
    c = np.asarray(color, float)
    if c.ndim == 0 or c.shape == shape:  # grey value(s)
        c = np.repeat(np.broadcast_to(c, shape)[..., None], 3, axis=-1)
    return np.broadcast_to(c, (*shape, 3))


def composite(shape, layers, background=(0.0, 0.0, 0.0)):
    """Front-to-back over compositing of (mask, opacity, colour) layers; grey or RGB colours."""
    k = len(layers)
    visible = np.zeros((k, *shape))
    rgb = np.zeros((*shape, 3))
    trans = np.ones(shape)
    for s, (mask, opacity, color) in enumerate(layers):
        a = np.where(mask, opacity, 0.0)
        visible[s] = a * trans
        rgb += visible[s][..., None] * as_rgb(color, shape)
        trans = trans * (1.0 - a)
    acc = 1.0 - trans
    return SimpleNamespace(
        rgba=np.concatenate([rgb, acc[..., None]], axis=-1).astype(np.float32),
        image=(rgb + trans[..., None] * np.asarray(background, float)).astype(np.float32),
        accumulated=acc,
        visible=visible,
    )


def make_spec(names, importances, background=(0.0, 0.0, 0.0)):
    structures = tuple(
        Structure(name=n, importance=w, colour=(1.0, 1.0, 1.0), range=(i, i + 1))
        for i, (n, w) in enumerate(zip(names, importances, strict=True))
    )
    return StructureSpec(structures=structures, background=background)


def analysis_and_spec(shape, layers, names, importances, background=(0.0, 0.0, 0.0)):
    ana = composite(shape, layers, background)
    ana.names = tuple(names)
    return ana, make_spec(names, importances, background)


def regions_with(res, layers):
    return [r for r in res.regions if sorted(r["layers"]) == sorted(layers)]


def band_over_backdrop(alpha=0.35, t=0.5, backdrop=0.9, bg=0.1, w_band=0.6, w_back=0.8):
    """8x8: opaque-ish backdrop on the left half, background on the right (the bipartite
    A/B split); a horizontal band of transmittance ``alpha`` in front, rows 3-4."""
    h, w = 8, 8
    band = np.zeros((h, w), bool)
    band[3:5, :] = True
    left = np.zeros((h, w), bool)
    left[:, :4] = True
    layers = [(band, 1.0 - alpha, t), (left, w_back, backdrop)]
    return analysis_and_spec((h, w), layers, ["band", "backdrop"], [w_band, w_back], (bg,) * 3)


def test_metelli_recovers_the_composited_transmittance():
    ana, spec = band_over_backdrop(alpha=0.35)
    res = transparency(ana, spec)
    assert isinstance(res, TransparencyResult)
    assert res.relations[("band", "backdrop")] == {"kind": "overlap", "encloser": None}
    plain, overlay = regions_with(res, ["band"]), regions_with(res, ["band", "backdrop"])
    assert len(plain) == len(overlay) == 1
    for region in (plain[0], overlay[0]):  # Case 2 and Case 3 give the same alpha
        assert region["transmittance"]["band"] == pytest.approx(0.35, abs=1e-6)
        assert region["method"]["band"] == "metelli"  # uniform regions: TAP undetermined
    # delta_t of the band's plain view: (1 - 0.35 - 0.6)^2
    assert plain[0]["delta_t"] == pytest.approx(0.05**2, abs=1e-6)
    assert res.per_structure["band"]["perceived_transparency"] == pytest.approx(0.35, abs=1e-6)
    assert res.per_structure["band"]["expected_opacity"] == 0.6


def test_out_of_range_transmittance_is_clipped_and_reported():
    # the backdrop "seen through" the band: (p - a) / (q - b) = (0.584 - 0.74) / (0.36 - 0.1)
    ana, spec = band_over_backdrop(alpha=0.35)
    res = transparency(ana, spec)
    backdrop_plain = regions_with(res, ["backdrop"])
    assert len(backdrop_plain) == 2  # above and below the band
    for region in [*backdrop_plain, *regions_with(res, ["band", "backdrop"])]:
        assert region["clipped"]["backdrop"] == pytest.approx(-0.6, abs=1e-5)
        assert region["transmittance"]["backdrop"] == 0.0
    assert any("clipped" in n for n in res.notes)
    # E_t by hand: 4 non-empty regions (areas 12, 8, 8, 12 of 64 pixels)
    d_back, d_band = (1 - 0 - 0.8) ** 2, (1 - 0.35 - 0.6) ** 2
    sum_wd = 2 * 12 / 64 * d_back + 8 / 64 * (d_back + d_band) + 8 / 64 * d_band
    assert res.E_t == pytest.approx(sum_wd / (40 / 64), abs=1e-6)  # area-weighted mean
    expected_image = np.array([r["delta_t"] for r in res.regions])[res.region_id]
    np.testing.assert_allclose(res.deviation, expected_image, rtol=1e-6)


def test_calibration_maps_measured_to_perceived():
    ana, spec = band_over_backdrop(alpha=0.35)
    res = transparency(ana, spec, calibration=([0.0, 0.5, 1.0], [0.0, 0.7, 1.0]))
    region = regions_with(res, ["band"])[0]
    assert region["measured"]["band"] == pytest.approx(0.35, abs=1e-6)
    assert region["transmittance"]["band"] == pytest.approx(0.49, abs=1e-6)
    assert region["delta_t"] == pytest.approx((1 - 0.49 - 0.6) ** 2, abs=1e-6)
    with pytest.raises(DVRInputError, match="calibration"):
        transparency(ana, spec, calibration=([0.0, 1.0], [1.0, 0.0]))


@pytest.mark.parametrize("contrast", ["range", "michelson"])
def test_textured_backdrop_blends_metelli_and_tap(contrast):
    # backdrop stripes 0.4 / 0.6 (mu 0.5, sigma 0.1), opaque; band alpha 0.35, luminance 0.8
    alpha, t = 0.35, 0.8
    h, w = 8, 8
    stripes = np.where(np.arange(w) % 2 == 0, 0.4, 0.6)[None, :].repeat(h, axis=0)
    band = np.zeros((h, w), bool)
    band[3:5, :] = True
    left = np.zeros((h, w), bool)
    left[:, :4] = True
    layers = [(band, 1.0 - alpha, t), (left, 1.0, stripes)]
    ana, spec = analysis_and_spec((h, w), layers, ["band", "backdrop"], [0.6, 1.0], (0.1,) * 3)
    res = transparency(ana, spec, contrast=contrast)
    overlay = regions_with(res, ["band", "backdrop"])[0]
    # Metelli on the means is exact; TAP "range" is exact for a uniform layer; Michelson
    # gives alpha mu_A / (alpha mu_A + (1 - alpha) t).  Eq. 8's h = 1 - C(P) (D2): P has
    # mu_P = alpha 0.5 + (1 - alpha) t and sigma_P = alpha 0.1 (no clipping), so its range is
    # 4 sigma_P and its Michelson contrast 4 sigma_P / (2 mu_P)
    tap = alpha if contrast == "range" else alpha * 0.5 / (alpha * 0.5 + (1 - alpha) * t)
    mu_p, sigma_p = alpha * 0.5 + (1 - alpha) * t, alpha * 0.1
    c_p = 4 * sigma_p if contrast == "range" else 4 * sigma_p / (2 * mu_p)
    h_blend = 1.0 - c_p
    assert overlay["method"]["band"] == "blend"
    expected = h_blend * alpha + (1 - h_blend) * tap
    assert overlay["transmittance"]["band"] == pytest.approx(expected, abs=1e-6)
    plain = regions_with(res, ["band"])[0]  # uniform: h = 1, Metelli alone
    assert plain["method"]["band"] == "metelli"
    assert plain["transmittance"]["band"] == pytest.approx(alpha, abs=1e-6)


def test_eq8_weight_is_one_minus_the_michelson_contrast_of_the_region():
    """D2 by hand: h = 1 - C with C = (I_max - I_min) / (I_max + I_min) of the region.

    An opaque backdrop of stripes 0.2 / 0.6 (mu_A 0.4, sigma_A 0.2) on the left, background
    0.1 on the right; a band of transmittance 0.5 and luminance 0.2 in front.  Overlay P =
    0.5 A + 0.1: stripes 0.2 / 0.4, mu 0.3, sigma 0.1, robust range [0.1, 0.5], C = 0.4 / 0.6
    = 2/3 (the range would give h = 0.6, Michelson gives h = 1/3).  Metelli on the means:
    (0.3 - 0.15) / (0.4 - 0.1) = 0.5; TAP: C(P) / C(A) = (2/3) / 1 (A's range [0, 0.8]).
    """
    h, w = 8, 8
    stripes = np.where(np.arange(w) % 2 == 0, 0.2, 0.6)[None, :].repeat(h, axis=0)
    band = np.zeros((h, w), bool)
    band[3:5, :] = True
    left = np.zeros((h, w), bool)
    left[:, :4] = True
    layers = [(band, 0.5, 0.2), (left, 1.0, stripes)]
    ana, spec = analysis_and_spec((h, w), layers, ["band", "backdrop"], [0.5, 1.0], (0.1,) * 3)
    res = transparency(ana, spec)
    overlay = regions_with(res, ["band", "backdrop"])[0]
    assert overlay["method"]["band"] == "blend"
    met, tap, h_d2 = 0.5, 2.0 / 3.0, 1.0 - 2.0 / 3.0
    expected = h_d2 * met + (1 - h_d2) * tap
    assert overlay["transmittance"]["band"] == pytest.approx(expected, abs=1e-6)
    # = 0.6111..., not the range-weighted 0.6 * 0.5 + 0.4 * (2/3) = 0.5667
    assert overlay["transmittance"]["band"] == pytest.approx(11.0 / 18.0, abs=1e-6)


def test_darker_of_two_equal_opacity_layers_is_less_transparent():
    # Fig. 4(c): equal opacity 0.5, purple (dark) in front of yellow, on white
    h, w = 8, 10
    purple_m = np.zeros((h, w), bool)
    purple_m[1:6, 1:6] = True
    yellow_m = np.zeros((h, w), bool)
    yellow_m[3:7, 4:9] = True
    purple, yellow = (0.5, 0.0, 0.5), (1.0, 1.0, 0.0)
    layers = [(purple_m, 0.5, purple), (yellow_m, 0.5, yellow)]
    ana, spec = analysis_and_spec((h, w), layers, ["purple", "yellow"], [0.5, 0.5], (1.0, 1.0, 1.0))
    res = transparency(ana, spec)
    overlay = regions_with(res, ["purple", "yellow"])[0]
    a_purple, a_yellow = overlay["transmittance"]["purple"], overlay["transmittance"]["yellow"]
    y_p, y_y = composite_luminance([*purple, 1.0]), composite_luminance([*yellow, 1.0])
    assert a_purple == pytest.approx(0.5, abs=1e-6)  # the front layer: exact
    assert a_yellow == pytest.approx((y_p - 0.5 * y_y - 0.5) / (y_p - 1.0), abs=1e-6)
    assert a_purple < a_yellow


def test_enclosing_layer_uses_tap_against_the_enclosed_region():
    # opaque striped outer layer (0.4 / 0.6) encloses an inner layer (opacity 0.7, grey 0.5)
    # in front of it: the enclosed part shows stripes 0.47 / 0.53, contrast ratio 0.3
    h, w = 10, 10
    stripes = np.where(np.arange(w) % 2 == 0, 0.4, 0.6)[None, :].repeat(h, axis=0)
    outer = np.zeros((h, w), bool)
    outer[1:9, 1:9] = True
    inner = np.zeros((h, w), bool)
    inner[3:7, 3:7] = True
    layers = [(inner, 0.7, 0.5), (outer, 1.0, stripes)]
    ana, spec = analysis_and_spec((h, w), layers, ["inner", "outer"], [0.7, 0.4])
    res = transparency(ana, spec)
    assert res.relations[("inner", "outer")] == {"kind": "enclose", "encloser": "outer"}
    y = composite_luminance(ana.rgba)
    expected = tap_transmittance(y[inner], y[outer & ~inner])
    assert expected == pytest.approx(0.3, abs=1e-6)
    plain = regions_with(res, ["outer"])[0]  # Case 2
    assert plain["method"] == {"outer": "tap"}
    assert plain["transmittance"]["outer"] == pytest.approx(expected, abs=1e-9)
    assert plain["delta_t"] == pytest.approx((1 - expected - 0.4) ** 2, abs=1e-9)
    overlay = regions_with(res, ["inner", "outer"])[0]  # Case 3: the encloser keeps it
    assert overlay["transmittance"] == {"outer": pytest.approx(expected, abs=1e-9)}
    assert res.per_structure["inner"]["perceived_transparency"] is None
    assert res.undetermined == []


def test_uniform_encloser_is_undetermined_not_guessed():
    h, w = 10, 10
    outer = np.zeros((h, w), bool)
    outer[1:9, 1:9] = True
    inner = np.zeros((h, w), bool)
    inner[3:7, 3:7] = True
    layers = [(inner, 0.7, 0.5), (outer, 1.0, 0.4)]
    ana, spec = analysis_and_spec((h, w), layers, ["inner", "outer"], [0.7, 0.4])
    res = transparency(ana, spec)
    reasons = res.per_structure["outer"]["undetermined_reasons"]
    assert len(reasons) == 1
    assert "no luminance contrast" in reasons[0]
    assert res.per_structure["outer"]["perceived_transparency"] is None
    assert {u["structure"] for u in res.undetermined} == {"outer"}
    assert res.E_t == 0.0
    assert not res.deviation.any()


def test_disjoint_layers_are_separate_with_zero_deviation():
    h, w = 6, 10
    a = np.zeros((h, w), bool)
    a[1:5, 1:4] = True
    b = np.zeros((h, w), bool)
    b[1:5, 6:9] = True
    ana, spec = analysis_and_spec((h, w), [(a, 0.5, 0.8), (b, 0.5, 0.3)], ["a", "b"], [0.5, 0.5])
    res = transparency(ana, spec)
    assert res.relations[("a", "b")] == {"kind": "separate", "encloser": None}
    for region in regions_with(res, ["a"]) + regions_with(res, ["b"]):
        assert region["kind"] == "plain"
        assert region["delta_t"] == 0.0
        assert region["transmittance"] == {}
    assert res.E_t == 0.0
    assert res.per_structure["a"]["perceived_transparency"] is None
    assert any("no region has a determinable" in n for n in res.notes)


def test_missing_reference_region_is_undetermined():
    # two overlapping layers covering the whole image: no empty region B = {} exists
    h, w = 4, 9
    a = np.zeros((h, w), bool)
    a[:, :6] = True
    b = np.zeros((h, w), bool)
    b[:, 3:] = True
    ana, spec = analysis_and_spec((h, w), [(a, 0.5, 0.8), (b, 0.5, 0.3)], ["a", "b"], [0.5, 0.5])
    res = transparency(ana, spec)
    assert res.relations[("a", "b")]["kind"] == "overlap"
    assert {(u["structure"], u["region"]) for u in res.undetermined} == {
        (name, r["id"]) for r in res.regions for name in r["layers"]
    }
    for name in ("a", "b"):
        info = res.per_structure[name]
        assert info["perceived_transparency"] is None
        assert info["perceived_opacity"] is None
        assert any("layer set(s) {}" in r for r in info["undetermined_reasons"])
    assert res.E_t == 0.0
    assert np.all(np.isfinite(res.deviation))
    assert not res.deviation.any()


def test_three_overlapping_layers_use_generalized_metelli():
    # Venn layout of three equally bright layers: Eq. 9 is exact in any depth order
    h, w = 12, 12
    m0, m1, m2 = (np.zeros((h, w), bool) for _ in range(3))
    m0[0:8, 0:8] = True
    m1[0:8, 4:12] = True
    m2[4:12, 2:10] = True
    alphas = (0.6, 0.5, 0.7)  # the back layer stays visible (0.3 * 0.6 * 0.5 > threshold)
    layers = [(m, 1.0 - a, 0.6) for m, a in zip((m0, m1, m2), alphas, strict=True)]
    names = ["l0", "l1", "l2"]
    ana, spec = analysis_and_spec((h, w), layers, names, [0.4, 0.5, 0.3], (0.1,) * 3)
    res = transparency(ana, spec)
    assert all(r["kind"] == "overlap" for r in res.relations.values())
    triple = regions_with(res, ["l0", "l1", "l2"])
    assert len(triple) == 1
    assert set(triple[0]["method"].values()) == {"generalized"}
    for name, alpha in zip(("l0", "l1", "l2"), alphas, strict=True):
        assert triple[0]["transmittance"][name] == pytest.approx(alpha, abs=1e-6)
        assert res.per_structure[name]["perceived_transparency"] == pytest.approx(alpha, abs=1e-6)
    assert triple[0]["delta_t"] == pytest.approx(0.0, abs=1e-9)  # o = 1 - alpha everywhere
    assert res.E_t == pytest.approx(0.0, abs=1e-9)


def test_empty_image_gives_zero_with_note():
    h, w = 4, 4
    ana, spec = analysis_and_spec((h, w), [(np.zeros((h, w), bool), 0.5, 0.5)], ["a"], [0.5])
    res = transparency(ana, spec)
    assert res.E_t == 0.0
    assert [r["kind"] for r in res.regions] == ["empty"]
    assert any("no non-empty region" in n for n in res.notes)


def test_bad_input():
    ana, spec = band_over_backdrop()
    with pytest.raises(DVRInputError, match="spec"):
        transparency(ana, None)
    with pytest.raises(DVRInputError, match="names"):
        transparency(ana, make_spec(["x", "y"], [0.5, 0.5]))
    with pytest.raises(DVRInputError, match="contrast"):
        transparency(ana, spec, contrast="weber")
    with pytest.raises(DVRInputError, match="threshold"):
        transparency(ana, spec, threshold=1.5)
    bad = SimpleNamespace(**vars(ana))
    bad.rgba = ana.rgba[:4]
    with pytest.raises(DVRInputError, match="rgba"):
        transparency(bad, spec)
