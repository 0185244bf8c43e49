"""The memory plan's rule (issue 31): the whole volume whenever its peak fits the limit.

No voxel count decides any more (the old rule bricked every volume over 64 M voxels, so a
512 x 512 x 452 CT that fits a workstation many times over was analysed 15x slower in
bricks).  The plan estimates the whole-volume run's peak (the volume, its derived volumes,
``|H|``, samples, scratch, per-ray buffers) and chooses it when that fits; the CT shapes are
planned here without allocating them (a broadcast array has their size and no memory).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dvr_perception import _memory
from dvr_perception.rays import memory
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature_field import CurvatureField, CurvaturePages, curvature_source
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.structures.transfer import build_lut

pytest.importorskip("numba")

#: The voxel count over which the old rule bricked every volume.
OLD_RULE = 64 * 2**20


@pytest.fixture(autouse=True)
def _no_reused_buffers():
    """Each test plans from a clean slate: the buffers earlier bricked runs of the process left
    for reuse count in every plan (and a plan that must fit drops them), whatever the volume."""
    memory.drop_kept(None, ("bricks_buffers", "bricks_runs"))


def _ct(shape):
    """A uint16 CT of ``shape`` (z, y, x) that takes no memory, and the phantom's spec."""
    _, spec = make_phantom(size=16)
    data = np.broadcast_to(np.uint16(0), shape)
    vol = SimpleNamespace(data=data, labels=None, name="ct")
    lut = build_lut(spec, scalar_range=(0.0, 4095.0), dtype=np.uint16)
    return vol, spec, lut, np.ones(lut.size, np.uint32)


def _plan(vol, spec, lut, memb, limit, *, pixels=512, depth=700, build_cache=False):
    return memory.plan(vol, pixels * pixels, pixels * pixels * depth, k=len(spec.structures),
                       shade=True, curvature=True, build_cache=build_cache, lut=lut,
                       membership=memb, memory_limit=limit)  # fmt: skip


def test_a_ct_over_the_old_voxel_rule_is_whole_when_it_fits():
    vol, spec, lut, memb = _ct((452, 512, 512))
    assert vol.data.size > OLD_RULE  # the old rule bricked it whatever the limit
    need = _plan(vol, spec, lut, memb, "16G")
    assert need["mode"] == "whole"
    # the estimate is the run's peak: the volume (2 B), records (4, the table index inside),
    # cell map (1), |H| (4) and the blocks' occupancy bits (1/8) a voxel (a table of over 256
    # entries: no compact index), and
    # the per-ray buffers, and 2 a voxel of temporaries while the derived volumes are made
    # (the index beside the records being built); 1.5-2 GB, as measured (issue 31: 1.9 GB
    # peak RSS with the curvature's own temporaries)
    assert lut.size > 256
    per_voxel = 2 + 4 + 1 + 4 + memory.TRANSIENT_VOXEL_BYTES
    assert need["whole"] == pytest.approx(vol.data.size * per_voxel + vol.data.size // 8 + 512 * 512
                                          * memory.ray_bytes(len(spec.structures)))  # fmt: skip
    assert 1.5 * 2**30 < need["whole"] < 2 * 2**30


def test_the_limit_alone_decides_at_the_byte():
    vol, spec, lut, memb = _ct((452, 512, 512))
    whole = int(_plan(vol, spec, lut, memb, "16G")["whole"])
    assert _plan(vol, spec, lut, memb, whole)["mode"] == "whole"
    below = _plan(vol, spec, lut, memb, whole - 1)
    assert below["mode"] == "bricks"
    assert below["bricked"] <= whole - 1


def test_the_default_limit_is_a_quarter_of_the_machine(monkeypatch):
    monkeypatch.delenv(memory.ENV, raising=False)
    memory.set_limit(None)
    big, spec, lut, memb = _ct((904, 1024, 1024))  # the 1024 x 1024 x 904 CT
    whole = int(_plan(big, spec, lut, memb, "64G")["whole"])
    assert 11 * 2**30 < whole < 12 * 2**30  # 13 bytes a voxel
    monkeypatch.setattr(_memory, "machine_memory", lambda: 4 * whole)
    assert memory.limit() == whole
    assert _plan(big, spec, lut, memb, None)["mode"] == "whole"
    monkeypatch.setattr(_memory, "machine_memory", lambda: 4 * whole - 4)
    assert _plan(big, spec, lut, memb, None)["mode"] == "bricks"


def test_the_cache_of_samples_counts_when_it_is_kept():
    vol, spec, lut, memb = _ct((452, 512, 512))
    bare = _plan(vol, spec, lut, memb, "64G")["whole"]
    kept = _plan(vol, spec, lut, memb, "64G", build_cache=True)["whole"]
    assert kept > bare  # samples and scratch of the cache on top


def test_small_analyses_follow_the_same_rule_and_agree():
    vol, spec = make_phantom(size=64)
    cam = Camera.from_view(vol.bounds, width=16, height=16, azimuth=30.0)
    whole = analyze(vol, spec, cam, memory_limit="64M")
    assert "bricks" not in whole.stats
    parts = analyze(vol, spec, cam, memory_limit="2M")  # under the 2.4 MB of the volume's share
    assert parts.stats["bricks"] > 1
    np.testing.assert_allclose(parts.rgba, whole.rgba, atol=1e-6)
    np.testing.assert_allclose(parts.visible, whole.visible, atol=1e-6)


def test_curvature_is_whole_exactly_when_the_volumes_share_fits():
    vol, spec = make_phantom(size=64)
    need = memory.whole_volume_bytes(vol)
    assert vol.labels is not None
    # the uint8 volume, records (the table index inside them), compact index, cell map,
    # label map and |H|, and the blocks' occupancy bits (one bit a cell)
    assert need == 64**3 * (1 + 4 + 1 + 1 + 1 + 4) + 64**3 // 8
    # with the uint8 label volume and the temporaries made beside the derived volumes
    need += 64**3 * (1 + memory.TRANSIENT_VOXEL_BYTES)
    assert isinstance(curvature_source(vol, spec, memory_limit=need), CurvaturePages)
    assert isinstance(curvature_source(vol, spec, memory_limit=need - 1), CurvatureField)
