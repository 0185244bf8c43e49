"""Curvature on boundary voxels: bricks equal the full result, numba equals numpy, and both
equal the whole-volume reference (:func:`mean_curvature` read at the boundary)."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays import curvature as C
from dvr_perception.rays.curvature import (
    CurvatureGlobals,
    curvature_ghost,
    curvature_globals,
    curvature_volume,
    mean_curvature,
)
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.volume import Volume


def _spec(*ranges):
    return StructureSpec(
        tuple(Structure(f"s{i}", 0.5, (1.0, 1.0, 1.0), range=r) for i, r in enumerate(ranges))
    )


def _reference(vol, spec, sigma=1.0):
    """The previous full-volume implementation (range structures only)."""
    ids = C.classify_structures(vol, spec)
    bnd = np.zeros(ids.shape, bool)
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        d = ids[tuple(a)] != ids[tuple(b)]
        bnd[tuple(a)] |= d
        bnd[tuple(b)] |= d
    h = mean_curvature(vol.data, spacing=vol.spacing, sigma=sigma)
    return np.where(bnd, h, 0), bnd


@pytest.fixture(params=["numba", "numpy"])
def backend(request, monkeypatch):
    if request.param == "numpy":
        monkeypatch.setattr(C, "_curvature_kernels", lambda: None)
    elif C._curvature_kernels() is None:
        pytest.skip("numba is not available")
    return request.param


def test_full_result_equals_the_reference(backend, noisy_blobs):
    vol = noisy_blobs()
    spec = _spec((500, 1500), (1500, 4000))
    curv, bnd = curvature_volume(vol, spec)
    ref, ref_bnd = _reference(vol, spec)
    np.testing.assert_array_equal(bnd, ref_bnd)
    assert bnd.sum() > 500
    assert np.all(curv[~bnd] == 0)
    np.testing.assert_allclose(curv, ref, rtol=0, atol=1e-4 * float(ref.max()))


def _extents(shape, rng, n):
    out = [tuple((0, s) for s in shape), ((0, 1), (0, shape[1]), (0, shape[2]))]
    out.append(tuple((s - 3, s) for s in shape))  # the far corner
    for _ in range(n):
        ext = []
        for s in shape:
            a = int(rng.integers(0, s - 1))
            ext.append((a, int(rng.integers(a + 1, s + 1))))
        out.append(tuple(ext))
    return out


@pytest.mark.parametrize("with_globals", [False, True])
def test_bricks_equal_slices_of_the_full_result(backend, with_globals, noisy_blobs):
    vol = noisy_blobs()
    spec = _spec((500, 1500), (1500, 4000))
    full, full_bnd = curvature_volume(vol, spec)
    g = curvature_globals(vol, spec) if with_globals else None
    rng = np.random.default_rng(7)
    for ext in _extents(vol.data.shape, rng, 8):
        curv, bnd = curvature_volume(vol, spec, extent=ext, gradient_max=g)
        sl = tuple(slice(a, b) for a, b in ext)
        assert curv.shape == tuple(b - a for a, b in ext)
        np.testing.assert_array_equal(bnd, full_bnd[sl])
        np.testing.assert_array_equal(curv, full[sl])


def test_numba_and_numpy_agree(monkeypatch, noisy_blobs):
    if C._curvature_kernels() is None:
        pytest.skip("numba is not available")
    vol = noisy_blobs()
    spec = _spec((500, 1500), (1500, 4000))
    fast, bnd = curvature_volume(vol, spec)
    g_fast = curvature_globals(vol, spec)
    monkeypatch.setattr(C, "_curvature_kernels", lambda: None)
    slow, bnd2 = curvature_volume(vol, spec)
    g_slow = curvature_globals(vol, spec)
    np.testing.assert_array_equal(bnd, bnd2)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-5 * float(slow.max()))
    assert g_fast.gradient_max == pytest.approx(g_slow.gradient_max, rel=1e-5)
    assert g_fast.offset == g_slow.offset


def test_gradient_max_is_the_whole_volume_maximum(backend, noisy_blobs):
    vol = noisy_blobs()
    spec = _spec((500, 1500))
    f = vol.data.astype(np.float32)
    f -= np.float32(C._offset_of(vol.data))
    sx, sy, sz = vol.spacing
    d = C._derivatives(f, C._axis_sigmas(1.0, vol.spacing))
    g2 = (
        (d[(1, 0, 0)].astype(np.float64) / sz) ** 2
        + (d[(0, 1, 0)].astype(np.float64) / sy) ** 2
        + (d[(0, 0, 1)].astype(np.float64) / sx) ** 2
    )
    g = curvature_globals(vol, spec)
    assert g.gradient_max == pytest.approx(float(np.sqrt(g2.max())), rel=1e-5)
    # over a part only (an MPI rank's), and combined again
    half = ((0, 9), (0, 30), (0, 26))
    rest = ((9, 18), (0, 30), (0, 26))
    parts = curvature_globals(vol, spec, extent=half).combine(
        curvature_globals(vol, spec, extent=rest)
    )
    assert parts.gradient_max == pytest.approx(g.gradient_max, rel=1e-12)


def test_flat_boundary_far_from_the_steepest_edge(backend):
    """A boundary on an almost flat ramp is flat relative to a steep edge elsewhere: 0, also
    in a brick that does not contain the edge (the maximum is the whole volume's)."""
    _z, _y, x = np.mgrid[:12, :16, :40].astype(np.float64)
    f = 1000.0 + 0.01 * (x - 30)  # gentle ramp crossing 1000 at x = 30
    f[:, :, :12] = np.where(x[:, :, :12] < 6, 0.0, 400.0)  # a steep step, no structure there
    vol = Volume(f.astype(np.float32))
    spec = _spec((1000.0, 2000.0))
    curv, bnd = curvature_volume(vol, spec)
    ref, ref_bnd = _reference(vol, spec)
    np.testing.assert_array_equal(bnd, ref_bnd)
    assert bnd[:, :, 29:32].any()
    assert np.all(ref[bnd] == 0)
    assert np.all(curv == 0)
    brick, _ = curvature_volume(vol, spec, extent=((2, 10), (3, 12), (20, 40)))
    assert np.all(brick == 0)
    # without the step the ramp is the steepest thing: no longer flat (planes: |H| ~ 0 anyway)
    g = curvature_globals(vol, spec)
    assert g.gradient_max > 100


def test_sphere_in_a_brick_is_one_over_r(backend):
    radius = 10
    n = 2 * radius + 10
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2).astype(np.float64)
    r = np.sqrt(x**2 + y**2 + z**2)
    vol = Volume((200 / (1 + np.exp((r - radius) / 1.5))).astype(np.float32))
    ext = ((0, n // 2), (3, n), (n // 2 - 4, n))
    curv, bnd = curvature_volume(vol, _spec((100, 255)), extent=ext)
    assert bnd.sum() > 50
    np.testing.assert_allclose(curv[bnd], 1.0 / radius, rtol=0.2)


def test_constant_volume_is_zero(backend):
    vol = Volume(np.full((6, 7, 8), 120, np.uint8))
    curv, bnd = curvature_volume(vol, _spec((100, 200)), extent=((1, 5), (0, 7), (2, 3)))
    assert curv.shape == (4, 7, 1)
    assert not bnd.any()
    assert not curv.any()
    assert curvature_globals(vol, _spec((100, 200))).gradient_max == 0


def test_labels_in_bricks(backend):
    radius = 7
    n = 2 * radius + 9
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2).astype(np.float64)
    r = np.sqrt(x**2 + y**2 + z**2)
    labels = (r <= radius).astype(np.uint8) * 2
    data = (60 * (np.abs(x) < 3)).astype(np.uint8)
    vol = Volume(data, labels=labels)
    spec = StructureSpec(
        (
            Structure("slab", 0.5, (1.0, 1.0, 1.0), range=(30, 100)),
            Structure("ball", 1.0, (1.0, 0.0, 0.0), label=2),
        ),
        labels_file="l",
    )
    full, full_bnd = curvature_volume(vol, spec, sigma=2.0)
    assert full_bnd.sum() > 0
    for ext in (
        ((0, n), (0, n), (0, n)),
        ((3, 14), (5, n), (0, 12)),
        ((n - 5, n), (0, 9), (4, 20)),
    ):
        curv, bnd = curvature_volume(vol, spec, sigma=2.0, extent=ext)
        sl = tuple(slice(a, b) for a, b in ext)
        np.testing.assert_array_equal(bnd, full_bnd[sl])
        np.testing.assert_array_equal(curv, full[sl])
    ball = full_bnd & (labels == 2) & (np.abs(x) >= 4)
    assert abs(float(np.median(full[ball])) * radius - 1) < 0.2


def test_ghost():
    assert curvature_ghost(1.0, (1.0, 1.0, 1.0)) == 5
    assert curvature_ghost(1.0, (1.0, 1.0, 2.0)) == 5
    assert curvature_ghost(2.0, (0.5, 0.5, 0.5)) == 8
    with pytest.raises(DVRInputError, match="sigma"):
        curvature_ghost(0, (1, 1, 1))
    with pytest.raises(DVRInputError, match="spacing"):
        curvature_ghost(1.0, (1, 1))


def test_brick_reads_only_its_ghost(backend, noisy_blobs):
    """A brick is computed from the voxels within curvature_ghost of its extent."""
    vol = noisy_blobs()
    spec = _spec((500, 1500), (1500, 4000))
    g = curvature_globals(vol, spec)
    ext = ((5, 11), (8, 20), (6, 15))
    ghost = curvature_ghost(1.0, vol.spacing)
    data = vol.data.copy()
    keep = np.zeros(data.shape, bool)
    keep[tuple(slice(max(0, a - ghost), b + ghost) for a, b in ext)] = True
    data[~keep] = 4000
    want, _ = curvature_volume(vol, spec, extent=ext, gradient_max=g)
    got, _ = curvature_volume(Volume(data, spacing=vol.spacing), spec, extent=ext, gradient_max=g)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"extent": ((0, 3), (0, 3))}, "extent must be"),
        ({"extent": ((2, 2), (0, 3), (0, 3))}, "extent must be"),
        ({"extent": ((0, 3), (0, 3), (0, 9))}, "extent must be"),
        ({"extent": "all"}, "extent must be"),
        ({"gradient_max": -1.0}, "gradient_max must be"),
        ({"gradient_max": CurvatureGlobals(2.0, 0.0, 1.0)}, "computed for sigma=2.0"),
        ({"offset": float("nan")}, "offset must be"),
        ({"sigma": 0}, "sigma must be"),
    ],
)
def test_bad_arguments(kwargs, message):
    vol = Volume(np.zeros((4, 5, 6), np.uint8))
    with pytest.raises(DVRInputError, match=message):
        curvature_volume(vol, _spec((1, 2)), **kwargs)


