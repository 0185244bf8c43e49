"""Per-layer-set estimates of the transparency measure against the per-region rules."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dvr_perception.measures import transparency
from dvr_perception.measures._estimates import region_estimates, region_table
from dvr_perception.measures._layer_sets import _group_stats, _LayerSets, _robust
from dvr_perception.measures.regions import layer_footprints, layer_relations, subregions
from dvr_perception.measures.results import _image_luminance
from dvr_perception.measures.transparency import transparency_table
from dvr_perception.rays import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.phantom import make_phantom


@pytest.fixture(scope="module")
def phantom_view():
    """The phantom seen from an oblique view: many regions of many layer sets."""
    vol, spec = make_phantom(size=48)
    cam = Camera.from_view(vol.bounds, azimuth=35, elevation=20, width=72, height=64)
    return analyze(vol, spec, cam, build_cache=False), spec


def _layer_sets(analysis, spec):
    y, _ = _image_luminance(analysis, spec, analysis.accumulated.shape)
    fp = layer_footprints(np.asarray(analysis.visible, np.float64), threshold=0.05)
    rmap = subregions(fp)
    layer_sets = _LayerSets(y, rmap, layer_relations(fp), analysis.names, "michelson")
    return y, rmap, layer_sets


@pytest.mark.parametrize("calibration", [None, ([0.0, 0.4, 1.0], [0.0, 0.6, 1.0])])
def test_layer_set_estimates_equal_the_rules_region_by_region(phantom_view, calibration):
    analysis, spec = phantom_view
    y, rmap, layer_sets = _layer_sets(analysis, spec)
    expected = [s.target_opacity for s in spec.structures]
    est = region_estimates(layer_sets, rmap, y, expected, calibration, [])
    _, mean, std = _group_stats(y.ravel(), rmap.region_id.ravel(), len(rmap.regions))
    kinds, methods = set(), set()
    for region in rmap.regions:
        ref = layer_sets.evaluate(region.layers, _robust(mean[region.id], std[region.id]), [])
        lays = est.layers[region.id]
        assert [lay.k for lay in lays] == list(ref)
        p = est.position[region.id]
        delta = 0.0
        for lay in lays:
            want = ref[lay.k]
            assert lay.reason == want.reason
            if want.reason is not None:
                kinds.add("undetermined")
                continue
            measured = min(max(want.alpha, 0.0), 1.0)
            alpha_t = measured
            if calibration is not None:
                alpha_t = float(np.interp(measured, *calibration))
            assert lay.raw[p] == want.alpha  # bit for bit
            assert lay.measured[p] == measured
            assert lay.alpha_t[p] == pytest.approx(alpha_t, abs=1e-15)
            assert lay.method[p] == want.method
            methods.add(want.method)
            delta += (1.0 - lay.alpha_t[p] - expected[lay.k]) ** 2
        assert est.deltas[region.id] == delta
        kinds.add(region.kind)
    # the view exercises the rules: plain and overlaid regions, several methods, undetermined
    assert {"plain", "overlay", "undetermined"} <= kinds
    assert len(methods) >= 2
    assert len(rmap.regions) > 40


def test_table_holds_what_the_records_say(phantom_view):
    analysis, spec = phantom_view
    res = transparency(analysis, spec)
    region_id, deltas, alpha, empty = transparency_table(analysis, spec)
    names = list(analysis.names)
    np.testing.assert_array_equal(region_id, res.region_id)
    assert alpha.shape == (len(res.regions), len(names))
    for r in res.regions:
        assert deltas[r["id"]] == r["delta_t"]
        # left out of E_t: empty regions and those whose layers are all undetermined (D3)
        assert empty[r["id"]] == (not r["counted"])
        assert r["counted"] == (
            r["kind"] != "empty" and not (r["undetermined"] and not r["transmittance"])
        )
        for k, name in enumerate(names):
            if name in r["transmittance"]:
                assert alpha[r["id"], k] == r["transmittance"][name]
            else:
                assert math.isnan(alpha[r["id"], k])
    assert np.isfinite(alpha).any()


def test_region_table_of_an_empty_image_is_all_empty():
    fp = np.zeros((2, 5, 6), bool)
    rmap = subregions(fp)
    layer_sets = _LayerSets(np.zeros((5, 6)), rmap, layer_relations(fp), ("a", "b"), "michelson")
    est = region_estimates(layer_sets, rmap, np.zeros((5, 6)), [0.5, 0.5], None, [])
    alpha, empty = region_table(est, rmap, 2)
    assert alpha.shape == (1, 2)
    assert np.all(np.isnan(alpha))
    assert empty.tolist() == [True]
    assert est.deltas.tolist() == [0.0]


def test_subregions_without_geometry_differ_only_in_it(phantom_view):
    analysis, _ = phantom_view
    fp = layer_footprints(np.asarray(analysis.visible, np.float64), threshold=0.05)
    full, bare = subregions(fp), subregions(fp, geometry=False)
    np.testing.assert_array_equal(full.region_id, bare.region_id)
    assert len(full.regions) == len(bare.regions)
    for a, b in zip(full.regions, bare.regions, strict=True):
        assert (a.id, a.layers, a.kind, a.area, a.area_fraction) == (
            b.id, b.layers, b.kind, b.area, b.area_fraction,
        )  # fmt: skip
        assert b.bbox is None
        assert b.centroid is None
        assert a.bbox is not None
        assert a.centroid is not None
