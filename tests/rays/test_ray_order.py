"""The rays' dealing to parallel chunks gives every thread an equal share (issue 31, cores)."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.rays import _walk_setup
from dvr_perception.rays.engine import TILE, ray_order


def _static_speedup(cost, order, chunk_ptr, threads):
    """Ideal speedup when ``threads`` threads get equal runs of chunks (numba's schedule)."""
    per = np.add.reduceat(cost[order], chunk_ptr[:-1])
    n = len(per)
    loads = [per[t * n // threads : (t + 1) * n // threads].sum() for t in range(threads)]
    return per.sum() / max(loads)


@pytest.fixture
def many_threads(monkeypatch):
    monkeypatch.setattr(_walk_setup, "_threads", lambda: 16)


@pytest.mark.parametrize("size", [512, 384, 700])
def test_every_ray_once_and_threads_get_equal_shares_of_a_central_object(size, many_threads):
    order, chunk_ptr = ray_order(size, size)
    assert np.array_equal(np.sort(order), np.arange(size * size))
    assert chunk_ptr[0] == 0
    assert chunk_ptr[-1] == size * size
    assert np.all(np.diff(chunk_ptr) > 0)
    # the cost of a ray: high on a disc in the middle of the image (a head), 0 around it
    y, x = np.mgrid[:size, :size] - size / 2
    cost = np.where(np.hypot(x, y) < 0.35 * size, 1.0 + (y / size) ** 2, 0.0).ravel()
    for threads in (2, 4, 8, 16):
        # dealt round-robin, a 512-pixel image's chunks were tile columns: 8 threads 3.4x
        assert _static_speedup(cost, order, chunk_ptr, threads) > 0.85 * threads


def test_a_chunk_is_no_tile_column(many_threads):
    order, chunk_ptr = ray_order(512, 512)
    columns = order[chunk_ptr[0] : chunk_ptr[1]] % 512 // TILE[1]
    assert len(np.unique(columns)) > 4


def test_few_threads_keep_the_round_robin_sweeps(monkeypatch):
    monkeypatch.setattr(_walk_setup, "_threads", lambda: 2)
    order, chunk_ptr = ray_order(512, 512)
    assert np.array_equal(np.sort(order), np.arange(512 * 512))
    columns = order[chunk_ptr[5] : chunk_ptr[6]] % 512 // TILE[1]
    assert set(columns.tolist()) == {5}  # chunk 5: tile column 5, every other tile row
