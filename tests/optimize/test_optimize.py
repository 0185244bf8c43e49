"""Tests of the staged optimiser on the phantom (48^3 volume, 48 px images: fast)."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.optimize import (
    STAGES,
    ColourStage,
    LightingStage,
    OpacityStage,
    optimize,
    register_stage,
)
from dvr_perception.optimize._exact import OpacityModel
from dvr_perception.optimize._problem import Params, Problem
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume

PX = 48


@pytest.fixture(scope="module")
def phantom():
    vol, spec = make_phantom(size=48)
    cam = Camera.from_view(vol.bounds, width=PX, height=PX)
    # a poor start: every structure rendered at opacity 0.3 (importance 0.1 ... 0.9)
    return vol, spec.with_opacities([0.3] * len(spec.structures)), cam


@pytest.fixture(scope="module")
def stage1(phantom):
    vol, spec, cam = phantom
    return optimize(vol, spec, cam, stages=("opacity",), max_iter=8, seed=3)


def _measure(vol, spec, cam):
    curv, _ = curvature_volume(vol, spec)
    a = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    return a, visibility(a, spec).E_v, shape(a, spec).E_s, transparency(a, spec).E_t


def test_the_kept_renderings_equal_fresh_analyses_of_both_specs(phantom):
    """``res.analyses``: what the CLI measures before and after, without analysing again."""
    vol, spec, cam = phantom
    r = optimize(vol, spec, cam, stages=("opacity", "lighting", "colour"), max_iter=2, seed=1)
    assert r.final["E"] < r.initial["E"]  # the spec changed, so "after" differs from "before"
    for got, sp in zip(r.analyses, (spec, r.spec), strict=True):
        fresh, *terms = _measure(vol, sp, cam)
        for f in ("rgba", "visible", "assigned", "present", "curvature"):
            assert np.abs(getattr(got, f).astype(float) - getattr(fresh, f)).max() <= 1e-6, f
        assert terms == pytest.approx(
            [visibility(got, sp).E_v, shape(got, sp).E_s, transparency(got, sp).E_t], abs=1e-7
        )


def _same_measures(a, b) -> bool:
    """Whether two MeasureSets hold the same numbers and arrays, bit for bit."""
    from dataclasses import fields, is_dataclass
    from functools import partial

    def same(x, y):
        if isinstance(x, partial):  # a lazily made field: the same call
            return (isinstance(y, partial) and x.func is y.func and same(x.args, y.args)
                    and same(x.keywords, y.keywords))  # fmt: skip
        if is_dataclass(x):
            return type(x) is type(y) and all(
                same(getattr(x, f.name), getattr(y, f.name)) for f in fields(x)
            )
        if isinstance(x, np.ndarray):
            return isinstance(y, np.ndarray) and np.array_equal(x, y, equal_nan=True)
        if isinstance(x, dict):
            return x.keys() == y.keys() and all(same(x[k], y[k]) for k in x)
        if isinstance(x, (list, tuple)):
            return len(x) == len(y) and all(same(u, v) for u, v in zip(x, y, strict=True))
        if isinstance(x, float) and np.isnan(x):
            return isinstance(y, float) and np.isnan(y)
        return x == y

    return same(tuple(a), tuple(b))


def test_measures_kept_by_the_optimiser_equal_measuring_its_renderings(phantom):
    """``measures=True``: the before/after MeasureSets the CLI reports, without measuring again.

    Measured where the optimiser had just rendered each (cheaper), they equal
    ``all_measures`` of ``res.analyses`` afterwards, every field bit for bit; without the
    option the result holds none, and the optimisation is the same.
    """
    from dvr_perception.measures import all_measures, results

    vol, spec, cam = phantom
    kw = {"stages": ("opacity", "lighting", "colour"), "max_iter": 2, "seed": 1}
    r = optimize(vol, spec, cam, measures=True, **kw)
    plain = optimize(vol, spec, cam, **kw)
    assert plain.measures == ()
    assert (plain.initial, plain.final, plain.spec) == (r.initial, r.final, r.spec)
    assert len(r.measures) == 2
    results._FIELD_MEMO.clear()  # measured afresh
    for kept, analysis, sp in zip(r.measures, r.analyses, (spec, r.spec), strict=True):
        again = all_measures(analysis, sp)
        assert _same_measures(kept, again)
    before, after = r.measures
    assert before.visibility.E_v == pytest.approx(r.initial["E_v"], abs=1e-6)
    assert after.transparency.E_t == pytest.approx(r.final["E_t"], abs=1e-6)
    assert not _same_measures(before, after)  # the spec changed: the check can tell them apart


def test_stage1_lowers_visibility_without_washing_out(phantom, stage1):
    vol, spec, cam = phantom
    r = stage1
    assert r.final["E_v"] <= 0.7 * r.initial["E_v"]  # the 30 %
    assert r.final["E"] <= r.initial["E"]
    # the reported terms are the measures of the returned spec, and no fading in the image
    a0, ev0, _, _ = _measure(vol, spec, cam)
    a1, ev1, es1, et1 = _measure(vol, r.spec, cam)
    assert ev0 == pytest.approx(r.initial["E_v"], abs=1e-6)
    assert (ev1, es1, et1) == pytest.approx(
        (r.final["E_v"], r.final["E_s"], r.final["E_t"]), abs=1e-6
    )
    rays = a0.assigned.sum(axis=0) > 0
    assert a1.accumulated[rays].mean() == pytest.approx(r.final["coverage"], abs=1e-6)
    # no wash-out (D6) against the rendering at the importances, which E_v aims at (the
    # start, every opacity 0.3, over-shows the structures of importance 0.1)
    assert r.final["coverage"] >= 0.6 * a0.importance_accumulated[rays].mean()
    rec = r.stages[0]
    assert rec.name == "opacity"
    assert rec.accepted
    assert 1 <= rec.iterations <= 8
    assert rec.params_after["opacity"] != rec.params_before["opacity"]
    assert all(0.01 <= s.opacity <= 1.0 for s in r.spec.structures)
    assert len(rec.history) == rec.iterations
    assert r.nit == rec.iterations
    # the other terms stay within the stage tolerance (0.05 + half the E_v gain)
    gain = rec.terms_before["E_v"] - rec.terms_after["E_v"]
    for t in ("E_s", "E_t"):
        allowed = OpacityStage.tolerance + OpacityStage.trade * gain
        assert rec.terms_after[t] <= rec.terms_before[t] + allowed + 1e-9


def test_exact_opacity_model_matches_the_problem(phantom):
    """E_v and coverage of the exact model equal the Problem's; gradients match differences."""
    vol, spec, cam = phantom
    curv, _ = curvature_volume(vol, spec)
    cache = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    problem = Problem([cache], [None], spec, np.ones(3), {}, None)
    params = Params.from_spec(spec)
    model = OpacityModel(problem, params)
    ops = np.array([0.2, 0.5, 0.35, 0.6, 0.45, 0.8])
    e_v, cov, g_v, g_c = model.evaluate(ops)
    ref = problem.terms(params.replace(opacities=ops), need=("E_v",))
    assert e_v == pytest.approx(ref["E_v"], abs=1e-6)
    assert cov == pytest.approx(ref["coverage"], abs=1e-6)
    h = 2e-3  # well above the 1/32767 rounding of the opacity table
    for k in range(ops.size):
        up, down = ops.copy(), ops.copy()
        up[k] += h
        down[k] -= h
        (ev_u, c_u, *_), (ev_d, c_d, *_) = model.evaluate(up), model.evaluate(down)
        assert g_c[k] == pytest.approx((c_u - c_d) / (2 * h), rel=0.1, abs=2e-3)
        assert g_v[k] == pytest.approx((ev_u - ev_d) / (2 * h), rel=0.15, abs=5e-3)


