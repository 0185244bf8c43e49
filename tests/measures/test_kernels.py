"""The measures' numba twins give the numpy reference's numbers to the last bit."""

import numpy as np
import pytest

from dvr_perception.measures import _scene

pytest.importorskip("numba")


@pytest.mark.parametrize("dtype", [np.uint32, np.int32, np.int64])
def test_group_stats_equal_the_numpy_reference_bit_for_bit(dtype):
    rng = np.random.default_rng(3)
    groups = rng.integers(0, 40, 5000).astype(dtype)
    values = rng.random(5000) * rng.choice([1e-3, 1.0, 1e3], 5000)
    values[groups == 7] = 0.25  # a uniform group: std exactly 0
    got = _scene._group_stats(values, groups, 48)
    want = _scene._group_stats_numpy(values, groups, 48)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
    count, mean, std = got
    assert count[40:].sum() == 0
    assert mean[45] == 0.0  # empty groups: 0, not NaN
    assert std[7] == 0.0


def test_group_stats_use_numpy_when_numba_is_disabled(monkeypatch):
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    assert _scene._numba_group_stats() is None
    count, mean, std = _scene._group_stats(np.array([1.0, 3.0, 5.0]), np.array([0, 0, 2]), 3)
    np.testing.assert_array_equal(count, [2, 0, 1])
    np.testing.assert_array_equal(mean, [2.0, 0.0, 5.0])
    np.testing.assert_array_equal(std, [1.0, 0.0, 0.0])
