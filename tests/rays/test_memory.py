"""Memory plan (issue 17): whole or bricks, and one clear error before a run that cannot fit."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays import memory
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.phantom import make_phantom

pytest.importorskip("numba")


@pytest.fixture(scope="module")
def scene():
    vol, spec = make_phantom(size=40)
    return vol, spec, Camera.from_view(vol.bounds, width=48, height=48, azimuth=30.0)


def test_sizes_parse_and_bad_ones_are_named():
    assert memory.parse_size("2G") == 2 * 2**30
    assert memory.parse_size("1.5 GB") == int(1.5 * 2**30)
    assert memory.parse_size("300m") == 300 * 2**20
    for bad in ("lots", "-1G", "1e999", "10", "", "5X"):
        with pytest.raises(DVRInputError, match="--memory-limit: expected a memory size"):
            memory.parse_size(bad)


def test_limit_order(monkeypatch):
    monkeypatch.delenv(memory.ENV, raising=False)
    memory.set_limit(None)
    assert memory.limit() == int(memory.DEFAULT_FRACTION * memory.machine_memory())
    monkeypatch.setenv(memory.ENV, "3G")
    assert memory.limit() == 3 * 2**30
    memory.set_limit("2G")
    try:
        assert memory.limit() == 2 * 2**30
        assert memory.limit("1G") == 2**30
    finally:
        memory.set_limit(None)


def test_small_volume_is_whole_and_big_one_in_bricks():
    vol, spec = make_phantom(size=64)  # 2.4 MB whole (9 bytes a voxel) at a 16 x 16 image
    cam = Camera.from_view(vol.bounds, width=16, height=16, azimuth=30.0)
    whole = analyze(vol, spec, cam)
    assert "bricks" not in whole.stats
    parts = analyze(vol, spec, cam, memory_limit="2M")  # less than the whole run needs
    assert parts.stats["bricks"] >= 1
    assert np.array_equal(whole.rgba, parts.rgba)
    assert np.array_equal(whole.visible, parts.visible)


def test_a_run_that_cannot_fit_is_refused_before_it_starts(scene):
    vol, spec, cam = scene
    with pytest.raises(DVRInputError, match=r"memory: .* more than the memory limit of .*"
                       r"--memory-limit"):  # fmt: skip
        analyze(vol, spec, cam, memory_limit="1M")
    # a limit that fits the bricks but not the whole volume's derived arrays: bricks
    need = memory.plan(vol, 48 * 48, 10**6, k=6, shade=True, curvature=False,
                       build_cache=True, lut=_lut(vol, spec), membership=np.ones(300))  # fmt: skip
    assert need["mode"] == "whole"
    assert need["bricked"] > 0
    assert need["whole"] > 0


def _lut(vol, spec):
    from dvr_perception.structures.transfer import build_lut

    return build_lut(spec, scalar_range=vol.scalar_range, dtype=vol.data.dtype)