def test_exact_opacity_model_is_the_same_serial_and_parallel(phantom, monkeypatch):
    """From PARALLEL_RAYS rays on the rays are composited in parallel: the same numbers."""
    from dvr_perception.optimize import _exact

    vol, spec, cam = phantom
    problem = Problem(
        [analyze(vol, spec, cam, build_cache=True).cache], [None], spec, np.ones(3), {}, None
    )
    model = OpacityModel(problem, Params.from_spec(spec))
    ops = np.array([0.2, 0.5, 0.35, 0.6, 0.45, 0.8])
    serial = model.evaluate(ops, shares=True)
    monkeypatch.setattr(_exact, "PARALLEL_RAYS", 1)
    parallel = model.evaluate(ops, shares=True)
    for a, b in zip(serial, parallel, strict=True):
        assert np.array_equal(a, b)


_LAYER_PROBE = """
import sys, numpy as np, numba
from dvr_perception.optimize import _exact
n, k = 64, 3
rays = np.arange(n, dtype=np.int64)
start, count = np.zeros(n, np.int64), np.ones(n, np.int64)
lut, ids = np.zeros(1, np.uint16), np.zeros(4, np.int64)
alpha, dalpha = np.full(4, 0.5), np.ones(4)
vis, acc, dvis, dacc = np.empty((k, n)), np.empty(n), np.zeros((k, k, n)), np.zeros((k, n))
getattr(_exact, sys.argv[1])(rays, start, count, lut, ids, alpha, dalpha, dalpha, k, 0.01, True,
                             vis, dvis, acc, dacc)
assert np.all(acc == 0.5) and np.all(vis[0] == 0.5), (acc, vis)
try:
    print(numba.threading_layer())
except ValueError:  # no parallel region has run in this process
    print("serial")
"""


