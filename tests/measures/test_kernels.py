"""The measures' numba twins give the numpy reference's numbers to the last bit."""

import importlib

import numpy as np
import pytest

from dvr_perception.measures import _layer_sets

pytest.importorskip("numba")


@pytest.mark.parametrize("dtype", [np.uint32, np.int32, np.int64])
def test_group_stats_equal_the_numpy_reference_bit_for_bit(dtype):
    rng = np.random.default_rng(3)
    groups = rng.integers(0, 40, 5000).astype(dtype)
    values = rng.random(5000) * rng.choice([1e-3, 1.0, 1e3], 5000)
    values[groups == 7] = 0.25  # a uniform group: std exactly 0
    got = _layer_sets._group_stats(values, groups, 48)
    want = _layer_sets._group_stats_numpy(values, groups, 48)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
    count, mean, std = got
    assert count[40:].sum() == 0
    assert mean[45] == 0.0  # empty groups: 0, not NaN
    assert std[7] == 0.0


def test_group_stats_use_numpy_when_numba_is_disabled(monkeypatch):
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    assert _layer_sets._numba_group_stats() is None
    count, mean, std = _layer_sets._group_stats(np.array([1.0, 3.0, 5.0]), np.array([0, 0, 2]), 3)
    np.testing.assert_array_equal(count, [2, 0, 1])
    np.testing.assert_array_equal(mean, [2.0, 0.0, 5.0])
    np.testing.assert_array_equal(std, [1.0, 0.0, 0.0])


@pytest.mark.parametrize("composition", ["importance", "thickness"])
@pytest.mark.parametrize("with_bits", [True, False])
def test_visibility_core_equals_the_numpy_reference(composition, with_bits):
    """Per ray to the last bit; image-wide sums to rounding (they are summed in chunks)."""
    from types import SimpleNamespace

    vis_mod = importlib.import_module("dvr_perception.measures.visibility")

    rng = np.random.default_rng(5)
    k, h, w = 3, 37, 41
    assigned = rng.random((k, h, w)) * rng.choice([0.0, 0.01, 1.0], (k, h, w))
    visible = rng.random((k, h, w)) * 0.3
    visible[:, :3] = np.linspace(0, 1, 21)[rng.integers(0, 21, (k, 3, w))]  # on bin edges
    assigned[:, -2:] = 0.0  # empty rays
    a_imp = rng.random((h, w))
    bits = rng.integers(0, 8, (h, w)).astype(np.uint32)
    ana = SimpleNamespace(present=bits if with_bits else None)
    imp = np.array([0.2, 0.5, 0.9])
    edges = np.linspace(0.0, 1.0, 21)
    args = (ana, visible, assigned, a_imp, imp, composition, 0.05, edges)
    got = vis_mod._core_numba(*args)
    want = vis_mod._core_numpy(*args)
    for i in (0, 1, 2):  # target, deviation, nonempty
        assert got[i].dtype == want[i].dtype
        np.testing.assert_array_equal(got[i], want[i])
    assert got[3] == pytest.approx(want[3], rel=1e-12)
    for g, wt in zip(got[4], want[4], strict=True):
        np.testing.assert_allclose(g, wt, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(got[5]), np.asarray(want[5]))
    np.testing.assert_array_equal(got[6], want[6])
    assert np.asarray(got[5]).sum() > 0


def test_visibility_uses_the_numpy_core_without_numba(monkeypatch):
    from types import SimpleNamespace

    vis_mod = importlib.import_module("dvr_perception.measures.visibility")

    ray = SimpleNamespace(visible=np.array([[[0.9]], [[0.0]]]),
                          assigned=np.array([[[2.0]], [[1.0]]]), accumulated=np.array([[0.9]]),
                          importance_accumulated=np.array([[0.9]]), names=("a", "b"))  # fmt: skip
    calls = []
    real = vis_mod._core_numpy
    monkeypatch.setattr(vis_mod, "_core_numpy", lambda *a: calls.append(1) or real(*a))
    assert vis_mod.visibility(ray).E_v == pytest.approx(0.9)
    assert calls == []
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    assert vis_mod.visibility(ray).E_v == pytest.approx(0.9)
    assert calls == [1]


