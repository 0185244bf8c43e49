"""The skipping walk behind early ray termination (DECISIONS D8) against the exact walk.

Without the re-evaluation cache ``analyze`` stops adding to a structure's ``assigned`` once it
reaches :data:`~dvr_perception.rays._grid.SATURATION` and, once the ray's transmittance at the
importances is below early ray termination, jumps blocks that can reach only saturated
structures; ``exact=True`` walks every sample.  Every buffer but ``assigned`` (which is
``min(assigned, 1)``) and every measure's terms must be the exact walk's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dvr_perception.measures import all_measures
from dvr_perception.rays import _grid
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, analyze_views
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.volume import Volume

pytest.importorskip("numba")

REPO = Path(__file__).resolve().parents[2]
#: The buffers the measures read, equal to the bit between the two walks.
SAME = ("rgba", "image", "accumulated", "visible", "present", "curvature",
        "importance_accumulated")  # fmt: skip
TERMS = ("E_v", "E_s", "E_t")


def _spec(*structures):
    return StructureSpec(tuple(structures), rendering=RenderSettings(shade=False))


def _top_camera(vol: Volume, size: int = 8) -> Camera:
    """Parallel camera looking down -z: every ray crosses the volume from its top face."""
    cx, cy, cz = vol.center
    return Camera(
        position=(cx, cy, cz + 100.0),
        focal_point=(cx, cy, cz),
        parallel_projection=True,
        parallel_scale=4.0,
        width=size,
        height=size,
    )


def _slab_and_layer() -> Volume:
    """An opaque slab (z 16..47, value 220) in front of a thin layer (z 3..4, value 100)."""
    data = np.zeros((48, 16, 16), np.uint8)
    data[16:] = 220
    data[3:5] = 100
    return Volume(data)


SLAB = Structure("slab", 1.0, (1, 1, 1), range=(180, 255), edge=0.0)
LAYER = Structure("layer", 0.05, (1, 0, 0), range=(60, 140), edge=0.0)


def _terms(analysis, spec) -> dict:
    m = all_measures(analysis, spec)
    return {"E_v": m.visibility.E_v, "E_s": m.shape.E_s, "E_t": m.transparency.E_t}


def _assert_skip_equals_exact(skip, exact, spec=None, atol=1e-6):
    assert skip.stats["assigned_cap"] == _grid.SATURATION
    assert exact.stats["assigned_cap"] is None
    for name in SAME:
        np.testing.assert_array_equal(getattr(skip, name), getattr(exact, name), err_msg=name)
    np.testing.assert_array_equal(skip.assigned, np.minimum(exact.assigned, _grid.SATURATION))
    if spec is not None:
        ts, te = _terms(skip, spec), _terms(exact, spec)
        for t in TERMS:
            assert abs(ts[t] - te[t]) <= atol, (t, ts[t], te[t])


def test_opaque_slab_skipped_and_the_thin_layer_behind_it_still_found():
    vol = _slab_and_layer()
    spec = _spec(LAYER, SLAB)
    cam = _top_camera(vol)
    exact = analyze(vol, spec, cam, build_cache=False, exact=True)
    skip = analyze(vol, spec, cam, build_cache=False)
    _assert_skip_equals_exact(skip, exact, spec)
    # the slab saturates within its first planes; the exact walk still adds the rest of it
    assert np.all(exact.assigned[1] > 5.0)
    assert np.all(skip.assigned[1] == 1.0)
    # the thin layer, 12 planes behind the slab, is present on every ray with its full share
    assert np.all(skip.present == 3)
    np.testing.assert_array_equal(skip.assigned[0], exact.assigned[0])
    assert np.all((skip.assigned[0] > 0.05) & (skip.assigned[0] < 1.0))
    assert np.all(skip.visible[0] == 0.0)  # hidden: found only behind termination
    # a sample every voxel along z: the exact walk looks at all 47 of a ray; the skipping one
    # at the slab's first plane, one per block of 4 planes after it (7), the 4 of the block
    # at the slab's face (its cells' values run from 0 to 220 through the layer's range, so
    # the layer may be there), one for the empty block and the 8 of the layer's two blocks
    n = cam.width * cam.height
    assert exact.stats["samples_walked"] >= 40 * n  # empty blocks are jumped
    assert skip.stats["samples_walked"] <= 22 * n


def test_a_ray_stops_once_every_structure_has_saturated():
    vol = _slab_and_layer()
    spec = _spec(SLAB)  # one structure: saturated in the slab's first planes
    cam = _top_camera(vol)
    exact = analyze(vol, spec, cam, build_cache=False, exact=True)
    skip = analyze(vol, spec, cam, build_cache=False)
    _assert_skip_equals_exact(skip, exact, spec)
    n = cam.width * cam.height
    assert skip.stats["samples_walked"] == n  # the first sample saturates, the ray stops
    assert exact.stats["samples_walked"] >= 40 * n  # empty blocks are jumped


def test_importance_transmittance_still_terminates_the_skipping():
    """A structure rendered opaque but of low importance: the transmittance at the importances
    (``A_imp``) stays above termination, so every sample is still looked at."""
    vol = _slab_and_layer()
    slab = Structure("slab", 0.02, (1, 1, 1), range=(180, 255), edge=0.0, opacity=1.0)
    spec = _spec(LAYER, slab)
    cam = _top_camera(vol)
    exact = analyze(vol, spec, cam, build_cache=False, exact=True)
    skip = analyze(vol, spec, cam, build_cache=False)
    _assert_skip_equals_exact(skip, exact, spec)
    assert skip.stats["samples_walked"] == exact.stats["samples_walked"]
    assert np.all(skip.importance_accumulated < 0.9)


def test_the_cache_building_walk_is_always_exact():
    vol = _slab_and_layer()
    spec = _spec(LAYER, SLAB)
    cam = _top_camera(vol)
    built = analyze(vol, spec, cam, build_cache=True)
    exact = analyze(vol, spec, cam, build_cache=False, exact=True)
    assert built.stats["assigned_cap"] is None
    assert built.stats["samples_walked"] == exact.stats["samples_walked"]
    np.testing.assert_array_equal(built.assigned, exact.assigned)


def test_structure_blocks_numba_equals_numpy_and_covers_every_cell():
    rng = np.random.default_rng(5)
    data = rng.integers(0, 256, (21, 18, 27)).astype(np.uint8)
    data[:, :, :9] = 0  # a region with nothing
    data[10:, :, 12:] = 200  # one structure only
    labels = np.zeros(data.shape, np.uint8)
    labels[2:4, 5:7, 20:22] = 7
    vol = Volume(data, labels=labels)
    spec = StructureSpec((
        Structure("low", 0.3, (1, 0, 0), range=(40, 120)),
        Structure("high", 0.6, (0, 1, 0), range=(150, 255)),
        Structure("lab", 0.5, (0, 0, 1), label=7),
    ))  # fmt: skip
    lut = build_lut(spec, scalar_range=_grid.scalar_range(vol), dtype=vol.data.dtype)
    idx = _grid.index_volume(vol, lut.lo, lut.scale, lut.size)
    lab = _grid.label_map(vol, [7])
    ids = np.append(lut.ids, 2)
    memb = np.append(lut.membership, 1.0)
    bits = np.where(memb > 0, np.left_shift(1, ids), 0).astype(np.uint32)
    fast = _grid.structure_blocks(None, idx, bits, lab, lut.size)
    assert fast.shape == _grid.block_map(vol, _grid.cell_map(vol, idx, ids, memb, lab)).shape
    ref = np.zeros_like(fast)
    n = len(bits)
    change = np.flatnonzero(bits[1:] != bits[:-1]) + 1
    run = np.cumsum(np.isin(np.arange(n), change)).astype(np.int64)
    run_bits = bits[np.concatenate([[0], change])]
    _grid._structure_blocks_numpy(idx, run, run_bits, bits, lab, True, lut.size, lut.size - 1,
                                  ref)  # fmt: skip
    np.testing.assert_array_equal(fast, ref)
    assert np.all(fast[:, :, :2] == 0)  # x cells 0..7: voxels 0..8, all 0
    assert np.all(fast[3:, :, 4:] == 2)  # z from 12, x from 16: only "high"
    assert fast[0, 1, 5] & 4  # the label structure's block
    assert not np.any(fast[2:] & 4)
    # every cell's corners' structures are in its block's mask
    for z, y, x in zip(*np.nonzero(np.ones((20, 17, 26), bool)), strict=True):
        corners = idx[z : z + 2, y : y + 2, x : x + 2]
        want = np.bitwise_or.reduce(bits[corners.ravel()])
        assert want & ~fast[z // 4, y // 4, x // 4] == 0


def test_phantom_every_buffer_and_term_as_the_exact_walk_whole_bricked_and_views():
    vol, spec = make_phantom(size=40)
    cams = [Camera.from_view(vol.bounds, azimuth=az, elevation=20, width=40, height=40)
            for az in (0, 120, 240)]  # fmt: skip
    for cam in cams:
        exact = analyze(vol, spec, cam, build_cache=False, exact=True)
        skip = analyze(vol, spec, cam, build_cache=False)
        _assert_skip_equals_exact(skip, exact, spec)
        assert skip.stats["samples_walked"] <= exact.stats["samples_walked"]
        bricked = analyze(vol, spec, cam, build_cache=False, brick=(9, 10, 11))
        _assert_skip_equals_exact(bricked, exact)
        bricked_exact = analyze(vol, spec, cam, build_cache=False, brick=(9, 10, 11), exact=True)
        np.testing.assert_array_equal(bricked_exact.assigned, exact.assigned)
    views = analyze_views(vol, spec, cams, build_cache=False, exact=True)
    assert all(v.stats["assigned_cap"] is None for v in views)
    views = analyze_views(vol, spec, cams, build_cache=False)
    assert all(v.stats["assigned_cap"] == _grid.SATURATION for v in views)


@pytest.mark.parametrize("name", ["cthead", "engine"])
def test_shared_volumes_skip_equals_exact(shared_data, name):
    from dvr_perception.structures.io import attach_labels, load_spec
    from dvr_perception.volume.io import load_volume

    spec = load_spec(REPO / "state_files" / f"{name}.json")
    vol = attach_labels(load_volume(shared_data / f"{name}.nhdr"), spec)
    fewer = 0
    for az in (0, 120, 240):
        cam = Camera.from_view(vol.bounds, azimuth=az, elevation=20, width=48, height=48)
        exact = analyze(vol, spec, cam, build_cache=False, exact=True)
        skip = analyze(vol, spec, cam, build_cache=False)
        _assert_skip_equals_exact(skip, exact, spec)
        fewer += skip.stats["samples_walked"] < exact.stats["samples_walked"]
    assert fewer == 3


def test_structure_distances_are_chessboard_distances_to_blocks_reaching_each_structure():
    smask = np.zeros((3, 4, 5), np.uint32)
    smask[0, 0, 0] = 1  # structure 0 in one corner block
    smask[2, 3, 4] = 2 | 1  # structures 0 and 1 in the opposite corner
    dist = _grid.structure_distances(smask, 3)
    assert dist.shape == (3, 3, 4, 5)
    for p in np.ndindex(smask.shape):
        d0 = min(max(abs(np.subtract(p, (0, 0, 0)))), max(abs(np.subtract(p, (2, 3, 4)))))
        assert dist[0][p] == d0
        assert dist[1][p] == max(abs(np.subtract(p, (2, 3, 4))))
    assert np.all(dist[2] == 255)  # structure 2: in no block
    assert _grid.structure_distances(smask, 3) is dist  # memoised


def test_long_jumps_over_blocks_far_from_unsaturated_structures():
    """Behind a saturated slab a long run of its blocks is crossed in a few jumps: the walk
    visits about as many samples as through a short slab, however deep the slab."""
    walked = []
    for depth in (40, 160):
        data = np.zeros((depth + 12, 16, 16), np.uint8)
        data[12:] = 220
        data[3:5] = 100
        vol = Volume(data)
        spec = _spec(LAYER, SLAB)
        cam = _top_camera(vol)
        exact = analyze(vol, spec, cam, build_cache=False, exact=True)
        skip = analyze(vol, spec, cam, build_cache=False)
        _assert_skip_equals_exact(skip, exact, spec)
        walked.append((skip.stats["samples_walked"], exact.stats["samples_walked"]))
    (s40, e40), (s160, e160) = walked
    assert e160 - e40 >= 100 * 64  # the exact walk visits every plane of the deeper slab
    assert s160 - s40 <= 5 * 64  # the skipping walk: a few jumps more


def test_the_thickness_readings_ask_for_the_exact_walk():
    """The thickness composition reads ``assigned`` beyond saturation: refused on a skipping
    analysis (its image-wide ``assigned_share`` is that of the capped opacities)."""
    from dvr_perception.errors import DVRInputError
    from dvr_perception.measures import visibility

    vol = _slab_and_layer()
    spec = _spec(LAYER, SLAB)
    cam = _top_camera(vol)
    skip = analyze(vol, spec, cam, build_cache=False)
    exact = analyze(vol, spec, cam, build_cache=False, exact=True)
    with pytest.raises(DVRInputError, match="exact=True"):
        visibility(skip, spec, composition="thickness")
    thick = visibility(exact, spec, composition="thickness")
    assert thick.per_structure["slab"]["assigned_share"] > 0.8  # the slab's whole depth
    capped = visibility(skip, spec).per_structure["slab"]["assigned_share"]
    assert 0.5 < capped < thick.per_structure["slab"]["assigned_share"]