def test_the_parallel_opacity_kernel_stays_parallel_with_a_warm_cache(tmp_path):
    """The serial and the parallel compositing kernel have their own numba cache entries.

    numba's cache keys a kernel by its Python function and signature, not by ``parallel``:
    compiled from one function, whichever variant was cached first was loaded for both (the
    optimiser composites few rays first, so the "parallel" kernel ran serially).  Here the
    serial one is compiled and cached first, then a fresh process runs the parallel one from
    the same cache folder: it must start numba's threads.
    """
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "NUMBA_NUM_THREADS": "2"}

    def run(kernel):
        proc = subprocess.run([sys.executable, "-c", _LAYER_PROBE, kernel], env=env,
                              capture_output=True, text=True, timeout=600, check=False)  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        return proc.stdout.strip().splitlines()[-1]

    assert run("_composite_grad") == "serial"
    assert any(tmp_path.rglob("*.nbi"))  # cached
    assert run("_composite_grad_parallel") != "serial"  # a threading layer (omp, tbb, ...)
    assert run("_composite_grad") == "serial"  # and the serial one stays serial


def test_coverage_alone_is_the_evaluations_coverage_bit_for_bit(phantom, monkeypatch):
    """``coverage`` equals ``evaluate``'s, serial and parallel, and counts one evaluation.

    The opacity stage checks its floor at the user's resolution with it.
    """
    from dvr_perception.optimize import _exact

    vol, spec, cam = phantom
    cache = analyze(vol, spec, cam, build_cache=True).cache
    problem = Problem([cache], [None], spec, np.ones(3), {}, None)
    model = OpacityModel(problem, Params.from_spec(spec))
    rng = np.random.default_rng(3)
    for ops in [np.array([0.2, 0.5, 0.35, 0.6, 0.45, 0.8]), *rng.uniform(0, 1, (4, 6))]:
        for parallel in (False, True):
            monkeypatch.setattr(_exact, "PARALLEL_RAYS", 1 if parallel else 10**9)
            want = model.evaluate(ops, grad=False)[1]
            n = model.nfev
            got = model.coverage(ops)
            assert model.nfev == n + 1
            assert got == want
            assert 0.0 < got < 1.0