@pytest.mark.parametrize("shape", [(3, 5), (40, 70), (96, 96)])
@pytest.mark.parametrize("sigma", [0.5, 2.0, 10.666666666666666])
def test_shape_filters_equal_scipy_bit_for_bit(shape, sigma):

    shape_module = importlib.import_module("dvr_perception.measures.shape")
    rng = np.random.default_rng(5)
    values = rng.random(shape) * rng.choice([0.0, 1e-3, 1.0], shape)
    mask = rng.random(shape) > 0.3
    log_y = np.log(rng.random(shape) + 0.01)
    _assert_filters_are_scipys(shape_module, values, mask, log_y, sigma)


@pytest.mark.parametrize("numba_on", [True, False])
@pytest.mark.parametrize("box", [(10, 30, 20, 50), (0, 5, 60, 80), (0, 64, 0, 3), (30, 31, 40, 41)])
def test_shape_filters_of_a_framed_image_equal_scipy_bit_for_bit(monkeypatch, numba_on, box):
    """Only the window around what varies is filtered; the bits are scipy's everywhere."""

    if not numba_on:
        monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    shape_module = importlib.import_module("dvr_perception.measures.shape")
    rng = np.random.default_rng(7)
    y0, y1, x0, x1 = box
    log_y = np.full((64, 80), np.log(0.2 + 0.01))  # a uniform background
    log_y[y0:y1, x0:x1] = np.log(rng.random((y1 - y0, x1 - x0)) + 0.01)
    mask = np.zeros((64, 80), bool)
    mask[y0:y1, x0:x1] = rng.random((y1 - y0, x1 - x0)) > 0.3
    values = rng.random((64, 80))  # values outside the mask do not count
    sizes = []
    real = shape_module._filtered
    monkeypatch.setattr(
        shape_module, "_filtered", lambda v, *a: sizes.append(v.shape) or real(v, *a)
    )
    for sigma in (0.5, 2.0, 10.666666666666666):
        _assert_filters_are_scipys(shape_module, values, mask, log_y, sigma)
    assert sizes[0] != (64, 80)  # a window
    assert (1, 1) in sizes  # and the constant image
    flat = shape_module._filters(values, np.zeros((64, 80), bool), np.full((64, 80), -1.5), 2.0)
    for got in flat:  # nothing varies: the filters' response to a constant image
        assert np.all(got == got[0, 0])
    assert flat[0][0, 0] == 0.0
    assert flat[2][0, 0] == 0.0


def test_shape_gives_the_same_result_without_numba(monkeypatch):
    from types import SimpleNamespace

    from dvr_perception.measures.shape import shape

    rng = np.random.default_rng(6)
    acc = np.where(rng.random((64, 80)) > 0.2, rng.random((64, 80)), 0.0)
    scene = SimpleNamespace(curvature=rng.random((64, 80)) * 0.3, accumulated=acc,
                            image=rng.random((64, 80, 3)))  # fmt: skip
    fast = shape(scene)
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    slow = shape(scene)
    assert fast.E_s == slow.E_s
    assert 0 < fast.E_s < 1
    np.testing.assert_array_equal(fast.deviation, slow.deviation)


def test_visibility_sums_do_not_depend_on_the_thread_count():
    import numba

    from dvr_perception.measures import _kernels

    rng = np.random.default_rng(9)
    k, n = 4, 300_000
    assigned = rng.random((k, n)) * rng.choice([0.0, 0.01, 1.0], (k, n))
    visible = rng.random((k, n)) * 0.3
    args = (visible, assigned, rng.random(n), np.array([0.2, 0.5, 0.9, 0.4]), 0.05, False,
            np.zeros(0, np.uint64), np.linspace(0.0, 1.0, 21))  # fmt: skip
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _kernels.visibility_core(*args)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = _kernels.visibility_core(*args)
    finally:
        numba.set_num_threads(before)
    assert one[3] == two[3]  # the sum of the deviations, to the last bit
    for a, b in zip(one[4:], two[4:], strict=True):
        np.testing.assert_array_equal(a, b)
    assert one[3] == pytest.approx(float(one[1].astype(np.float64).sum()), rel=1e-9)


