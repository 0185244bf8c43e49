"""|H| kept in 8^3 pages (CurvaturePages): the same values, the same analyses, less memory."""

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.curvature_field import PAGE, CurvaturePages, curvature_source
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.phantom import make_phantom


def _sparse(shape, where):
    out = np.zeros(shape, np.float32)
    for (z, y, x), v in where.items():
        out[z, y, x] = v
    return out


def test_pages_hold_only_what_is_not_zero():
    # 10 x 20 x 17: 2 x 3 x 3 pages, the last ones cut by the volume's edge
    dense = _sparse((10, 20, 17), {(9, 19, 16): 1.5, (0, 0, 0): 0.25, (1, 2, 3): 4.0})
    paged = CurvaturePages.from_dense(dense)
    assert paged.index.shape == (2, 3, 3)
    assert paged.pages.shape == (2, PAGE, PAGE, PAGE)  # (0,0,0) and (1,2,3) share a page
    assert int((paged.index >= 0).sum()) == 2
    assert paged.index[0, 0, 0] >= 0
    assert paged.index[1, 2, 2] >= 0
    assert paged.nbytes < dense.nbytes
    np.testing.assert_array_equal(np.asarray(paged), dense)
    empty = CurvaturePages.from_dense(np.zeros((9, 9, 9), np.float32))
    assert empty.pages.shape[0] == 0
    assert (empty.index == -1).all()
    np.testing.assert_array_equal(np.asarray(empty), 0.0)


@pytest.mark.parametrize(
    "extent", [((0, 10), (0, 20), (0, 17)), ((3, 9), (5, 19), (7, 16)), ((9, 10), (0, 1), (16, 17))]
)
def test_a_piece_is_the_slice_of_the_dense_volume(extent):
    rng = np.random.default_rng(0)
    dense = np.where(rng.random((10, 20, 17)) < 0.05, rng.random((10, 20, 17)), 0).astype(
        np.float32
    )
    piece = CurvaturePages.from_dense(dense).piece(extent)
    (z0, z1), (y0, y1), (x0, x1) = extent
    np.testing.assert_array_equal(piece, dense[z0:z1, y0:y1, x0:x1])
    assert piece.dtype == np.float32
    assert piece.flags.c_contiguous


def test_curvature_source_pages_the_volume():
    vol, spec = make_phantom(size=40)
    src = curvature_source(vol, spec)
    assert isinstance(src, CurvaturePages)
    np.testing.assert_array_equal(np.asarray(src), curvature_volume(vol, spec)[0])


@pytest.mark.parametrize("build_cache", [False, True])
def test_analyses_with_pages_equal_those_with_the_dense_volume(build_cache):
    vol, spec = make_phantom(size=40)
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=40, height=40)
    dense = curvature_volume(vol, spec)[0]
    paged = CurvaturePages.from_dense(dense)
    a = analyze(vol, spec, cam, curvature=dense, build_cache=build_cache)
    b = analyze(vol, spec, cam, curvature=paged, build_cache=build_cache)
    assert np.nanmax(a.curvature) > 0  # the test reads some curvature
    np.testing.assert_array_equal(b.image, a.image)
    np.testing.assert_array_equal(b.curvature, a.curvature)
    c = analyze(vol, spec, cam, curvature=paged, build_cache=build_cache, brick=(16, 16, 16))
    assert c.stats["bricks"] > 1
    np.testing.assert_allclose(c.curvature, a.curvature, atol=1e-6)
    np.testing.assert_allclose(c.image, a.image, atol=1e-6)
    if build_cache:  # re-composited entries behind termination read their |H| from the pages
        ops = np.full(len(spec.structures), 0.3)
        again = reevaluate(b.cache, opacities=ops)
        fresh = analyze(vol, spec.with_opacities(ops), cam, curvature=dense)
        np.testing.assert_allclose(again.curvature, fresh.curvature, atol=1e-6)


def test_bad_pages_are_refused_by_name():
    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    dense = curvature_volume(vol, spec)[0]
    bad = CurvaturePages.from_dense(np.where(dense > 0, np.nan, 0).astype(np.float32))
    with pytest.raises(DVRInputError, match="curvature: values must be finite"):
        analyze(vol, spec, cam, curvature=bad)
    small = CurvaturePages.from_dense(dense[1:])
    with pytest.raises(DVRInputError, match="curvature: a field of shape"):
        analyze(vol, spec, cam, curvature=small)
    negative = CurvaturePages.from_dense(-dense)  # |H| is read: the sign is dropped
    got = analyze(vol, spec, cam, curvature=negative)
    want = analyze(vol, spec, cam, curvature=dense)
    np.testing.assert_array_equal(got.curvature, want.curvature)


def test_numpy_and_numba_page_alike(monkeypatch):
    rng = np.random.default_rng(1)
    shape = (19, 9, 26)
    dense = np.where(rng.random(shape) < 0.03, rng.random(shape), 0).astype(np.float32)
    fast = CurvaturePages.from_dense(dense)
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    slow = CurvaturePages.from_dense(dense)
    np.testing.assert_array_equal(slow.index, fast.index)
    np.testing.assert_array_equal(slow.pages, fast.pages)
    extent = ((2, 17), (1, 9), (5, 25))
    np.testing.assert_array_equal(slow.piece(extent), dense[2:17, 1:9, 5:25])


def test_pages_whose_index_points_outside_them_are_refused():
    dense = np.zeros((9, 9, 9), np.float32)
    dense[0, 0, 0] = 1.0
    good = CurvaturePages.from_dense(dense)
    bad_index = good.index.copy()
    bad_index[1, 1, 1] = len(good.pages)  # one past the last page
    with pytest.raises(DVRInputError, match="page numbers"):
        CurvaturePages(bad_index, good.pages, good.shape)
    with pytest.raises(DVRInputError, match="need an index of shape"):
        CurvaturePages(good.index[:1], good.pages, good.shape)