def test_the_latest_rendering_is_reused_for_the_same_parameters(phantom):
    vol, spec, cam = phantom
    problem = Problem(
        [analyze(vol, spec, cam, build_cache=True).cache], [None], spec, np.ones(3), {}, None
    )
    params = Params.from_spec(spec)
    first = problem.render(params)
    assert problem.render(params.replace(opacities=params.opacities.copy())) is first
    other = problem.render(params.replace(opacities=params.opacities * 0.5))
    assert other is not first
    assert not np.array_equal(other.rgba, first.rgba)
    assert problem.render(params) is not first  # only the latest is kept
    assert np.array_equal(problem.render(params).rgba, first.rgba)


def test_no_fading_holds_at_the_user_resolution(phantom):
    """Optimised on 24 px rays, the 48 px image keeps its coverage when the user asks for it
    (``coverage_keep=1``, checked exactly there)."""
    vol, spec, cam = phantom
    r = optimize(vol, spec, cam, stages=("opacity",), max_iter=3, seed=1, resolution=24,
                 coverage_keep=1.0)  # fmt: skip
    assert r.stages[0].accepted
    assert r.final["E_v"] < r.initial["E_v"]
    assert r.final["coverage"] >= r.initial["coverage"]


def test_coverage_floor_is_off_by_default_and_holds_when_asked(phantom, stage1):
    """No floor by default (D1: fading raises E_v); a user floor is kept, and costs E_v."""
    vol, spec, cam = phantom
    assert OpacityStage().floor({"coverage": 0.7}) == 0.0
    assert OpacityStage(opacity_floor=0.5).floor({"coverage": 0.7}) == 0.5
    keep = OpacityStage()
    keep.coverage_keep = 0.8
    assert keep.floor({"coverage": 0.5}) == pytest.approx(0.4)
    floor = 0.95 * stage1.initial["coverage"]
    assert stage1.final["coverage"] < floor  # the free optimum fades the phantom somewhat
    r = optimize(vol, spec, cam, stages=("opacity",), max_iter=8, seed=3, opacity_floor=floor)
    assert r.final["coverage"] >= floor
    assert r.final["E_v"] < r.initial["E_v"]
    assert r.final["E_v"] > stage1.final["E_v"]  # the floor costs visibility
    rel = optimize(vol, spec, cam, stages=("opacity",), max_iter=8, seed=3, coverage_keep=0.95)
    assert rel.final["coverage"] >= 0.95 * rel.initial["coverage"]
    assert rel.final["E_v"] < rel.initial["E_v"]


def test_lighting_stage_does_not_raise_E(phantom, stage1):
    vol, _, cam = phantom
    r = optimize(vol, stage1.spec, cam, stages=("lighting",), max_iter=3, seed=1)
    assert r.final["E"] <= r.initial["E"] + 1e-12
    assert r.final["E_s"] <= r.initial["E_s"] + 1e-12  # the lead never rises
    assert r.final["E_v"] == pytest.approx(r.initial["E_v"], abs=1e-9)  # opacity untouched
    rec = r.stages[0]
    assert set(rec.params_after) == {"lighting", "light_direction"}
    assert rec.message == "improved"
    assert r.final["E_s"] < r.initial["E_s"]
    assert np.linalg.norm(r.spec.rendering.light_direction) == pytest.approx(1.0)


