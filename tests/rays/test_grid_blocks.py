"""The coarse block map of empty space and the tiled ray order of the numba walk."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.rays import _grid
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, ray_order
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.volume import Volume


def _blocks(vol, spec):
    lut = build_lut(spec, scalar_range=_grid.scalar_range(vol), dtype=vol.data.dtype)
    idx = _grid.index_volume(vol, lut.lo, lut.scale, lut.size)
    cells = _grid.cell_map(vol, idx, lut.ids, lut.membership)
    return cells, _grid.block_map(vol, cells)


def _bright_voxel():
    """A 13 x 14 x 15 volume with one bright voxel at (3, 4, 5), and its one structure."""
    data = np.zeros((13, 14, 15), np.uint8)
    data[3, 4, 5] = 200
    vol = Volume(data)
    spec = StructureSpec((Structure("dot", 1.0, (1, 1, 1), range=(100, 255)),))
    return vol, spec


def test_one_bright_voxel_gives_block_chessboard_distances():
    vol, spec = _bright_voxel()
    _, blocks = _blocks(vol, spec)
    # 12 x 13 x 14 cells -> 3 x 4 x 4 blocks; the voxel is a corner of cells z 2-3, y 3-4,
    # x 4-5, i.e. of blocks (0, 0, 1) and (0, 1, 1)
    assert blocks.shape == (3, 4, 4)
    busy = np.argwhere(blocks == 0)
    assert sorted(map(tuple, busy)) == [(0, 0, 1), (0, 1, 1)]
    for p in np.ndindex(blocks.shape):
        if blocks[p]:
            assert blocks[p] == np.abs(busy - np.array(p)).max(axis=1).min(), p


def test_empty_volume_has_the_largest_block_distance():
    vol = Volume(np.zeros((9, 9, 9), np.uint8))
    _, blocks = _blocks(vol, StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(100, 200)),)))
    assert blocks.shape == (2, 2, 2)
    assert np.all(blocks == 255)


def test_every_block_within_the_distance_holds_only_empty_cells():
    rng = np.random.default_rng(3)
    data = np.zeros((30, 33, 35), np.uint8)
    for _ in range(6):  # a few small bright specks in empty space
        z, y, x = (rng.integers(0, n - 2) for n in data.shape)
        data[z : z + 2, y : y + 2, x : x + 2] = rng.integers(120, 250)
    vol = Volume(data)
    spec = StructureSpec((Structure("specks", 0.7, (1, 1, 1), range=(100, 255)),))
    cells, blocks = _blocks(vol, spec)
    empty_cell = cells[:-1, :-1, :-1] == _grid.CELL_EMPTY
    b = _grid.BLOCK
    assert (blocks > 1).any()
    assert (blocks == 0).any()
    for p in zip(*np.nonzero(blocks), strict=True):
        d = int(blocks[p])
        lo = [max(q - d + 1, 0) * b for q in p]
        hi = [(q + d) * b for q in p]
        assert empty_cell[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].all(), p
        # and the distance is the largest such: a block at distance d holds a busy cell
        lo = [max(q - d, 0) * b for q in p]
        hi = [(q + d + 1) * b for q in p]
        assert not empty_cell[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].all(), p


def test_kernel_block_size_matches_grid():
    nk = pytest.importorskip("dvr_perception.rays._numba_kernels")
    assert nk._BLOCK == _grid.BLOCK == 4  # the kernels index blocks with ``>> 2``


def test_long_jumps_through_empty_space_change_nothing():
    """Sparse scene, oblique rays: block jumps in front of and behind early termination.

    The numpy back end samples every position; the numba walk must give the same result
    while visiting a small fraction of them.
    """
    pytest.importorskip("numba")
    data = np.zeros((60, 64, 62), np.uint8)
    z, y, x = np.mgrid[:60, :64, :62].astype(float)
    data[np.sqrt((x - 20) ** 2 + (y - 22) ** 2 + (z - 18) ** 2) < 6] = 230  # opaque ball
    data[np.sqrt((x - 44) ** 2 + (y - 40) ** 2 + (z - 42) ** 2) < 9] = 90  # veil ball behind
    vol = Volume(data)
    spec = StructureSpec(
        (
            Structure("veil", 0.2, (0.2, 0.6, 1.0), range=(60, 120)),
            Structure("ball", 1.0, (1.0, 0.8, 0.3), range=(180, 255)),
        ),
        rendering=RenderSettings(shade=True),
    )
    curv = np.linspace(0, 1, data.size, dtype=np.float32).reshape(data.shape)
    for azimuth in (35.0, 215.0):  # each ball in front once
        cam = Camera.from_view(vol.bounds, azimuth=azimuth, elevation=25, width=40, height=36)
        a = analyze(vol, spec, cam, curvature=curv, backend="numba")
        b = analyze(vol, spec, cam, curvature=curv, backend="numpy")
        for field in ("rgba", "visible", "assigned", "present", "curvature"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-6)
        assert a.accumulated.max() > 0.99
        assert a.present.max() == 3
        assert a.stats["samples_walked"] < a.stats["samples"] / 4


@pytest.mark.parametrize(("height", "width"), [(1, 1), (3, 20), (37, 50), (64, 64)])
def test_ray_order_visits_every_pixel_once_in_tiles(height, width):
    order, ptr = ray_order(height, width)
    n = height * width
    assert sorted(order.tolist()) == list(range(n))
    assert ptr[0] == 0
    assert ptr[-1] == n
    assert np.all(np.diff(ptr) > 0)
    t = 16
    ntiles = -(-height // t) * -(-width // t)
    assert len(ptr) - 1 == min(ntiles, 64)
    # a chunk's pixels come a whole tile at a time, rows in order inside each tile
    tile = (order // width // t) * 1000 + (order % width) // t
    first = order[: ptr[1]]
    runs = np.flatnonzero(np.diff(tile[: ptr[1]])) + 1
    for part in np.split(first, runs):
        assert np.all(np.diff(part // width) >= 0)
    assert not order.flags.writeable


def _occupancy_by_hand(cells):
    """Bit ``(z & 3) * 16 + (y & 3) * 4 + (x & 3)`` of block ``(z >> 2, y >> 2, x >> 2)``."""
    shape = tuple(-(-(n - 1) // 4) for n in cells.shape)
    out = np.zeros(shape, np.uint64)
    for z, y, x in zip(*np.nonzero(cells[:-1, :-1, :-1] != _grid.CELL_EMPTY), strict=True):
        bit = np.uint64(((z & 3) << 4) | ((y & 3) << 2) | (x & 3))
        out[z >> 2, y >> 2, x >> 2] |= np.uint64(1) << bit
    return out


def test_one_bright_voxel_occupies_its_eight_cells():
    vol, spec = _bright_voxel()
    cells, _ = _blocks(vol, spec)
    occ = _grid.block_occupancy(vol, cells)
    assert occ.shape == (3, 4, 4)
    assert occ.dtype == np.uint64
    # cells z 2-3, y 3-4, x 4-5: block (0, 0, 1) holds y = 3, block (0, 1, 1) y = 4
    bits = {(0, 0, 1): [(z, 3, x) for z in (2, 3) for x in (4, 5)],
            (0, 1, 1): [(z, 4, x) for z in (2, 3) for x in (4, 5)]}  # fmt: skip
    for p in np.ndindex(occ.shape):
        want = sum(1 << (((z & 3) << 4) | ((y & 3) << 2) | (x & 3)) for z, y, x in bits.get(p, []))
        assert int(occ[p]) == want, p
    assert _grid.block_occupancy(vol, cells) is occ  # memoised


@pytest.mark.parametrize("fast", [True, False])
def test_occupancy_bits_are_the_non_empty_cells(monkeypatch, fast):
    rng = np.random.default_rng(5)
    data = np.zeros((19, 22, 26), np.uint8)  # every size not a multiple of 4
    data[:, :, :11] = rng.random((19, 22, 11)) * 255  # noise in part, empty blocks beside it
    vol = Volume(data)
    spec = StructureSpec((Structure("mid", 0.6, (1, 0, 0), range=(90, 160)),
                          Structure("top", 0.9, (0, 1, 0), range=(200, 255))))  # fmt: skip
    cells, _ = _blocks(vol, spec)
    if not fast:
        monkeypatch.setattr(_grid, "_fast", lambda: None)
    occ = _grid.block_occupancy(None, cells)  # None: not memoised
    assert occ.shape == (5, 6, 7)
    want = _occupancy_by_hand(cells)
    assert 0 < np.count_nonzero(want) < want.size
    np.testing.assert_array_equal(occ, want)