@pytest.mark.parametrize("with_bits", [True, False])
def test_visibility_core_reads_float32_fields_as_their_float64_values(with_bits):
    """The engine's float32 fields go to the kernel as they are: the float64 results."""
    from types import SimpleNamespace

    vis_mod = importlib.import_module("dvr_perception.measures.visibility")

    rng = np.random.default_rng(8)
    k, h, w = 3, 29, 31
    assigned = (rng.random((k, h, w)) * rng.choice([0.0, 0.01, 1.0], (k, h, w))).astype(np.float32)
    visible = (rng.random((k, h, w)) * 0.3).astype(np.float32)
    visible[:, :4], assigned[:, :4] = 0.0, 0.0  # blank rays
    bits = rng.integers(0, 8, (h, w)).astype(np.uint32)
    bits[:2] = 0
    ana = SimpleNamespace(present=bits if with_bits else None)
    rest = (rng.random((h, w)), np.array([0.2, 0.5, 0.9]), "importance", 0.05,
            np.linspace(0.0, 1.0, 21))  # fmt: skip
    got = vis_mod._core_numba(ana, visible, assigned, *rest)
    want = vis_mod._core_numba(ana, visible.astype(np.float64), assigned.astype(np.float64), *rest)
    ref = vis_mod._core_numpy(ana, visible.astype(np.float64), assigned.astype(np.float64), *rest)
    for i in (0, 1, 2):
        np.testing.assert_array_equal(got[i], want[i])
        np.testing.assert_array_equal(got[i], ref[i])
    assert got[3] == want[3]
    for g, wt in zip(got[4], want[4], strict=True):
        np.testing.assert_array_equal(g, wt)
    np.testing.assert_array_equal(np.asarray(got[5]), np.asarray(want[5]))
    np.testing.assert_array_equal(got[6], want[6])


@pytest.mark.parametrize("numba_on", [True, False])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_layer_set_bits_equal_the_bitmask_of_the_footprints(monkeypatch, numba_on, dtype):
    from dvr_perception.errors import DVRInputError
    from dvr_perception.measures import regions

    if not numba_on:
        monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    rng = np.random.default_rng(4)
    k, h, w = 5, 23, 17
    visible = (rng.random((k, h, w)) * 0.1).astype(dtype)
    assigned = (rng.random((k, h, w)) * 0.2).astype(dtype)
    # float32(0.05) lies above 0.05 in float64 (the comparison the footprints make)
    visible[0, :3] = np.float32(0.05) if dtype == np.float32 else 0.05
    assigned[0, :3] = 0.0
    limits = 0.05 * np.array([0.2, 1.0, 0.5, 0.0, 0.9])
    fp = regions.layer_footprints(visible.astype(np.float64), threshold=0.05)
    want = regions._bitmask(fp | (assigned.astype(np.float64) > limits[:, None, None]))
    got = regions._layer_set_bits(visible, 0.05, assigned, limits)
    assert got.dtype == np.uint32
    np.testing.assert_array_equal(got, want)
    assert np.all(got[:3] & 1 == (1 if dtype == np.float32 else 0))
    np.testing.assert_array_equal(regions._layer_set_bits(visible, 0.05), regions._bitmask(fp))
    with pytest.raises(DVRInputError, match="threshold"):
        regions._layer_set_bits(visible, 1.0)


@pytest.mark.parametrize("size", [(1, 1), (1, 9), (9, 1), (17, 23), (64, 48)])
def test_label_regions_equal_skimage_in_raster_order(size):
    from skimage.measure import label

    from dvr_perception.measures import _kernels, regions

    rng = np.random.default_rng(size[0] * 100 + size[1])
    for values in (2, 3, 5):
        image = rng.integers(0, values, size).astype(np.uint32)
        image[size[0] // 2] = 7  # a band across: components joined around it
        want, first = regions._raster_ordered(
            label(image.astype(np.int64), background=-1, connectivity=2)
        )
        got, got_first, area = _kernels.label_regions(image)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(got_first, first)
        np.testing.assert_array_equal(area, np.bincount(want.ravel()))


def test_label_regions_join_diagonal_and_u_shaped_components():
    from dvr_perception.measures import _kernels

    image = np.array(
        [[1, 0, 0, 1],
         [0, 1, 0, 1],
         [0, 0, 0, 1],
         [1, 1, 0, 1]], np.uint32,
    )  # fmt: skip
    ids, first, area = _kernels.label_regions(image)
    # 1s: a diagonal pair, the right column, the bottom left pair; 0s: one 8-connected set
    want = [[0, 1, 1, 2], [1, 0, 1, 2], [1, 1, 1, 2], [3, 3, 1, 2]]
    np.testing.assert_array_equal(ids, want)
    assert first.tolist() == [0, 1, 3, 12]
    assert area.tolist() == [2, 8, 4, 2]
    u_shape = np.array([[1, 0, 1], [1, 0, 1], [1, 1, 1]], np.uint32)
    ids, first, area = _kernels.label_regions(u_shape)  # the arms meet on the last row
    np.testing.assert_array_equal(ids, [[0, 1, 0], [0, 1, 0], [0, 0, 0]])
    assert first.tolist() == [0, 1]
    assert area.tolist() == [7, 2]


@pytest.mark.parametrize("numba_on", [True, False])
def test_regions_and_relations_do_not_depend_on_numba(monkeypatch, numba_on):
    from dvr_perception.measures import layer_relations, subregions

    rng = np.random.default_rng(12)
    fp = np.zeros((4, 40, 50), bool)
    fp[0, 5:35, 5:45] = True  # encloses 1
    fp[1, 10:20, 10:20] = True
    fp[2, 15:30, 15:50] = rng.random((15, 35)) > 0.2  # overlaps 0 and 1, ragged
    fp[3, 36:40, 46:50] = True  # touches 0 diagonally at most: separate or touch
    if not numba_on:
        monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    rmap, rel = subregions(fp), layer_relations(fp)
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "0" if not numba_on else "1")
    ref_map, ref_rel = subregions(fp), layer_relations(fp)
    np.testing.assert_array_equal(rmap.region_id, ref_map.region_id)
    assert rmap.regions == ref_map.regions
    assert rel == ref_rel
    assert rel[(0, 1)].kind == "enclose"
    assert rel[(0, 2)].kind == "overlap"


