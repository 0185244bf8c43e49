"""The quick preview's scene: the volume (reduced above a budget) and the spec's colours."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.app.preview import (
    PREVIEW_VOXELS,
    RAY_STEP_VOXELS,
    Preview,
    preview_detail,
    preview_step,
    preview_volume,
)
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.volume import Volume


def test_copy_keeps_every_nth_voxel_and_the_extent():
    data = np.arange(130 * 20 * 10, dtype=np.uint16).reshape(130, 20, 10)
    vol = Volume(data, spacing=(1.0, 2.0, 0.5), origin=(3.0, 0.0, 0.0))
    # 26000 voxels: every 2nd leaves 65 x 10 x 5 = 3250, every 3rd 44 x 7 x 4 = 1232
    small = preview_volume(vol, max_voxels=1232)
    assert small.data.shape == (44, 7, 4)  # every 3rd voxel
    assert small.spacing == (3.0, 6.0, 1.5)
    assert small.origin == vol.origin
    assert np.array_equal(small.data, data[::3, ::3, ::3])
    assert preview_volume(vol, max_voxels=1231).data.shape == (33, 5, 3)  # every 4th
    assert preview_volume(vol, max_voxels=26000) is vol
    assert preview_volume(vol) is vol


def test_full_resolution_up_to_the_budget():
    """The budget is 256\u00b3 voxels: cthead (256 x 256 x 113) is sent whole."""
    assert PREVIEW_VOXELS == 256**3
    assert preview_step((256, 256, 113)) == 1
    assert preview_step((256, 256, 256)) == 1
    assert preview_step((256, 256, 257)) == 2  # one voxel over: every 2nd
    assert preview_step((1024, 1024, 64)) == 2  # 512 x 512 x 32 = 8.4 million
    assert preview_step((2048, 2048, 2048)) == 8
    assert preview_detail((256, 256, 113), (256, 256, 113)) == (
        "full volume, 256\u00d7256\u00d7113 voxels"
    )
    assert "every 3rd voxel" in preview_detail((600, 600, 600), (200, 200, 200))
    assert "256\u00b3-voxel budget" in preview_detail((600, 600, 600), (200, 200, 200))
    # 64-bit floats go as 32-bit floats, nothing else changes
    vol = Volume(np.linspace(0, 1, 8**3).reshape(8, 8, 8))
    copy = preview_volume(vol)
    assert copy.data.dtype == np.float32
    assert np.array_equal(copy.data, vol.data.astype(np.float32))
    assert copy.spacing == vol.spacing


@pytest.mark.parametrize("oriented", [True, False])
def test_copy_keeps_the_direction_and_the_orientation_flag(oriented):
    """A strided copy lies on the same rotated grid: first voxel, axes and ``oriented`` kept,
    so every corner voxel of the copy is at the world position of the same full voxel."""
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    rot = ((-c, -s, 0.0), (-s, c, 0.0), (0.0, 0.0, -1.0))  # x and z flipped, turned about z
    data = np.zeros((70, 9, 8), np.uint8)
    vol = Volume(data, spacing=(1.0, 2.0, 0.5), origin=(5.0, -2.0, 7.0), direction=rot,
                 oriented=oriented)  # fmt: skip
    small = preview_volume(vol, max_voxels=24 * 3 * 3)  # every 3rd voxel
    np.testing.assert_allclose(small.direction, vol.direction, atol=1e-12)
    assert small.oriented is oriented
    assert small.origin == vol.origin
    last = np.array(small.dims) - 1
    np.testing.assert_allclose(
        small.to_world(np.array(small.origin) + last * small.spacing),
        vol.to_world(np.array(vol.origin) + 3 * last * vol.spacing),
    )


def test_preview_scene_follows_the_spec():
    vol = Volume(np.linspace(0, 100, 100**3).reshape(100, 100, 100).astype(np.float32))
    spec = StructureSpec(
        (
            Structure("a", 0.5, (1.0, 0.0, 0.0), range=(10.0, 40.0)),
            Structure("l", 0.5, (0.0, 0.0, 1.0), label=2),
        )
    )
    p = Preview(vol, spec)
    assert p.image.GetDimensions() == (100, 100, 100)  # the whole volume, under the budget
    assert p.detail == "full volume, 100\u00d7100\u00d7100 voxels"
    assert p.mapper.GetSampleDistance() == pytest.approx(RAY_STEP_VOXELS * 1.0)
    otf = p.property.GetScalarOpacity()
    assert otf.GetValue(25.0) == pytest.approx(0.5)  # inside a's range: its opacity
    assert otf.GetValue(70.0) == 0.0
    assert p.property.GetRGBTransferFunction().GetColor(25.0) == pytest.approx((1, 0, 0))
    assert p.actor.GetVisibility() == 1
    # only label structures: nothing to show
    p.set_spec(StructureSpec((spec.structures[1],)))
    assert p.actor.GetVisibility() == 0
