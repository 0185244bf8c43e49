"""The per-cell class map the numba walk classifies samples with."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.rays import _grid
from dvr_perception.structures.spec import Structure, StructureSpec
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.volume import Volume

_WS = 32765.0 / 32768.0
_WB = 32767.0 / 32768.0


def _map(vol, spec):
    lut = build_lut(spec, scalar_range=_grid.scalar_range(vol), dtype=vol.data.dtype)
    idx = _grid.index_volume(vol, lut.lo, lut.scale, lut.size)
    return lut, idx, _grid.cell_map(vol, idx, lut.ids, lut.membership)


def test_one_bright_voxel_makes_only_its_eight_cells_busy():
    data = np.zeros((7, 8, 9), np.uint8)
    data[3, 4, 5] = 200
    vol = Volume(data)
    spec = StructureSpec((Structure("dot", 1.0, (1, 1, 1), range=(100, 255)),))
    _, _, cells = _map(vol, spec)
    assert cells.dtype == np.uint8
    assert cells.shape == data.shape
    # the 8 cells sharing the voxel as a corner hold samples of the structure
    busy = np.argwhere(cells[:-1, :-1, :-1] != _grid.CELL_EMPTY)
    assert sorted(map(tuple, busy)) == [(z, y, x) for z in (2, 3) for y in (3, 4) for x in (4, 5)]
    assert np.all(cells[tuple(busy.T)] == _grid.CELL_MIXED)  # 200 is on the ramp: interpolate
    assert not cells[-1].any()  # the last plane is never sampled


def test_constant_volume_inside_a_plateau_is_classified_without_interpolation():
    vol = Volume(np.full((5, 5, 5), 150, np.uint8))
    spec = StructureSpec(
        (
            Structure("a", 0.5, (1, 0, 0), range=(20, 90), edge=0.1),
            Structure("b", 0.5, (0, 1, 0), range=(100, 200), edge=0.1),
        )
    )
    _, _, cells = _map(vol, spec)
    inner = cells[:-1, :-1, :-1]
    assert np.all(inner == 1 + 1)  # structure 1 ("b"), its plateau


def test_empty_volume_is_empty():
    vol = Volume(np.zeros((4, 4, 4), np.uint8))
    spec = StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(100, 200)),))
    _, _, cells = _map(vol, spec)
    assert np.all(cells == _grid.CELL_EMPTY)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_classes_hold_for_every_sample_in_a_noisy_volume(dtype):
    rng = np.random.default_rng(7)
    z, y, x = np.mgrid[:14, :15, :16].astype(float)
    smooth = 120 + 90 * np.sin(x / 3.0) * np.cos(y / 4.0) + 8 * np.sin(z)
    data = np.clip(smooth + rng.normal(0, 6, smooth.shape), 0, 250).astype(dtype)
    vol = Volume(data)
    spec = StructureSpec(
        (
            Structure("low", 0.3, (1, 0, 0), range=(40, 110), edge=0.2),
            Structure("high", 0.8, (0, 0, 1), range=(150, 240), edge=0.1),
        )
    )
    lut, idx, cells = _map(vol, spec)
    cls = cells[:-1, :-1, :-1]
    assert {0, 1, 2, 255} <= set(np.unique(cls).tolist())  # every class occurs
    # random sample positions in every cell; the table entry the walk would interpolate
    pts = np.stack(np.meshgrid(*(np.arange(n - 1) for n in idx.shape), indexing="ij"), -1)
    pts = pts.reshape(-1, 3)
    f = idx.astype(np.float64)
    for _ in range(6):
        fr = rng.random(pts.shape)
        c0 = [pts[:, i] for i in range(3)]
        val = np.zeros(len(pts))
        for corner in np.ndindex(2, 2, 2):
            w = np.prod([fr[:, i] if corner[i] else 1 - fr[:, i] for i in range(3)], axis=0)
            val += w * f[c0[0] + corner[0], c0[1] + corner[1], c0[2] + corner[2]]
        k = np.minimum((val * _WS + _WB).astype(np.int64), lut.size - 1)
        c = cls[c0[0], c0[1], c0[2]]
        empty = c == _grid.CELL_EMPTY
        assert np.all(lut.membership[k[empty]] <= 0)
        plat = (c != _grid.CELL_EMPTY) & (c != _grid.CELL_MIXED)
        assert np.all(lut.membership[k[plat]] == 1)
        assert np.all(lut.ids[k[plat]] == c[plat] - 1)


def test_kernel_cell_codes_match_grid():
    nk = pytest.importorskip("dvr_perception.rays._numba_kernels")
    assert nk._CELL_EMPTY == _grid.CELL_EMPTY
    assert nk._CELL_MIXED == _grid.CELL_MIXED


def test_only_the_newest_cell_maps_are_kept():
    vol = Volume(np.arange(4 * 5 * 6, dtype=np.uint8).reshape(4, 5, 6))
    for hi in range(20, 30):
        _map(vol, StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(10, hi)),)))
    kept = [k for k in _grid._store(vol) if isinstance(k, tuple) and k[0] == "cells"]
    assert len(kept) == _grid._CELL_MAPS_KEPT
