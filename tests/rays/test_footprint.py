"""What a whole-volume analysis keeps in memory: the index inside the records, sparse scratch."""

from __future__ import annotations

import mmap
import sys

import numpy as np
import pytest

from dvr_perception.rays import _grid, engine
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.volume import Volume


def _data(seed=5, shape=(20, 22, 24)):
    """A smooth uint16 volume over 0..3000: a transfer table of more than 256 entries."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n) for n in shape), indexing="ij")
    ball = 3000 * np.exp(-2.0 * (x * x + 1.3 * y * y + 0.8 * z * z))
    return np.clip(ball + rng.normal(0, 60, shape), 0, 3000).astype(np.uint16)


def _spec(lo=400, mid=1500, shade=True):
    return StructureSpec(
        (
            Structure("outer", 0.4, (0.9, 0.6, 0.3), range=(lo, mid)),
            Structure("inner", 0.8, (0.2, 0.5, 1.0), range=(mid, 3000)),
        ),
        rendering=RenderSettings(shade=shade),
    )


_FIELDS = ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature",
           "importance_accumulated")  # fmt: skip


def _buffers(res) -> dict:
    out = {q: np.asarray(getattr(res, q)) for q in _FIELDS}
    if res.cache is not None:
        for q in ("start", "count", "lut", "curvature"):
            out["cache." + q] = np.asarray(getattr(res.cache, q))
        sh = np.asarray(res.cache.shading)
        out["cache.shading"] = np.where(sh[:, :1] == 65535, 65535, sh)  # unset: one marker
    return out


def _same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for q in a:
        assert a[q].dtype == b[q].dtype, q
        assert a[q].shape == b[q].shape, q
        assert np.array_equal(a[q], b[q], equal_nan=True), q


def test_the_index_lives_on_inside_the_voxel_records():
    vol = Volume(_data())
    spec = _spec()
    cam = Camera.from_view(vol.bounds, width=24, height=20)
    analyze(vol, spec, cam, backend="numba", build_cache=True)
    lut = build_lut(spec, scalar_range=_grid.scalar_range(vol), dtype=vol.data.dtype)
    assert lut.size > 256
    idx = _grid.index_volume(vol, lut.lo, lut.scale, lut.size)
    records = [v for k, v in _grid._store(vol).items() if k[0] == "records"]
    assert len(records) == 1
    assert not idx.flags.c_contiguous
    assert np.shares_memory(idx, records[0])
    fresh = Volume(vol.data.copy())
    assert np.array_equal(idx, _grid.index_volume(fresh, lut.lo, lut.scale, lut.size))
    # the walk behind early ray termination reads the records (a table too large for uint8)
    assert _grid.compact_index(vol, idx) is records[0]


@pytest.mark.parametrize("shape", [(20, 22, 24), (9, 31, 17)])
def test_analyses_after_the_index_moved_equal_those_of_a_fresh_volume(shape):
    data = _data(shape=shape)
    vol = Volume(data)
    cam = Camera.from_view(vol.bounds, width=26, height=21)
    curv = np.abs(np.sin(np.arange(data.size, dtype=np.float32))).reshape(data.shape)
    kinds = (
        {"curvature": curv, "build_cache": True},
        {"curvature": curv, "build_cache": False},
        {"curvature": curv, "build_cache": False, "exact": True},
        {"build_cache": False, "occlusion_free": False},
    )
    # new ranges on the same volume: a new cell map and records from the moved index; then
    # without shading (the walk reads the index from the records)
    for spec in (_spec(), _spec(600, 1200), _spec(), _spec(shade=False), _spec(500, 900, False)):
        for kw in kinds:
            got = analyze(vol, spec, cam, backend="numba", **kw)
            want = analyze(Volume(data.copy()), spec, cam, backend="numba", **kw)
            _same(_buffers(got), _buffers(want))
            if got.cache is not None:
                ops = [0.9, 0.3]
                _same(_buffers(reevaluate(got.cache, opacities=ops, light_direction=(0.4, 0.2, 1))),
                      _buffers(reevaluate(want.cache, opacities=ops,
                                          light_direction=(0.4, 0.2, 1))))  # fmt: skip


def test_a_table_that_fits_uint8_keeps_its_compact_index():
    data = (_data() // 12).astype(np.uint8)
    vol = Volume(data)
    spec = _spec(30, 120)
    cam = Camera.from_view(vol.bounds, width=16, height=16)
    got = analyze(vol, spec, cam, backend="numba", build_cache=False)
    lut = build_lut(spec, scalar_range=_grid.scalar_range(vol), dtype=vol.data.dtype)
    idx = _grid.index_volume(vol, lut.lo, lut.scale, lut.size)
    tix = _grid.compact_index(vol, idx)
    assert tix.dtype == np.uint8
    assert np.array_equal(tix, idx)
    want = analyze(Volume(data.copy()), spec, cam, backend="numba", build_cache=False)
    _same(_buffers(got), _buffers(want))


def _resident_kib(a: np.ndarray) -> float:
    """KiB resident of the mappings holding ``a`` (``/proc/self/smaps``)."""
    p = a.__array_interface__["data"][0]
    q = p + a.nbytes
    total, inside = 0.0, False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if head and "-" in head[0] and not head[0].endswith(":"):
                lo, hi = (int(v, 16) for v in head[0].split("-"))
                inside = lo < q and hi > p
            elif inside and head[0] == "Rss:":
                total += float(head[1])
    return total


def test_sparse_scratch_takes_memory_only_where_written():
    a = _grid.sparse_zeros((3 * 2**21, 2), np.uint16)  # 24 MiB
    assert a.shape == (3 * 2**21, 2)
    assert a.dtype == np.uint16
    assert a.flags.c_contiguous
    assert a.flags.writeable
    a[5 * 2**20 : 5 * 2**20 + 10] = 7  # a few entries in the middle
    assert int(a[5 * 2**20 + 9, 1]) == 7
    if sys.platform.startswith("linux") and hasattr(mmap, "MADV_NOHUGEPAGE"):
        assert _resident_kib(a) <= 64  # a page or two, not a 2 MiB huge page
    small = _grid.sparse_zeros((10, 3), np.float32)  # small: numpy's own
    assert small.shape == (10, 3)
    assert small.dtype == np.float32


def test_releasing_the_scratch_changes_no_result():
    vol = Volume(_data())
    spec = _spec()
    cam = Camera.from_view(vol.bounds, width=20, height=20)
    first = _buffers(analyze(vol, spec, cam, backend="numba", build_cache=True))
    engine.release_scratch()
    assert not engine._SCRATCH
    _same(first, _buffers(analyze(vol, spec, cam, backend="numba", build_cache=True)))
