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
