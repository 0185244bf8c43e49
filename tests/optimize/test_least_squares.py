"""Eq. 13's least-squares objective (decision D4) beside the image-mean E."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.optimize import optimize
from dvr_perception.optimize._problem import Params, Problem, residue
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom

PX = 24


@pytest.fixture(scope="module")
def tiny():
    vol, spec = make_phantom(size=32)
    cam = Camera.from_view(vol.bounds, width=PX, height=PX)
    return vol, spec.with_opacities([0.3] * len(spec.structures)), cam


def test_residue_by_hand():
    # two rays: E(f, r) = 2 * 0.5 + 1 * 0.2 + 0 = 1.2 and 2 * 0 + 1 * 0.4 + 0 = 0.4
    stack = np.array([[0.5, 0.0], [0.2, 0.4], [0.0, 0.0]])
    assert residue([stack], (2.0, 1.0, 0.0)) == pytest.approx((1.2**2 + 0.4**2) / 2)
    # a zero weight ignores its row, even an undetermined one; views are averaged
    partial = np.array([[0.5, 0.0], [np.nan, np.nan], [0.1, 0.3]])
    assert residue([partial], (1.0, 0.0, 1.0)) == pytest.approx((0.6**2 + 0.3**2) / 2)
    assert residue([stack, np.zeros((3, 5))], (2.0, 1.0, 0.0)) == pytest.approx(0.4)
    assert np.isnan(residue([partial], (1.0, 1.0, 1.0)))


def test_S_is_the_per_pixel_sum_of_the_public_measures(tiny):
    vol, spec, cam = tiny
    curv, _ = curvature_volume(vol, spec)
    a = analyze(vol, spec, cam, curvature=curv)
    w = np.array([1.0, 0.5, 2.0])
    problem = Problem([a.cache], [None], spec, w, {}, None)
    terms = problem.terms(Params.from_spec(spec), analyses=[a])
    vis, shp, trn = visibility(a, spec), shape(a, spec), transparency(a, spec)
    rays = np.asarray(a.assigned).sum(axis=0) > 0
    d_v = np.asarray(vis.deviation, float)
    d_s = np.where(shp.nonempty, shp.deviation, 0.0)
    d_t = np.asarray(trn.deviation, float)  # delta_t of the pixel's region, 0 where empty
    e = w[0] * d_v + w[1] * d_s + w[2] * d_t
    assert rays.sum() > 50
    assert np.all(d_t[~rays] == 0)
    assert np.any(d_t[rays] > 0)
    assert terms["S"] == pytest.approx(float(np.mean(e[rays] ** 2)), rel=1e-5)
    assert terms["E_v"] == pytest.approx(float(d_v[rays].mean()), abs=1e-6)


@pytest.mark.parametrize("stages", [("opacity",), ("opacity", "lighting", "colour")])
def test_least_squares_never_raises_S_and_reports_both(tiny, stages):
    vol, spec, cam = tiny
    res = optimize(vol, spec, cam, stages=stages, objective="least_squares", max_iter=3)
    assert res.final["S"] <= res.initial["S"] + 1e-12
    for t in (res.initial, res.final):
        assert np.isfinite(t["S"])
        assert np.isfinite(t["E"])
        assert t["whole"]["S"] == pytest.approx(t["S"])
    mean = optimize(vol, spec, cam, stages=stages, objective="mean", max_iter=3)
    assert mean.final["E"] <= mean.initial["E"] + 1e-12
    assert mean.initial["S"] == pytest.approx(res.initial["S"])


@pytest.mark.parametrize("bad", ["squares", "", None, 2, "MEAN"])
def test_objective_is_validated(tiny, bad):
    vol, spec, cam = tiny
    with pytest.raises(DVRInputError, match="objective"):
        optimize(vol, spec, cam, stages=("opacity",), objective=bad)
