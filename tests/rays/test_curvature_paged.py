"""|H| paged band by band as it is computed equals the paged dense result, bit for bit.

:func:`~dvr_perception.rays.curvature.curvature_pages` never holds the dense volume; its
pages, their numbers and values must be exactly those of
``CurvaturePages.from_dense(curvature_volume(...)[0])``: with numba and without, with bands
whose edges would cut pages, volumes whose sides are not multiples of 8, label structures
(several fields writing a band in turn) and boundary voxels found flat only at the end.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from dvr_perception.rays import _curvature_pages as P
from dvr_perception.rays import curvature as C
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_pages, curvature_volume
from dvr_perception.rays.curvature_field import CurvatureField, CurvaturePages, curvature_source
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.volume import Volume


def _spec(*ranges, labels=()):
    structs = [Structure(f"s{i}", 0.5, (1.0, 1.0, 1.0), range=r) for i, r in enumerate(ranges)]
    structs += [Structure(f"l{v}", 0.5, (1.0, 0.0, 0.0), label=v) for v in labels]
    return StructureSpec(tuple(structs), labels_file="l" if labels else None)


@pytest.fixture(params=["numba", "numpy"])
def backend(request, monkeypatch):
    """The curvature kernels: numba's, or none (the numpy twins)."""
    if request.param == "numpy":
        monkeypatch.setattr(C, "_curvature_kernels", lambda: None)
    else:
        assert C._curvature_kernels() is not None  # numba is a dependency of the core
    return request.param


@pytest.fixture
def bands(monkeypatch):
    """Record the y bands a paged run cuts (their first rows and row counts)."""
    seen = []

    class Recorded(P.BandPages):
        def __init__(self, nz, rows, nx, y0, nk, *, whole):
            seen.append((y0, rows, whole))
            super().__init__(nz, rows, nx, y0, nk, whole=whole)

    monkeypatch.setattr(C, "BandPages", Recorded)
    return seen


def _assert_same(vol, spec, **kwargs):
    """Paged as computed equals the dense result paged, and return the pages."""
    dense = curvature_volume(vol, spec, **kwargs)[0]
    want = CurvaturePages.from_dense(dense)
    index, pages = curvature_pages(vol, spec, **kwargs)
    np.testing.assert_array_equal(index, want.index)
    np.testing.assert_array_equal(pages, want.pages)
    assert index.dtype == np.int32
    assert pages.dtype == np.float32
    assert pages.flags.c_contiguous
    got = CurvaturePages(index, pages, vol.data.shape)
    np.testing.assert_array_equal(np.asarray(got), dense)
    return got, dense


@pytest.mark.parametrize("size", [40, 37])
def test_a_phantom_pages_as_its_dense_result(backend, size, bands):
    vol, spec = make_phantom(size=size)
    got, dense = _assert_same(vol, spec)
    assert dense.any()
    assert 0 < len(got.pages) < got.index.size  # some pages hold nothing
    assert bands
    assert not any(whole for _, _, whole in bands)  # the data alone: streamed


def test_band_edges_that_would_cut_pages(backend, bands, monkeypatch, noisy_blobs):
    # bands of 8 rows and three threads: the dense run cuts at rows 7, 15, 22, inside pages
    vol = noisy_blobs()
    spec = _spec((300, 900), (900, 4000))
    usual = curvature_volume(vol, spec)[0]  # one band
    monkeypatch.setattr(C, "_BAND_VOXELS", 1 << 10)
    monkeypatch.setattr(C, "_threads", lambda: 3)
    _, dense = _assert_same(vol, spec)
    assert [(y0, rows) for y0, rows, _ in bands] == [(0, 8), (8, 8), (16, 8), (24, 6)]
    np.testing.assert_array_equal(dense, usual)  # the same bits however it is cut


def test_label_structures_keep_a_band_whole(backend, bands, monkeypatch, noisy_blobs):
    monkeypatch.setattr(C, "_BAND_VOXELS", 1 << 10)
    vol = noisy_blobs(labels=True)
    spec = _spec((300, 900), labels=(3,))
    _, dense = _assert_same(vol, spec)
    assert all(whole for _, _, whole in bands)
    assert len(bands) > 1
    assert dense[vol.labels == 3].any()  # the label field wrote values too