def test_lighting_stage_keeps_shape_cues_and_brightness(phantom, stage1):
    """Ambient/diffuse split, specular and power bounds, light cone, brightness guard."""
    vol, _, cam = phantom
    r = optimize(vol, stage1.spec, cam, stages=("lighting",), max_iter=4, seed=5)
    assert r.stages[0].message == "improved"
    for before, after in zip(stage1.spec.structures, r.spec.structures, strict=True):
        lit = after.lighting
        assert 0.05 - 1e-9 <= lit.ambient <= 0.4 + 1e-9
        assert 0.4 - 1e-9 <= lit.diffuse <= 1.0 + 1e-9
        assert 0.0 <= lit.specular <= 0.8 + 1e-9
        assert 2.0 - 1e-6 <= lit.specular_power <= 96.0 + 1e-6
        total = before.lighting.ambient + before.lighting.diffuse
        assert lit.ambient + lit.diffuse == pytest.approx(total, abs=1e-6)  # split, not level
    light = np.asarray(r.spec.rendering.light_direction)
    assert np.degrees(np.arccos(light[2] / np.linalg.norm(light))) <= 40.0  # headlight cone
    lum0, lum1 = r.initial["luminance"], r.final["luminance"]
    for name, value in lum0.items():
        assert lum1[name] >= LightingStage.BRIGHTNESS * value - 1e-9, name
    # and in a rendering of the returned spec: no structure's footprint goes dark
    a0, *_ = _measure(vol, stage1.spec, cam)
    a1, *_ = _measure(vol, r.spec, cam)
    y0, y1 = a0.image @ [0.2126, 0.7152, 0.0722], a1.image @ [0.2126, 0.7152, 0.0722]
    for k in range(len(r.spec.structures)):
        w0, w1 = a0.visible[k], a1.visible[k]
        if w0.sum() > 0 and (w0 * y0).sum() / w0.sum() > 1e-3:
            ratio = ((w1 * y1).sum() / w1.sum()) / ((w0 * y0).sum() / w0.sum())
            assert ratio >= LightingStage.BRIGHTNESS - 1e-6


def test_partial_terms_complete_to_the_full_terms(phantom):
    vol, spec, cam = phantom
    curv, _ = curvature_volume(vol, spec)
    cache = analyze(vol, spec, cam, curvature=curv, build_cache=True).cache
    problem = Problem([cache], [None], spec, np.ones(3), {}, None)
    params = Params.from_spec(spec).replace(opacities=[0.5] * 6)
    fast = problem.terms(params, need=("E_v",))
    assert np.isnan(fast["E_t"])
    assert np.isnan(fast["E"])
    assert not np.isnan(fast["E_v"])
    done, ref = problem.complete(params, fast), problem.terms(params)
    for key in ("E_v", "E_s", "E_t", "E", "coverage"):
        assert done[key] == pytest.approx(ref[key], abs=1e-12)
    assert np.allclose(done["luminance"], ref["luminance"])


def test_colour_stage_keeps_hue_and_does_not_raise_E_t(phantom, stage1):
    import colorsys

    vol, _, cam = phantom
    r = optimize(vol, stage1.spec, cam, stages=("colour",), max_iter=3, seed=2)
    assert r.final["E_t"] <= r.initial["E_t"] + 1e-12
    assert r.final["E"] <= r.initial["E"] + 1e-12
    for before, after in zip(stage1.spec.structures, r.spec.structures, strict=True):
        h0, s0, v0 = colorsys.rgb_to_hsv(*before.colour)
        h1, s1, v1 = colorsys.rgb_to_hsv(*after.colour)
        assert s1 >= 0.8 * s0 - 1e-6  # keeps its colour identity: not washed out ...
        assert s1 <= s0 + 0.2 + 1e-6  # ... nor garish
        assert h1 == pytest.approx(h0, abs=1e-6)
        assert v1 >= max(0.05, ColourStage.VALUE_KEEP * v0) - 1e-6  # no darkening to black
    for name, value in r.initial["luminance"].items():  # the brightness guard
        assert r.final["luminance"][name] >= ColourStage.BRIGHTNESS * value - 1e-9


def test_same_seed_same_result(phantom):
    vol, spec, cam = phantom
    kw = {"stages": ("opacity",), "max_iter": 4, "seed": 7}
    a, b = optimize(vol, spec, cam, **kw), optimize(vol, spec, cam, **kw)
    assert [s.opacity for s in a.spec.structures] == [s.opacity for s in b.spec.structures]
    assert a.nfev == b.nfev
    assert a.final == b.final


