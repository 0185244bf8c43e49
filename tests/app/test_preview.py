"""The quick preview's scene: a small copy of the volume with the spec's transfer function."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.app.preview import PREVIEW_DIM, Preview, preview_volume
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.volume import Volume


def test_copy_keeps_every_nth_voxel_and_the_extent():
    data = np.arange(130 * 20 * 10, dtype=np.uint16).reshape(130, 20, 10)
    vol = Volume(data, spacing=(1.0, 2.0, 0.5), origin=(3.0, 0.0, 0.0))
    small = preview_volume(vol, max_dim=64)
    assert small.data.shape == (44, 7, 4)  # every 3rd voxel
    assert small.spacing == (3.0, 6.0, 1.5)
    assert small.origin == vol.origin
    assert np.array_equal(small.data, data[::3, ::3, ::3])
    assert preview_volume(vol, max_dim=200) is vol


@pytest.mark.parametrize("oriented", [True, False])
def test_copy_keeps_the_direction_and_the_orientation_flag(oriented):
    """A strided copy lies on the same rotated grid: first voxel, axes and ``oriented`` kept,
    so every corner voxel of the copy is at the world position of the same full voxel."""
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    rot = ((-c, -s, 0.0), (-s, c, 0.0), (0.0, 0.0, -1.0))  # x and z flipped, turned about z
    data = np.zeros((70, 9, 8), np.uint8)
    vol = Volume(data, spacing=(1.0, 2.0, 0.5), origin=(5.0, -2.0, 7.0), direction=rot,
                 oriented=oriented)  # fmt: skip
    small = preview_volume(vol, max_dim=32)  # every 3rd voxel
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
    assert max(p.image.GetDimensions()) <= PREVIEW_DIM
    otf = p.property.GetScalarOpacity()
    assert otf.GetValue(25.0) == pytest.approx(0.5)  # inside a's range: its opacity
    assert otf.GetValue(70.0) == 0.0
    assert p.property.GetRGBTransferFunction().GetColor(25.0) == pytest.approx((1, 0, 0))
    assert p.actor.GetVisibility() == 1
    # only label structures: nothing to show
    p.set_spec(StructureSpec((spec.structures[1],)))
    assert p.actor.GetVisibility() == 0
