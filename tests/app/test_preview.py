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
