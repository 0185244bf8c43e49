"""Bricked analysis (issue 17): brick by brick in view order equals the whole walk."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures.combined import all_measures
from dvr_perception.rays import bricks
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.io import load_spec
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.volume.io import load_volume

pytest.importorskip("numba")

BUFFERS = ("rgba", "image", "visible", "assigned", "present", "curvature",
           "importance_accumulated")  # fmt: skip


def _max_diff(a, b) -> float:
    return max(
        float(np.abs(getattr(a, f).astype(np.float64) - getattr(b, f).astype(np.float64)).max())
        for f in BUFFERS
        if getattr(a, f) is not None
    )


@pytest.fixture(scope="module")
def phantom():
    vol, spec = make_phantom(size=40)
    return vol, spec, curvature_volume(vol, spec)[0]


@pytest.mark.parametrize("brick", [(39, 39, 39), (20, 39, 39), (7, 9, 11), (3, 40, 5)])
@pytest.mark.parametrize("view", [(35.0, 25.0, False), (-120.0, -40.0, True)])
def test_bricked_equals_whole_on_the_phantom(phantom, brick, view):
    vol, spec, curv = phantom
    cam = Camera.from_view(vol.bounds, width=48, height=40, azimuth=view[0], elevation=view[1])
    if view[2]:
        cam = Camera(cam.position, cam.focal_point, cam.view_up, parallel_projection=True,
                     parallel_scale=30.0, width=48, height=40)  # fmt: skip
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    parts = bricks.analyze_bricked(vol, spec, cam, brick=brick, curvature=curv)
    assert whole.accumulated.max() > 0.5  # the view sees the phantom
    assert _max_diff(whole, parts) <= 1e-6
    assert np.array_equal(whole.cache.count, parts.cache.count)
    assert np.array_equal(whole.cache.lut, parts.cache.lut)
    # a re-evaluation after new opacities, and after a new light (shading re-read per brick)
    ops = np.linspace(0.9, 0.05, len(spec.structures))
    assert _max_diff(reevaluate(whole.cache, opacities=ops),
                     reevaluate(parts.cache, opacities=ops)) <= 1e-6  # fmt: skip
    light = (0.4, -0.3, 0.8)
    assert _max_diff(reevaluate(whole.cache, light_direction=light),
                     reevaluate(parts.cache, light_direction=light)) <= 1e-6  # fmt: skip


@pytest.mark.parametrize("room", ["memo", "codes", "none"])
def test_a_new_light_reshades_from_what_memory_allows(phantom, monkeypatch, room):
    """Derived volumes kept between analyses, or only normal codes, or nothing (re-read)."""
    vol, spec, curv = phantom
    if room != "memo":
        monkeypatch.setattr(bricks, "MEMO_SHARE", 0.0)
    if room == "none":
        monkeypatch.setattr(bricks, "KEEP_CODES_SHARE", 0.0)
    cam = Camera.from_view(vol.bounds, width=40, height=40, azimuth=-20.0, elevation=35.0)
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    for _ in range(2):  # the second analysis reuses the memo when there is one
        parts = bricks.analyze_bricked(vol, spec, cam, brick=(9, 13, 20), curvature=curv)
        assert _max_diff(whole, parts) <= 1e-6
    assert (vol in bricks._MEMO) == (room == "memo")
    light = (-0.5, 0.2, 0.7)
    assert _max_diff(reevaluate(whole.cache, light_direction=light),
                     reevaluate(parts.cache, light_direction=light)) <= 1e-6  # fmt: skip
    bricks._MEMO.pop(vol, None)


@pytest.mark.parametrize("room", ["memo", "codes", "none"])
def test_several_cameras_share_one_pass_and_equal_their_own_analyses(phantom, monkeypatch,
                                                                      room):  # fmt: skip
    """One view at three resolutions (one pass) and an opposite view (a pass of its own)."""
    vol, spec, curv = phantom
    if room != "memo":
        monkeypatch.setattr(bricks, "MEMO_SHARE", 0.0)
    if room == "none":
        monkeypatch.setattr(bricks, "KEEP_CODES_SHARE", 0.0)
    cams = [Camera.from_view(vol.bounds, width=n, height=n, azimuth=30.0, elevation=-25.0)
            for n in (44, 24, 12)]  # fmt: skip
    cams.append(Camera.from_view(vol.bounds, width=20, height=20, azimuth=210.0, elevation=25.0))
    orders = {
        tuple(bricks.view_order(bricks.split(vol.data.shape, (9, 13, 20)), st))
        for st in (
            bricks.RayState.start(bricks.Geometry.of(vol), spec, c, scalar_range=(0.0, 255.0))
            for c in cams
        )
    }
    assert len(orders) == 2  # the fourth camera meets the bricks in another order
    together = bricks.analyze_bricked_views(vol, spec, cams, brick=(9, 13, 20), curvature=curv)
    light = (0.3, 0.5, 0.8)
    for cam, got in zip(cams, together, strict=True):
        whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
        assert _max_diff(whole, got) <= 1e-6
        assert np.array_equal(whole.cache.lut, got.cache.lut)
        assert _max_diff(reevaluate(whole.cache, light_direction=light),
                         reevaluate(got.cache, light_direction=light)) <= 1e-6  # fmt: skip
    bricks._MEMO.pop(vol, None)


def test_the_memo_serves_analyses_with_and_without_curvature(phantom, monkeypatch):
    """Derived volumes are kept for any curvature; the curvature pieces for their field."""
    from dvr_perception.rays.curvature_field import CurvatureField

    vol, spec, curv = phantom
    field = CurvatureField(vol, spec)
    cam = Camera.from_view(vol.bounds, width=24, height=24, azimuth=15.0, elevation=20.0)
    calls = []
    real = bricks.derive
    monkeypatch.setattr(bricks, "derive", lambda *a: calls.append(1) or real(*a))
    a1 = bricks.analyze_bricked(vol, spec, cam, brick=(13, 13, 13), curvature=field)
    first = len(calls)
    assert first == len(bricks.split(vol.data.shape, (13, 13, 13)))
    a2 = bricks.analyze_bricked(vol, spec, cam, brick=(13, 13, 13))  # no curvature
    a3 = bricks.analyze_bricked(vol, spec, cam, brick=(13, 13, 13), curvature=field)
    assert len(calls) == first  # derived once, for all three analyses
    assert len(bricks._MEMO[vol]["curvature"]) == first  # the pieces survived the second
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    assert _max_diff(whole, a1) <= 1e-6
    assert _max_diff(whole, a3) <= 1e-6
    assert np.array_equal(whole.rgba, a2.rgba)
    assert not a2.curvature.any()
    bricks._MEMO.pop(vol, None)


def test_every_sample_belongs_to_exactly_one_brick(phantom):
    vol, spec, _ = phantom
    cam = Camera.from_view(vol.bounds, width=32, height=32, azimuth=33.0, elevation=-61.0)
    state = bricks.RayState.start(bricks.Geometry.of(vol), spec, cam,
                                  scalar_range=vol.scalar_range)  # fmt: skip
    _, nb = bricks._kernels()
    seg = state.seg
    n = seg["n"].astype(np.int64)
    covered = np.zeros(len(n), np.int64)
    runs = []
    for br in bricks.split(vol.data.shape, (6, 13, 8)):
        lo = np.array([c[0] for c in br.cells[::-1]], np.int64)
        hi = np.array([c[1] for c in br.cells[::-1]], np.int64)
        j0 = np.empty(len(n), np.int64)
        j1 = np.empty(len(n), np.int64)
        nb.brick_ranges(seg["a"], seg["b"], seg["t"], seg["n"], state.tables["step"], lo, hi,
                        np.array(vol.dims, np.int64), j0, j1)  # fmt: skip
        covered += j1 - j0
        runs.append((j0, j1))
    assert np.array_equal(covered, n)  # no sample twice, none left out
    # and the runs of one ray do not overlap (they tile [0, n))
    r = int(np.argmax(n))
    spans = sorted((int(a[r]), int(b[r])) for a, b in runs if b[r] > a[r])
    assert spans[0][0] == 0
    assert spans[-1][1] == n[r]
    assert all(s1[1] == s2[0] for s1, s2 in itertools.pairwise(spans))


def test_the_state_travels_between_processes(phantom):
    """Half the bricks in one state, its arrays loaded into another for the rest (MPI ranks)."""
    vol, spec, curv = phantom
    cam = Camera.from_view(vol.bounds, width=40, height=40, azimuth=70.0, elevation=10.0)
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=False)
    geo = bricks.Geometry.of(vol)
    first = bricks.RayState.start(geo, spec, cam, scalar_range=vol.scalar_range)
    pieces = bricks.split(vol.data.shape, (39, 20, 39))
    pieces = [pieces[i] for i in bricks.view_order(pieces, first)]
    cut = len(pieces) // 2
    for br, piece, off, cv in bricks._pieces(vol, pieces[:cut], curv):
        bricks.walk(first, piece, br, offset=off, curvature=cv, build_cache=False)
    second = bricks.RayState.start(geo, spec, cam, scalar_range=vol.scalar_range)
    second.load({k: v.copy() for k, v in first.arrays().items()})
    for br, piece, off, cv in bricks._pieces(vol, pieces[cut:], curv):
        bricks.walk(second, piece, br, offset=off, curvature=cv, build_cache=False)
    assert _max_diff(whole, bricks.finish(second)) <= 1e-6
    with pytest.raises(DVRInputError, match="state 'st'"):
        second.load({**first.arrays(), "st": np.zeros((3, 7))})


def test_bad_pieces_and_bricks_are_named(phantom):
    vol, spec, _ = phantom
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    state = bricks.RayState.start(bricks.Geometry.of(vol), spec, cam,
                                  scalar_range=vol.scalar_range)  # fmt: skip
    br = bricks.Brick(((10, 20), (0, 39), (0, 39)))
    small = bricks.Volume(vol.data[10:21], vol.spacing, vol.origin)
    with pytest.raises(DVRInputError, match=r"piece: axis z holds voxels 10\.\.20"):
        bricks.walk(state, small, br, offset=(10, 0, 0))
    with pytest.raises(DVRInputError, match="brick: expected three positive"):
        bricks.split(vol.data.shape, (0, 4, 4))
    with pytest.raises(DVRInputError, match="curvature: expected float32"):
        bricks.walk(state, vol, br, curvature=np.zeros((2, 2, 2), np.float32))


def test_piece_extent_maps_to_the_cells_it_owns():
    whole = (0, 63, 0, 63, 0, 63)
    a = bricks.from_piece_extent((0, 63, 0, 63, 0, 32), whole)
    b = bricks.from_piece_extent((0, 63, 0, 63, 32, 63), whole)
    assert a.cells == ((0, 32), (0, 63), (0, 63))
    assert b.cells == ((32, 63), (0, 63), (0, 63))
    assert a.ncells + b.ncells == 63**3  # every cell once
    assert a.voxels((64, 64, 64)) == ((0, 34), (0, 64), (0, 64))  # one ghost layer past 32


VIEWS = ((35.0, 25.0), (-120.0, -40.0))


@pytest.mark.parametrize("name", ["engine", "cthead", "tooth"])
def test_bricked_equals_whole_on_shared_volumes(shared_data, name):
    """Issue 17's check: two oblique views, three brick sizes (the last cuts every structure)."""
    vol = load_volume(shared_data / f"{name}.nhdr")
    spec = load_spec(f"state_files/{name}.json")
    curv = curvature_volume(vol, spec)[0]
    z, y, x = vol.data.shape
    sizes = ((z, y // 2, x), (64, 64, 64), (23, 29, 31))
    for az, el in VIEWS:
        cam = Camera.from_view(vol.bounds, width=64, height=64, azimuth=az, elevation=el)
        whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
        e_whole = all_measures(whole, spec)
        for size in sizes:
            parts = bricks.analyze_bricked(vol, spec, cam, brick=size, curvature=curv)
            assert parts.stats["bricks"] > 1
            assert _max_diff(whole, parts) <= 1e-5, (name, az, size)
            e_parts = all_measures(parts, spec)
            for term in ("E_v", "E_s", "E_t"):
                a = getattr(getattr(e_whole, _RESULT[term]), term)
                b = getattr(getattr(e_parts, _RESULT[term]), term)
                assert abs(a - b) <= 1e-6, (name, az, size, term)
        ops = np.linspace(0.8, 0.2, len(spec.structures))
        assert _max_diff(reevaluate(whole.cache, opacities=ops),
                         reevaluate(parts.cache, opacities=ops)) <= 1e-5  # fmt: skip


_RESULT = {"E_v": "visibility", "E_s": "shape", "E_t": "transparency"}


def test_the_one_pass_merge_of_the_arena_equals_brick_by_brick(phantom, monkeypatch):
    """Entries taken from the arena are merged in one pass (``place_all``), as brick by brick."""
    vol, spec, curv = phantom
    cam = Camera.from_view(vol.bounds, width=40, height=32, azimuth=30.0, elevation=20.0)
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    calls = {"all": 0, "one": 0}
    nb = bricks._kernels()[1]
    real_all, real_one = nb.place_all, nb.place

    def place_all(*args):
        calls["all"] += 1
        return real_all(*args)

    def place(*args):
        calls["one"] += 1
        return real_one(*args)

    monkeypatch.setattr(nb, "place_all", place_all)
    monkeypatch.setattr(nb, "place", place)
    bricks._ARENA_BUFFERS.clear()  # the first analysis: fresh arrays, merged brick by brick
    first = bricks.analyze_bricked(vol, spec, cam, brick=(9, 13, 20), curvature=curv)
    assert calls == {"all": 0, "one": 30}
    second = bricks.analyze_bricked(vol, spec, cam, brick=(9, 13, 20), curvature=curv)
    assert calls == {"all": 1, "one": 30}  # the arena holds them now: one pass
    for parts in (first, second):
        assert _max_diff(whole, parts) <= 1e-6
        for name in ("start", "count", "lut"):
            assert np.array_equal(getattr(whole.cache, name), getattr(parts.cache, name)), name
        assert np.array_equal(whole.cache.lazy["steps"], parts.cache.lazy["steps"])
    for name in ("shading", "curvature"):  # (lazily shaded: the same entries set in both)
        assert np.array_equal(getattr(first.cache, name), getattr(second.cache, name)), name


def test_a_partial_memo_keeps_the_front_bricks_of_renders(phantom, monkeypatch):
    """Too little room for every brick: the front ones are kept, the others derived again."""
    vol, spec, _ = phantom
    cam = Camera.from_view(vol.bounds, width=32, height=32, azimuth=-35.0, elevation=15.0)
    size = (13, 13, 13)
    every = bricks.split(vol.data.shape, size)
    one = max(np.prod([b - a for a, b in br.voxels(vol.data.shape)]) for br in every)
    bricks._MEMO.pop(vol, None)
    monkeypatch.setattr(bricks, "_room", lambda *a: 7.5 * 5 * one)  # about 5 of 27 bricks
    calls = []
    real, reached, compact = bricks.derive, bricks._derive_reached, bricks._derive_compact
    monkeypatch.setattr(bricks, "derive", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(bricks, "_derive_reached", lambda *a: calls.append(1) or reached(*a))
    monkeypatch.setattr(bricks, "_derive_compact", lambda *a: calls.append(1) or compact(*a))
    whole = analyze(vol, spec, cam, build_cache=False, occlusion_free=False)
    kw = {"brick": size, "build_cache": False, "occlusion_free": False}
    first = bricks.analyze_bricked(vol, spec, cam, **kw)
    walked = len(calls)
    memo = bricks._MEMO[vol]["bricks"]
    assert isinstance(memo, bricks._PartialMemo)
    assert 0 < len(memo) < walked
    assert memo.used <= memo.budget
    # compact entries (no voxel records): about 2 bytes a voxel, so more than 7.5 * 5 / 7 fit
    assert all(d[0] is None for d in memo.values())
    assert len(memo) > 5
    assert memo.used <= 2.1 * sum(
        np.prod([b - a for a, b in br.voxels(vol.data.shape)]) for br in memo
    )
    second = bricks.analyze_bricked(vol, spec, cam, **kw)
    assert len(calls) - walked == walked - len(memo)  # the kept bricks are not derived again
    for got in (first, second):
        assert np.array_equal(whole.rgba, got.rgba)
    # an analysis with a cache reads the kept bricks but adds none (its codes use the room)
    frame = bricks.analyze_bricked(vol, spec, cam, brick=size)
    assert len(memo) == len(bricks._MEMO[vol]["bricks"])
    full = analyze(vol, spec, cam, build_cache=True)
    assert _max_diff(full, frame) <= 1e-6
    light = (0.2, -0.6, 0.7)
    assert _max_diff(reevaluate(full.cache, light_direction=light),
                     reevaluate(frame.cache, light_direction=light)) <= 1e-6  # fmt: skip
    bricks._MEMO.pop(vol, None)


@pytest.mark.parametrize("brick", [(7, 9, 11), (20, 39, 39)])
@pytest.mark.parametrize("view", [(35.0, 25.0), (-150.0, -40.0), (90.0, 80.0)])
def test_codes_only_where_a_walk_without_a_cache_shades_equal_every_code(phantom, monkeypatch,
                                                                          brick, view):  # fmt: skip
    """A render or measure derives the normal codes only where it can shade: the same result."""
    vol, spec, curv = phantom
    cam = Camera.from_view(vol.bounds, width=40, height=36, azimuth=view[0], elevation=view[1])
    monkeypatch.setattr(bricks, "_memo", lambda *a, **kw: (None, None))  # derived every time
    calls = []
    real = bricks._derive_reached
    monkeypatch.setattr(bricks, "_derive_reached", lambda *a: calls.append(1) or real(*a))
    for kw in ({"build_cache": False, "occlusion_free": False},
               {"build_cache": False, "curvature": curv}):  # fmt: skip
        got = {}
        for reached in (False, True):
            monkeypatch.setattr(bricks, "REACHED_CODES", reached)
            got[reached] = bricks.analyze_bricked(vol, spec, cam, brick=brick, **kw)
        whole = analyze(vol, spec, cam, **kw)
        assert whole.accumulated.max() > 0.5
        for name in BUFFERS:
            a, b = getattr(got[False], name), getattr(got[True], name)
            if a is not None:
                assert np.array_equal(a, b, equal_nan=True), name
        assert _max_diff(whole, got[True]) <= 1e-6
    assert calls  # the reached codes were used


@pytest.mark.parametrize("compact", [True, False])
def test_compact_and_whole_memo_entries_give_the_same_renders(phantom, monkeypatch, compact):
    """A partial memo's entries without voxel records: the same images, frames and lights."""
    vol, spec, curv = phantom
    monkeypatch.setattr(bricks, "COMPACT_MEMO", compact)
    cam = Camera.from_view(vol.bounds, width=30, height=26, azimuth=50.0, elevation=-30.0)
    size = (9, 11, 13)
    one = max(np.prod([b - a for a, b in br.voxels(vol.data.shape)])
              for br in bricks.split(vol.data.shape, size))  # fmt: skip
    bricks._MEMO.pop(vol, None)
    monkeypatch.setattr(bricks, "_room", lambda *a: 7.5 * 4 * one)  # a few bricks only
    kw = {"brick": size, "build_cache": False, "occlusion_free": False}
    whole = analyze(vol, spec, cam, build_cache=False, occlusion_free=False)
    for _ in range(2):  # the second from the memo
        got = bricks.analyze_bricked(vol, spec, cam, **kw)
        assert np.array_equal(whole.rgba, got.rgba)
    memo = bricks._MEMO[vol]["bricks"]
    assert len(memo) > 0
    assert all((d[0] is None) == compact for d in memo.values())
    full = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    frame = bricks.analyze_bricked(vol, spec, cam, brick=size, curvature=curv)
    assert _max_diff(full, frame) <= 1e-6
    light = (-0.3, 0.6, 0.7)
    assert _max_diff(reevaluate(full.cache, light_direction=light),
                     reevaluate(frame.cache, light_direction=light)) <= 1e-6  # fmt: skip
    bricks._MEMO.pop(vol, None)
