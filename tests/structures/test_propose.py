"""Automatic structure proposal on volumes with known intensity modes."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures import propose_structures, spec_from_dict, spec_to_dict
from dvr_perception.structures.propose import PALETTE
from dvr_perception.volume import Volume


def _three_blobs(dtype=np.uint8, values=(60, 130, 210), noise=4.0, scale=1.0):
    """Background 10 plus three Gaussian-noise blobs of distinct mean intensities."""
    rng = np.random.default_rng(5)
    z, y, x = np.mgrid[:40, :40, :40]
    data = 10 + noise * rng.standard_normal((40, 40, 40))
    centres = [(10, 10, 10), (20, 28, 20), (30, 12, 28)]
    for (cz, cy, cx), v in zip(centres, values, strict=True):
        inside = (z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 <= 49
        data[inside] = v + noise * rng.standard_normal(int(inside.sum()))
    data = np.clip(data, 0, 255) * scale
    return Volume(data.astype(dtype), name="blobs")


@pytest.mark.parametrize(
    ("dtype", "scale"), [(np.uint8, 1.0), (np.uint16, 200.0), (np.float32, 0.01)]
)
def test_three_blobs_give_three_ranges(dtype, scale):
    spec = propose_structures(_three_blobs(dtype, scale=scale))
    assert len(spec.structures) == 3
    ranges = [s.range for s in spec.structures]
    for (lo, hi), v in zip(ranges, (60, 130, 210), strict=True):
        assert lo < v * scale < hi
    assert ranges[0][0] > 25 * scale  # the background (10 +- noise) is excluded
    for a, b in itertools.pairwise(ranges):
        assert a[1] == b[0]  # contiguous, touching
    assert ranges[-1][1] == pytest.approx(float(_three_blobs(dtype, scale=scale).data.max()))
    assert [s.importance for s in spec.structures] == [0.15, 0.5, 0.85]
    assert [s.colour for s in spec.structures] == [PALETTE[0], PALETTE[4], PALETTE[7]]
    assert spec.structures[-1].colour == (1.0, 0.96, 0.84)  # the densest class is ivory


def test_names_and_round_trip():
    spec = propose_structures(_three_blobs())
    assert spec.structures[0].name.startswith("class 1 (")
    lo, hi = spec.structures[0].range
    assert spec.structures[0].name == f"class 1 ({math.ceil(lo)}\u2013{math.ceil(hi) - 1})"
    assert spec_from_dict(spec_to_dict(spec)) == spec  # the proposal is a valid spec


def test_deterministic():
    vol = _three_blobs(np.float32)
    assert propose_structures(vol, seed=3) == propose_structures(vol, seed=3)


def test_two_structures():
    spec = propose_structures(_three_blobs(), n_structures=2)
    assert len(spec.structures) == 2
    assert [s.importance for s in spec.structures] == [0.15, 0.85]


def test_one_structure():
    spec = propose_structures(_three_blobs(), n_structures=1)
    assert len(spec.structures) == 1
    assert spec.structures[0].importance == 0.5
    assert spec.structures[0].range[0] > 20


def test_few_distinct_values():
    data = np.repeat(np.array([0, 0, 100, 200], np.uint8), 8).reshape(2, 4, 4)
    with pytest.warns(DVRWarning, match="only 3 distinct value"):
        spec = propose_structures(Volume(data), n_structures=4)
    assert [s.range for s in spec.structures] == [(50.0, 150.0), (150.0, 200.0)]


def test_exact_distinct_values_for_classes():
    data = np.repeat(np.array([0, 0, 100, 200], np.uint8), 8).reshape(2, 4, 4)
    spec = propose_structures(Volume(data), n_structures=2)
    assert [s.range for s in spec.structures] == [(50.0, 150.0), (150.0, 200.0)]


def test_constant_volume():
    with pytest.raises(DVRInputError, match="all voxels have the value 7; nothing to propose"):
        propose_structures(Volume(np.full((3, 3, 3), 7, np.uint16)))


@pytest.mark.parametrize("n", [0, 9, 2.5, True])
def test_bad_count(n):
    with pytest.raises(DVRInputError, match="n_structures must be"):
        propose_structures(_three_blobs(), n_structures=n)


def test_signed_and_many_classes():
    rng = np.random.default_rng(0)
    means = np.array([-900, -300, 0, 300, 700, 1200])
    data = means[rng.integers(0, 6, (20, 20, 20))] + rng.integers(-20, 20, (20, 20, 20))
    spec = propose_structures(Volume(data.astype(np.int16)), n_structures=5)
    assert len(spec.structures) == 5
    for s, m in zip(spec.structures, means[1:], strict=True):
        assert s.range[0] < m < s.range[1]