def test_many_threads_cut_more_bands_with_the_same_bits(backend, monkeypatch, noisy_blobs):
    from dvr_perception.rays import curvature as curvature_module

    vol = noisy_blobs(shape=(18, 70, 26))
    spec = _spec((500, 1500), (1500, 4000))
    monkeypatch.setattr(curvature_module, "_threads", lambda: 1)
    one, one_bnd = curvature_volume(vol, spec)
    cuts = []
    real = curvature_module._chunk
    monkeypatch.setattr(curvature_module, "_threads", lambda: 16)
    monkeypatch.setattr(curvature_module, "_chunk", lambda *a: cuts.append(a[2]) or real(*a))
    small, _ = curvature_volume(vol, spec)
    assert len(cuts) == 1  # a small extent keeps one band (progress slice by slice)
    np.testing.assert_array_equal(small, one)
    cuts.clear()
    monkeypatch.setattr(curvature_module, "_SPLIT_VOXELS", 1)  # as a large extent is cut
    many, many_bnd = curvature_volume(vol, spec)
    assert len(cuts) == 70 // curvature_module._MIN_ROWS  # 4 bands of 16 or more rows
    np.testing.assert_array_equal(many_bnd, one_bnd)
    np.testing.assert_array_equal(many, one)
    assert one_bnd.sum() > 500


