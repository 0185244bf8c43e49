"""Progress callbacks inside the long steps (issue 19): curvature volume and ray analysis.

Known answers: the fractions start at 0.0, never decrease, end at 1.0 with several values in
between and at most about 100 calls; the results are bit for bit those without a callback; a
callback raising StopIteration cancels the step with one DVRCancelled.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from dvr_perception._progress import Reporter
from dvr_perception.errors import DVRCancelled, DVRInputError
from dvr_perception.rays import curvature as curvature_mod
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.curvature_field import CurvatureField
from dvr_perception.rays.engine import analyze, analyze_views
from dvr_perception.structures.phantom import make_phantom

pytest.importorskip("numba")

BUFFERS = ("rgba", "image", "visible", "assigned", "present", "curvature",
           "importance_accumulated")  # fmt: skip


@pytest.fixture(scope="module")
def scene():
    vol, spec = make_phantom(size=40)
    cam = Camera.from_view(vol.bounds, width=128, height=128, azimuth=30.0, elevation=20.0)
    return vol, spec, cam, curvature_volume(vol, spec)[0]


def _check_fractions(got, *, inner: int):
    """The contract of every step's progress: 0.0 first, non-decreasing, 1.0 last."""
    assert got[0] == 0.0
    assert got[-1] == 1.0
    assert all(b >= a for a, b in itertools.pairwise(got)), got
    assert len([f for f in got if 0.0 < f < 1.0]) >= inner, got
    assert len(got) <= 102


def _same(a, b) -> None:
    for name in BUFFERS:
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name


@pytest.mark.parametrize("threads", [1, 2])
def test_curvature_reports_inside_and_gives_the_same_bits(scene, monkeypatch, threads):
    vol, spec, _, plain = scene
    monkeypatch.setattr(curvature_mod, "_BAND_VOXELS", 1 << 12)  # several y bands
    monkeypatch.setattr(curvature_mod, "_threads", lambda: threads)
    got: list[float] = []
    curv, boundary = curvature_volume(vol, spec, progress=got.append)
    # one thread: every z slice reports; two: the calling thread follows the bands
    _check_fractions(got, inner=10 if threads == 1 else 2)
    assert np.array_equal(curv, plain)
    assert np.array_equal(boundary, curvature_volume(vol, spec)[1])


@pytest.mark.parametrize("threads", [1, 2])
def test_curvature_stops_when_the_callback_raises_stop_iteration(scene, monkeypatch, threads):
    vol, spec, _, plain = scene
    monkeypatch.setattr(curvature_mod, "_BAND_VOXELS", 1 << 12)
    monkeypatch.setattr(curvature_mod, "_threads", lambda: threads)
    seen: list[float] = []

    def stop(fraction):
        seen.append(fraction)
        if fraction > 0.0:
            raise StopIteration

    with pytest.raises(DVRCancelled, match=r"progress: cancelled \(the callback raised Stop"):
        curvature_volume(vol, spec, progress=stop)
    assert seen[-1] < 1.0  # stopped before the end
    assert np.array_equal(curvature_volume(vol, spec)[0], plain)  # nothing left behind


@pytest.mark.parametrize(("brick", "inner"), [(None, 3), ((9, 13, 20), 20), ((20, 39, 39), 3)])
def test_analysis_reports_inside_and_gives_the_same_bits(scene, brick, inner):
    vol, spec, cam, curv = scene
    plain = analyze(vol, spec, cam, curvature=curv, brick=brick, build_cache=True)
    got: list[float] = []
    res = analyze(
        vol, spec, cam, curvature=curv, brick=brick, progress=got.append, build_cache=True
    )
    # whole: set-up, then 4 groups of 16 chunks (128 x 128 pixels: 64 tiles); 30 bricks: after
    # each; 2 bricks: also inside each, after each group of chunks (one brick alone gives 1)
    _check_fractions(got, inner=inner)
    assert ("bricks" in res.stats) == (brick is not None)
    _same(plain, res)
    for name in ("start", "count", "lut", "shading", "curvature"):
        assert np.array_equal(getattr(plain.cache, name), getattr(res.cache, name)), name


def test_bricked_analysis_with_a_curvature_field_reports_each_brick(scene):
    vol, spec, cam, curv = scene
    field = CurvatureField(vol, spec)
    got: list[float] = []
    res = analyze(
        vol, spec, cam, curvature=field, brick=(13, 13, 13), progress=got.append, build_cache=True
    )
    _check_fractions(got, inner=20)  # 27 bricks, each with its curvature piece
    _same(analyze(vol, spec, cam, curvature=curv, brick=(13, 13, 13), build_cache=True), res)


def test_several_views_share_one_bar(scene):
    vol, spec, cam, curv = scene
    small = Camera.from_view(vol.bounds, width=32, height=32, azimuth=30.0, elevation=20.0)
    got: list[float] = []
    res = analyze_views(
        vol, spec, [cam, small], curvature=curv, progress=got.append, build_cache=True
    )
    _check_fractions(got, inner=4)
    _same(analyze(vol, spec, small, curvature=curv, build_cache=True), res[1])


@pytest.mark.parametrize("brick", [None, (9, 13, 20)])
def test_analysis_stops_when_the_callback_raises_stop_iteration(scene, brick):
    vol, spec, cam, curv = scene

    def stop(fraction):
        if fraction >= 0.3:
            raise StopIteration

    with pytest.raises(DVRCancelled, match="cancelled"):
        analyze(vol, spec, cam, curvature=curv, brick=brick, progress=stop, build_cache=True)
    # the engine's scratch and lock were released: the next analysis runs and is right
    _same(analyze(vol, spec, cam, curvature=curv, brick=brick, build_cache=True),
          analyze(vol, spec, cam, curvature=curv, brick=brick, build_cache=False))  # fmt: skip


def test_progress_must_be_callable(scene):
    vol, spec, cam, _ = scene
    with pytest.raises(DVRInputError, match="progress: expected a callable"):
        analyze(vol, spec, cam, progress=0.5, build_cache=True)
    with pytest.raises(DVRInputError, match="progress: expected a callable"):
        curvature_volume(vol, spec, progress="yes")


def test_reporter_thins_and_maps_sub_steps():
    got: list[float] = []
    r = Reporter(got.append)
    first, second = r.sub(0.0, 0.25), r.sub(0.25, 1.0)
    for i in range(1001):
        first(i / 1000)
    second(0.5)
    second(1.0)
    second(1.0)  # the end is sent once
    assert got[0] == 0.0
    assert got[-2:] == [0.625, 1.0]
    assert 25 <= len(got) <= 28  # steps of at least 0.01 over a quarter of the bar
    assert not Reporter(None)  # no listener: steps skip their reports
