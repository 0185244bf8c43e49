"""Label structures: a sample whose nearest voxel carries a structure's label belongs to it."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays import _grid
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume


def _scene(shade=True):
    z, y, x = np.mgrid[:30, :32, :34].astype(float)
    d = np.sqrt((x - 16) ** 2 + (y - 15) ** 2 + (z - 14) ** 2)
    data = np.clip(220 - 8 * d, 0, 255).astype(np.uint8)
    labels = np.zeros(data.shape, np.uint16)
    labels[10:19, 11:20, 12:21] = 7  # a box around the centre
    labels[2:5, 2:5, 2:5] = 3  # a label no structure uses
    vol = Volume(data, labels=labels)
    spec = StructureSpec(
        (
            Structure("shell", 0.3, (1, 0.5, 0), range=(60, 160), edge=0.2),
            Structure("box", 0.9, (0, 0, 1), label=7),
        ),
        rendering=RenderSettings(shade=shade),
    )
    return vol, spec, Camera.from_view(vol.bounds, width=40, height=40)


@pytest.mark.parametrize("shade", [True, False])
def test_numba_and_numpy_agree_with_labels(shade):
    vol, spec, cam = _scene(shade)
    a = analyze(vol, spec, cam, backend="numba", build_cache=True)
    b = analyze(vol, spec, cam, backend="numpy", build_cache=True)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.visible_share, b.visible_share)
    np.testing.assert_allclose(a.assigned_share, b.assigned_share, atol=1e-6)


def test_label_box_shows_only_where_its_voxels_project():
    vol, spec, cam = _scene()
    only = StructureSpec((spec.structures[1],), rendering=spec.rendering)
    res = analyze(vol, only, cam, build_cache=True)
    hit = res.accumulated > 0
    # front view: pixel columns/rows map to x/y; the box spans x 12..20 and y 11..19
    xs = (np.nonzero(hit.any(axis=0))[0] + 0.5) * 33 / 40
    ys = (np.nonzero(hit.any(axis=1))[0] + 0.5) * 31 / 40
    assert xs.min() >= 11.0
    assert xs.max() <= 21.0
    assert ys.min() >= 10.0
    assert ys.max() <= 20.0
    assert hit.sum() > 30
    # the only structure: all visibility is its own
    np.testing.assert_allclose(res.visible_share[0][hit], 1.0, atol=1e-6)
    np.testing.assert_allclose(res.assigned_share[0][hit], 1.0, atol=1e-6)


def test_label_wins_over_intensity_range():
    vol, _, cam = _scene()
    # a range that holds every voxel: without labels everything is "all"
    spec2 = StructureSpec(
        (
            Structure("all", 0.2, (1, 1, 1), range=(0, 255), edge=0.0),
            Structure("box", 1.0, (0, 0, 1), label=7),
        ),
        rendering=RenderSettings(shade=False),
    )
    res = analyze(vol, spec2, cam, build_cache=True)
    centre = (20, 20)
    assert res.assigned_share[1][centre] > 0.5  # the box takes its voxels from "all"
    beside = (res.accumulated > 0) & (res.assigned_share[1] == 0)
    assert beside.sum() > 100  # rays past the box see only "all"
    np.testing.assert_allclose(res.assigned_share[0][beside], 1.0, atol=1e-6)


def test_reevaluation_with_labels_equals_fresh_analysis():
    vol, spec, cam = _scene()
    base = analyze(vol, spec, cam, build_cache=True)
    for ops in ([0.05, 0.5], [0.9, 0.02]):
        fresh = analyze(vol, spec, cam, opacities=ops, build_cache=True)
        again = reevaluate(base.cache, opacities=ops)
        np.testing.assert_array_equal(again.image, fresh.image)
        np.testing.assert_array_equal(again.visible_share, fresh.visible_share)


def test_label_structures_need_a_label_volume():
    vol, spec, cam = _scene()
    bare = Volume(vol.data)
    with pytest.raises(DVRInputError, match=r"volume\.labels"):
        analyze(bare, spec, cam, build_cache=True)


def test_cells_with_a_labelled_corner_are_mixed():
    data = np.full((5, 5, 5), 0, np.uint8)
    labels = np.zeros(data.shape, np.uint8)
    labels[2, 2, 2] = 1
    vol = Volume(data, labels=labels)
    spec = StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(100, 200)),))
    lab = _grid.label_map(vol, [1])
    idx = _grid.index_volume(vol, 0.0, 1.0, 256)
    ids = np.full(256, -1, np.int16)
    memb = np.zeros(256, np.float32)
    cells = _grid.cell_map(vol, idx, ids, memb, lab)
    mixed = np.argwhere(cells[:-1, :-1, :-1] == _grid.CELL_MIXED)
    assert sorted(map(tuple, mixed)) == [(z, y, x) for z in (1, 2) for y in (1, 2) for x in (1, 2)]
    assert spec.structures[0].label is None
