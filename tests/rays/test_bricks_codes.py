"""A bricked cache keeps the normal codes of its front bricks while they fit (issue 31).

Under the default limit (a quarter of the machine) the 1024 x 1024 x 904 CT's codes (2 bytes
a voxel) did not all fit beside the bricked run, and every change of light during the
optimiser's lighting stage derived all 64 bricks again from the volume (1333 s on a loaded
2-core machine).  Codes are now kept brick by brick in view order while they fit: a new
light re-derives only the bricks without them, with the same shading.  Or rather (the
default, ``REFILL_FROM_DATA``) it derives nothing: the entries of the bricks without codes are
shaded from normal codes computed from the volume at their cells' corners.
"""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.rays import bricks
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.phantom import make_phantom

pytest.importorskip("numba")

BUFFERS = ("rgba", "visible", "assigned", "accumulated")


@pytest.mark.parametrize("from_data", [True, False])
def test_codes_kept_for_the_front_bricks_only_reshade_as_the_whole_cache(monkeypatch, from_data):
    monkeypatch.setattr(bricks, "REFILL_FROM_DATA", from_data)
    vol, spec = make_phantom(size=40)
    curv = curvature_volume(vol, spec)[0]
    cam = Camera.from_view(vol.bounds, width=24, height=24, azimuth=40.0, elevation=-20.0)
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    size = (11, 17, 13)
    every = bricks.split(vol.data.shape, size)
    codes = sum(2 * int(np.prod([b - a for a, b in br.voxels(vol.data.shape)])) for br in every)
    limit = 64 * 2**20
    monkeypatch.setattr(bricks, "_memo", lambda *args, **kw: (None, None))  # no memo: codes
    monkeypatch.setattr(bricks, "KEEP_CODES_SHARE", 0.5 * codes / limit)  # half of them fit
    derived = []
    real, records = bricks.derive, bricks._records
    monkeypatch.setattr(bricks, "derive", lambda *a: derived.append(1) or real(*a))
    monkeypatch.setattr(bricks, "_records", lambda *a: derived.append(1) or records(*a))
    parts = analyze(vol, spec, cam, curvature=curv, brick=size, memory_limit=limit,
                    build_cache=True)  # fmt: skip
    assert parts.cache.lazy["fill"] is None  # not every brick's codes: shaded at the walk
    assert len(derived) == len(every)
    light = {"light_direction": (0.5, -0.4, 0.75)}
    a, b = reevaluate(whole.cache, **light), reevaluate(parts.cache, **light)
    for name in BUFFERS:
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), atol=1e-6, err_msg=name)
    assert b.visible.sum() > 0.0
    again = len(derived) - len(every)  # the bricks without kept codes, read again
    if from_data:
        assert again == 0  # their entries shaded from the volume
    else:
        assert 0 < again < len(every)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.7, 1.3, 2.1)])
def test_a_new_light_shades_from_the_volume_as_from_the_records(monkeypatch, spacing):
    """No memo and no codes kept: every entry's 8 normal codes come from the volume.

    Bricks on the volume's border and inside it (their corner voxels' neighbours in the ghost
    layer), an anisotropic grid (the gradient's aspect), two lights in a row: the shading
    equals the whole volume's and the re-derived records' to the last bit.
    """
    from dvr_perception.volume.volume import Volume

    base, spec = make_phantom(size=36)
    vol = Volume(base.data, spacing, base.origin)
    cam = Camera.from_view(vol.bounds, width=28, height=24, azimuth=-35.0, elevation=25.0)
    whole = analyze(vol, spec, cam, build_cache=True)
    monkeypatch.setattr(bricks, "MEMO_SHARE", 0.0)
    monkeypatch.setattr(bricks, "KEEP_CODES_SHARE", 0.0)
    parts = bricks.analyze_bricked(vol, spec, cam, brick=(10, 14, 9))
    assert parts.cache.lazy["fill"] is None
    got = {}
    for from_data in (True, False):
        monkeypatch.setattr(bricks, "REFILL_FROM_DATA", from_data)
        for light in ((0.5, -0.4, 0.75), (-0.2, 0.9, 0.3)):
            got[from_data, light] = reevaluate(parts.cache, light_direction=light)
            got[from_data, light, "shading"] = parts.cache.shading.copy()
            ref = reevaluate(whole.cache, light_direction=light)
            for name in BUFFERS:
                np.testing.assert_allclose(getattr(got[from_data, light], name),
                                           getattr(ref, name), atol=1e-6, err_msg=name)  # fmt: skip
            assert ref.visible.sum() > 0.0
    for light in ((0.5, -0.4, 0.75), (-0.2, 0.9, 0.3)):
        assert np.array_equal(got[True, light, "shading"], got[False, light, "shading"])
        assert np.array_equal(got[True, light].rgba, got[False, light].rgba)
    bricks._MEMO.pop(vol, None)


@pytest.mark.parametrize("shape", [(9, 14, 11), (13, 8, 17), (2, 6, 5)])
def test_records_reached_codes_the_corners_of_the_marked_blocks_only(shape):
    """A voxel gets its code when a cell it is a corner of (``v - 1`` or ``v``) is marked."""
    from dvr_perception.rays import _grid
    from dvr_perception.rays._numba_bricks import records_reached
    from dvr_perception.rays._numba_grid import _ZERO_CODE
    from dvr_perception.volume.volume import Volume

    rng = np.random.default_rng(sum(shape))
    data = rng.integers(0, 4000, shape).astype(np.uint16)
    index = rng.integers(0, 256, shape).astype(np.uint8)
    vol = Volume(data, (0.8, 1.0, 1.7), (0.0, 0.0, 0.0))
    codes = _grid.normal_codes(vol).astype(np.uint32)
    aspect = (2.0 * np.asarray(vol.spacing) / np.mean(vol.spacing)).astype(np.float32)
    blocks = tuple(-(-max(n - 1, 1) // 4) for n in shape)
    for density in (0.0, 0.3, 1.0):
        mask = rng.random(blocks) < density
        # per axis, the blocks of cells v - 1 and v (clamped to the cells 0 .. n - 2)
        b0, b1 = (
            [np.clip(np.arange(n) + d, 0, max(n - 2, 0)) >> 2 for n in shape] for d in (-1, 0)
        )
        need = np.zeros(shape, bool)
        for bz in (b0[0], b1[0]):
            for by in (b0[1], b1[1]):
                for bx in (b0[2], b1[2]):
                    need |= mask[np.ix_(bz, by, bx)]
        want = index.astype(np.uint32) | (np.where(need, codes, _ZERO_CODE).astype(np.uint32) << 16)
        out = np.full(shape, 7, np.uint32)
        records_reached(data, aspect, index, mask, out)
        assert np.array_equal(out, want), density
        assert need.any() == mask.any()