def test_callback_gets_copies_and_stopiteration_returns_best(phantom):
    vol, spec, cam = phantom
    seen = []

    def stop(inter):
        seen.append(inter)
        inter.terms["E"] = -1.0  # a copy: must not affect the optimiser
        if inter.iteration == 2:
            raise StopIteration

    r = optimize(vol, spec, cam, stages=("opacity", "lighting"), max_iter=8, callback=stop)
    assert r.status == 1
    assert not r.success
    assert "callback" in r.message
    assert len(seen) == 2
    assert r.nit == 2
    assert len(r.stages) == 1
    assert seen[0].stage == "opacity"
    assert seen[1].nfev >= seen[0].nfev
    assert r.final["E"] >= 0
    assert r.final["E_v"] <= r.initial["E_v"]


def test_opacity_floor_at_start_forbids_any_fading(phantom):
    vol, spec, cam = phantom
    r0 = optimize(vol, spec, cam, stages=("opacity",), max_iter=1)
    floor = r0.initial["coverage"]
    r = optimize(vol, spec, cam, stages=("opacity",), max_iter=4, opacity_floor=floor)
    assert r.final["coverage"] >= floor - 1e-12
    assert r.final["E_v"] <= r.initial["E_v"]


def test_region_changes_inside_more_than_outside(phantom):
    vol, spec, cam = phantom
    region = ("rect", 10, 8, 26, 24)
    r = optimize(vol, spec, cam, stages=("opacity",), region=region, max_iter=6)
    assert r.final["E_v"] < r.initial["E_v"]
    curv, _ = curvature_volume(vol, spec)
    a0 = analyze(vol, spec, cam, curvature=curv, build_cache=False)
    a1 = analyze(vol, r.spec, cam, curvature=curv, build_cache=False)
    d0, d1 = visibility(a0, spec).deviation, visibility(a1, r.spec).deviation
    inside = np.zeros((PX, PX), bool)
    inside[8:24, 10:26] = True
    ne = a0.assigned.sum(axis=0) > 0
    gain_in = d0[inside & ne].mean() - d1[inside & ne].mean()
    gain_out = d0[~inside & ne].mean() - d1[~inside & ne].mean()
    assert gain_in > 0
    assert gain_in > gain_out


def test_region_freezes_absent_structures(phantom):
    vol, spec, cam = phantom
    a = analyze(vol, spec, cam, build_cache=False)
    mask = np.zeros((PX, PX), bool)
    mask[2, 24] = True  # a ray at the top of the head: skin only
    present = [bool(int(a.present[2, 24]) >> k & 1) for k in range(len(spec.structures))]
    assert not all(present)
    r = optimize(vol, spec, cam, stages=("opacity",), region=mask, max_iter=3)
    for k, (before, after) in enumerate(zip(spec.structures, r.spec.structures, strict=True)):
        if not present[k]:
            assert after.opacity == before.opacity


def _view_E(vol, spec, cam):
    a = analyze(vol, spec, cam, build_cache=False)
    v, s, t = visibility(a, spec), shape(a, spec), transparency(a, spec)
    return v.E_v + s.E_s + t.E_t


def _walls():
    """A core (importance 0.9) between two pairs of walls: the z walls cover it seen from the
    front (azimuth 0), the x walls seen from the side (azimuth 90); all start at 0.9."""
    n = 40
    z, y, x = np.mgrid[:n, :n, :n]
    data = np.zeros((n, n, n), np.uint8)
    data[((z >= 3) & (z < 7)) | ((z >= n - 7) & (z < n - 3))] = 100
    data[((x >= 3) & (x < 7)) | ((x >= n - 7) & (x < n - 3))] = 150
    data[(x - n / 2) ** 2 + (y - n / 2) ** 2 + (z - n / 2) ** 2 < 64] = 220
    spec = StructureSpec(
        (
            Structure("wall z", 0.3, (0.9, 0.8, 0.6), range=(80, 120)),
            Structure("wall x", 0.3, (0.6, 0.8, 0.9), range=(130, 170)),
            Structure("core", 0.9, (1.0, 0.3, 0.2), range=(200, 240)),
        ),
        rendering=RenderSettings(shade=False),
    )
    return Volume(data), spec.with_opacities([0.9, 0.9, 0.9])