def test_group_stats_over_runs_of_one_group_equal_the_numpy_reference():
    """Runs of pixels of one group (the usual image) are summed in a register: same bits."""
    rng = np.random.default_rng(13)
    groups = np.repeat(rng.integers(0, 9, 300), rng.integers(1, 40, 300)).astype(np.uint32)
    values = rng.random(groups.size) * 1e3
    got = _layer_sets._group_stats(values, groups, 12)
    want = _layer_sets._group_stats_numpy(values, groups, 12)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_seen_on_equals_the_numpy_sums(dtype):
    from dvr_perception.measures import _kernels

    rng = np.random.default_rng(14)
    k, n = 4, 3000
    visible = (rng.random((k, n)) * rng.choice([0.0, 0.01, 0.3], (k, n))).astype(dtype)
    assigned = (rng.random((k, n)) * rng.choice([0.0, 0.2, 2.0], (k, n))).astype(dtype)
    carry = _layer_sets.Carried(assigned, np.array([0.5, 1.0, 2.0, 0.0]))
    pix = np.sort(rng.choice(n, 1500, replace=False))
    for layers in ([1], [2, 0], [0, 1, 3]):
        vis = visible[np.ix_(layers, pix)].astype(np.float64).sum(axis=0)
        held = carry.on(layers, pix).sum(axis=0)
        want = (vis > _layer_sets.HIDDEN_FRACTION * held) | (held <= 0.0)
        got = _kernels.seen_on(visible, assigned, carry.scale, np.array(layers), pix,
                               _layer_sets.PRESENCE_CAP, _layer_sets.HIDDEN_FRACTION)  # fmt: skip
        np.testing.assert_array_equal(got, want)
        assert 0 < np.count_nonzero(got) < pix.size  # both cases occur


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_premultiplied_excess_counts_as_numpy(dtype):
    from dvr_perception.measures import _kernels

    rng = np.random.default_rng(15)
    rgba = rng.random((500, 4)).astype(dtype)
    rgba[:100, 3] = 0.0
    rgba[100:200, :3] = rgba[100:200, 3:] + 1e-5  # on the edge of the slack
    got = _kernels.premultiplied_excess(rgba, 1e-5)
    wide = rgba.astype(np.float64)
    over = np.count_nonzero(wide[:, :3].max(axis=1) > wide[:, 3] + 1e-5)
    assert got == (over, np.count_nonzero(wide[:, 3] > 1e-5))
    assert 0 < got[0] < 500


def _assert_filters_are_scipys(shape_module, values, mask, log_y, sigma):
    """The shape measure's three filtered images equal scipy's to the bit (and are not 0)."""
    from scipy import ndimage

    num, den, grad = shape_module._filters(values, mask, log_y, sigma)
    weight = mask.astype(np.float64)
    want = ndimage.gaussian_filter(values * weight, sigma, mode="nearest")
    np.testing.assert_array_equal(num, want)
    np.testing.assert_array_equal(den, ndimage.gaussian_filter(weight, sigma, mode="nearest"))
    want = ndimage.gaussian_gradient_magnitude(log_y, sigma, mode="nearest")
    np.testing.assert_array_equal(grad, want)
    assert grad.max() > 0  # not trivially equal