def test_sides_not_multiples_of_eight(backend, noisy_blobs):
    vol = noisy_blobs(shape=(9, 17, 33), spacing=(1.0, 1.0, 1.0))
    got, _ = _assert_same(vol, _spec((300, 900)))
    assert got.index.shape == (2, 3, 5)


def test_boundary_found_flat_at_the_end_drops_its_pages(backend):
    # a gentle curved ramp crossing 1000 (its boundary's |H| is not 0 when computed) and a
    # steep step elsewhere that makes the ramp flat against the whole volume's maximum
    z, y, x = np.mgrid[:12, :24, :40].astype(np.float64)
    r = np.sqrt((z - 6) ** 2 + (y - 12) ** 2 + (x - 60) ** 2)
    ramp = 1000.0 + 0.001 * (30 - r)
    vol = Volume(ramp.astype(np.float32))
    spec = _spec((1000.0, 2000.0))
    curved, _ = _assert_same(vol, spec)
    assert len(curved.pages) > 0  # alone, the ramp's boundary has curvature
    stepped = ramp.copy()
    stepped[:, :, :8] = np.where(x[:, :, :8] < 4, 0.0, 400.0)  # no structure there
    vol = Volume(stepped.astype(np.float32))
    got, dense = _assert_same(vol, spec)
    assert not dense.any()
    assert len(got.pages) == 0
    assert (got.index == -1).all()


def test_pages_zeroed_after_the_fact_are_dropped_and_renumbered(backend):
    nk = C._curvature_kernels()
    rng = np.random.default_rng(5)
    dense = np.zeros((11, 24, 21), np.float32)
    band = P.BandPages(11, 16, 21, 8, nk, whole=False)
    for k in range(11):
        ys, xs = np.nonzero(rng.random((16, 21)) < 0.04)
        plane = band[k]
        plane[ys, xs] = rng.random(ys.size).astype(np.float32) + 0.5
        dense[k, 8:] = plane
        if nk is not None:
            band.mark(k, ys.astype(np.int64), xs.astype(np.int64))
    band.finish()
    # clear one whole page (z 0..7, rows 8..15, x 0..7) and one voxel of another
    ks, ys, xs = np.nonzero(dense[:8, 8:16, :8])
    band.zero(ks, ys + 8, xs)
    dense[:8, 8:16, :8] = 0.0
    k, y, x = (int(v[0]) for v in np.nonzero(dense[8:]))
    band.zero(k + 8, np.array([y]), np.array([x]))
    dense[k + 8, y, x] = 0.0
    index, pages = P.assemble([band], dense.shape)
    want = CurvaturePages.from_dense(dense)
    assert index[0, 1, 0] == -1
    np.testing.assert_array_equal(index, want.index)
    np.testing.assert_array_equal(pages, want.pages)


def test_page_cuts_fall_on_pages():
    for stop, bands in [(30, 4), (512, 9), (7, 3), (64, 64), (100, 1)]:
        cuts = P.page_cuts(0, stop, bands)
        assert cuts[0] == 0
        assert cuts[-1] == stop
        assert all(c % P.PAGE == 0 for c in cuts[:-1])
        assert all(a < b for a, b in itertools.pairwise(cuts))
        assert len(cuts) - 1 == min(bands, -(-stop // P.PAGE))


def test_progress_and_the_field_read_whole():
    vol, spec = make_phantom(size=32)
    seen = []
    src = curvature_source(vol, spec, progress=seen.append)
    assert isinstance(src, CurvaturePages)
    assert seen[0] == 0.0
    assert seen[-1] == 1.0
    assert seen == sorted(seen)
    want = CurvaturePages.from_dense(curvature_volume(vol, spec)[0])
    np.testing.assert_array_equal(src.index, want.index)
    np.testing.assert_array_equal(src.pages, want.pages)
    # a field analysed whole is paged as it is computed: the same analysis
    cam = Camera.from_view(vol.bounds, azimuth=20, elevation=10, width=24, height=24)
    a = analyze(vol, spec, cam, curvature=src)
    b = analyze(vol, spec, cam, curvature=CurvatureField(vol, spec))
    assert np.nanmax(a.curvature) > 0
    np.testing.assert_array_equal(b.curvature, a.curvature)
    np.testing.assert_array_equal(b.image, a.image)