def test_two_views_lower_the_worse_view_more_than_one():
    """Optimised from the front alone, the x walls still hide the core from the side; with
    both views the worse of the two views ends far lower."""
    vol, spec = _walls()
    front, side = (Camera.from_view(vol.bounds, azimuth=a, width=PX, height=PX) for a in (0, 90))
    one = optimize(vol, spec, front, stages=("opacity",), max_iter=5, seed=0)
    two = optimize(vol, spec, front, cameras=[side], stages=("opacity",), max_iter=5, seed=0)
    e_one = [_view_E(vol, one.spec, c) for c in (front, side)]
    e_two = [_view_E(vol, two.spec, c) for c in (front, side)]
    assert e_one[1] > e_one[0]  # the side is the worse view after the front alone
    # measured as the optimiser reads enclosers (D7, also without a cache): the worse view
    # 1.296 after the front alone, 1.239 with both views
    assert max(e_two) < max(e_one) - 0.04
    assert e_two[1] < e_one[1] - 0.04
    ops_two = np.array([s.opacity for s in two.spec.structures])
    # the x walls, which hide the core from the side, are lowered well below their start (0.9);
    # since E_s and E_t read the same at every size (D9) the front view alone lowers them too
    assert ops_two[1] < 0.9 - 0.3
    assert two.final["E"] <= two.initial["E"]


def test_a_visibility_target_moves_the_share_toward_it(phantom):
    vol, spec, cam = phantom
    plain = optimize(vol, spec, cam, stages=("opacity",), max_iter=5, seed=0)
    shares = {}
    for goal in (0.2, 0.5):
        t = optimize(vol, spec, cam, stages=("opacity",), max_iter=5, seed=0,
                     targets={"tumour": {"visibility": goal}})  # fmt: skip
        target = t.initial["target_share"]["tumour"]
        start, end = t.initial["visible_share"]["tumour"], t.final["visible_share"]["tumour"]
        assert target != plain.initial["target_share"]["tumour"]
        assert abs(end - target) < 0.5 * abs(start - target)
        assert abs(end - target) < abs(plain.final["visible_share"]["tumour"] - target)
        shares[goal] = end
    assert shares[0.5] > shares[0.2] + 0.03
    t = optimize(vol, spec, cam, stages=("opacity",), max_iter=1,
                 targets={"tumour": {"transparency": 0.2}})  # fmt: skip
    assert t.initial["E_t"] != plain.initial["E_t"]


def test_colour_stage_changes_colours_and_lowers_E_t(phantom, stage1):
    """Fails when the colour stage does nothing: E_t must fall and some colour change."""
    vol, _, cam = phantom
    r = optimize(vol, stage1.spec, cam, stages=("colour",), max_iter=3, seed=2)
    assert r.stages[0].message == "improved"
    assert r.final["E_t"] < r.initial["E_t"] - 5e-4
    moved = [np.abs(np.subtract(a.colour, b.colour)).max()
             for a, b in zip(stage1.spec.structures, r.spec.structures, strict=True)]  # fmt: skip
    assert max(moved) > 0.01