@pytest.mark.parametrize("step", [False, True])
def test_cell_bounds_bound_every_cells_exact_gradient_maximum(backend, step, noisy_blobs):
    """The branch and bound's per-cell bound lies above the cell's exact maximum, and the
    value range makes it tighter than the neighbour differences alone across a step."""
    from dvr_perception.rays import _curvature_passes as P

    vol = noisy_blobs(shape=(36, 40, 34))
    if step:  # a sharp edge: neighbour differences alone bound it by the full step
        data = np.full(vol.data.shape, 100, np.uint16)
        data[:, :, 17:] = 2100
        vol = Volume(data, spacing=vol.spacing)
    spec = _spec((500, 1500))
    fld = C._fields(vol, spec, None, None, None)[0]
    geo = P._Geometry(vol.data.shape, vol.spacing, 1.0, tuple((0, n) for n in vol.data.shape))
    nk = C._curvature_kernels()
    c = P._CELL
    ncell = [-(-n // c) for n in vol.data.shape]
    if nk is not None:
        diffs = np.zeros((*ncell, 5), np.float32)
        nk.cell_diffs(fld.src, fld.match, np.float32(fld.offset), c, 0, 0, 0,
                      *vol.data.shape, diffs)  # fmt: skip
        np.testing.assert_array_equal(diffs, P._cell_diffs_numpy(fld, [0, 0, 0], ncell, c))
    else:
        diffs = P._cell_diffs_numpy(fld, [0, 0, 0], ncell, c)
    bound2 = P._cell_bounds(diffs, geo)
    boxes = []
    for i, j, k in np.ndindex(*ncell):
        z0, y0, x0 = c * i, c * j, c * k
        zz, yy, xx = vol.data.shape
        boxes.append((z0, min(z0 + c, zz), y0, min(y0 + c, yy), x0, min(x0 + c, xx)))
    exact = P._cells_gradient_max_numpy(fld, geo, boxes).reshape(ncell)
    assert np.all(exact <= bound2)
    assert exact.max() > 0
    if step:  # at the step: about a third of what the differences alone allow
        old = ((diffs[..., :3].max(axis=(0, 1, 2)).astype(np.float64) * geo.inv) ** 2).sum()
        assert bound2.max() < 0.25 * old
        assert bound2.max() < 2.0 * exact.max()


@pytest.mark.parametrize("step", [False, True])
def test_range_bound_lies_above_the_gradient_maximum(step, noisy_blobs):
    """The flatness test's bound from the data range bounds the exact maximum, well below the
    plain ``range * |inv|`` (a third of it at sigma 1, where a step nearly reaches it)."""
    from dvr_perception.rays import _curvature_passes as P

    vol = noisy_blobs(shape=(24, 30, 28))
    if step:
        data = np.full(vol.data.shape, 100, np.uint16)
        data[:, 14:] = 2100
        vol = Volume(data, spacing=vol.spacing)
    spec = _spec((500, 1500))
    gmax = curvature_globals(vol, spec).gradient_max
    geo = P._Geometry(vol.data.shape, vol.spacing, 1.0, tuple((0, n) for n in vol.data.shape))
    span = float(vol.data.max()) - float(vol.data.min())
    bound2 = C._range_bound2(geo, span, float(vol.data.max()))
    assert 0 < gmax**2 <= bound2
    assert bound2 < 0.2 * span**2 * float((geo.inv**2).sum())
    if step:  # one axis reaches its term of the three-axis sum
        assert bound2 < 3.0 * gmax**2