def test_stage_registry_is_replaceable(phantom):
    vol, spec, cam = phantom

    class Frozen(OpacityStage):
        def encode(self, params, active):
            return super().encode(params, np.zeros_like(active))

    register_stage("frozen", Frozen)
    try:
        r = optimize(vol, spec, cam, stages=("frozen",), max_iter=2)
    finally:
        del STAGES["frozen"]
    assert [s.opacity for s in r.spec.structures] == [0.3] * 6
    assert r.final["E"] == r.initial["E"]
    assert r.status == 0


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"weights": (0, 0, 0)}, "weights"),
        ({"weights": (1, -1, 1)}, "weights"),
        ({"weights": (1, 1)}, "weights"),
        ({"stages": ("opacity", "sharpness")}, "stages"),
        ({"stages": ()}, "stages"),
        ({"region": ("rect", 100, 100, 120, 120)}, "region"),
        ({"region": ("circle", -50, -50, 3)}, "region"),
        ({"region": np.zeros((PX, PX), bool)}, "region"),
        ({"region": np.ones((PX, PX + 1), bool)}, "region"),
        ({"region": ("square", 1, 2, 3)}, "region"),
        ({"targets": {"liver": {"visibility": 0.5}}}, "targets"),
        ({"targets": {"skin": {"visibility": 1.5}}}, "targets"),
        ({"targets": {"skin": {"shine": 0.5}}}, "targets"),
        ({"calibration": ([0.0, 0.5, 1.0], [0.0, 0.8, 0.4])}, "calibration"),
        ({"calibration": ([0.0, 0.0], [0.0, 1.0])}, "calibration"),
        ({"max_iter": 0}, "max_iter"),
        ({"resolution": 4}, "resolution"),
        ({"seed": -1}, "seed"),
        ({"opacity_floor": 2.0}, "opacity_floor"),
        ({"coverage_keep": 1.5}, "coverage_keep"),
        ({"coverage_keep": 0.9, "opacity_floor": 0.5}, "coverage_keep"),
        ({"callback": 3}, "callback"),
        ({"cameras": [None]}, "cameras"),
    ],
)
def test_bad_input(phantom, kwargs, name):
    vol, spec, cam = phantom
    with pytest.raises(DVRInputError, match=name):
        optimize(vol, spec, cam, **kwargs)


def test_params_toward_mixes_and_keeps_the_light_a_unit_vector(phantom):
    _, spec, _ = phantom
    a = Params.from_spec(spec)
    b = a.replace(opacities=np.ones(len(spec.structures)), light=[1.0, 0.0, 0.0])
    assert a.toward(b, 0.0).same(a)
    assert np.allclose(a.toward(b, 1.0).opacities, 1.0)
    half = a.toward(b, 0.5)
    assert np.allclose(half.opacities, 0.5 * (a.opacities + 1.0))
    assert np.linalg.norm(half.light) == pytest.approx(1.0)
    assert half.light[0] == pytest.approx(half.light[2])  # halfway between x and the headlight z


def test_a_step_that_fails_at_full_size_is_retried_shorter(monkeypatch, phantom):
    """The hard check at the user's resolution keeps half a step when the whole one fails."""
    vol, spec, cam = phantom
    kw = {"stages": ("opacity",), "max_iter": 3, "seed": 3, "resolution": 24}
    full = optimize(vol, spec, cam, **kw)
    assert full.stages[0].message == "improved"
    whole = np.array([s.render_opacity for s in full.spec.structures])
    real_terms = Problem.terms

    def terms(self, params, **kwargs):  # the whole step breaks E at full size, shorter ones not
        t = real_terms(self, params, **kwargs)
        if self.caches[0].camera.width == cam.width and np.allclose(params.opacities, whole):
            t = dict(t, E=t["E"] + 10.0)
        return t

    monkeypatch.setattr(Problem, "terms", terms)
    res = optimize(vol, spec, cam, **kw)
    rec = res.stages[0]
    assert rec.accepted
    assert "cut to 50%" in rec.message
    start = np.full(len(spec.structures), 0.3)
    got = np.array([s.render_opacity for s in res.spec.structures])
    assert np.allclose(got, start + 0.5 * (whole - start))
    assert res.final["E"] < res.initial["E"]
