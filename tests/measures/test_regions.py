"""Tests for dvr_perception.measures.regions on tiny hand-drawn images."""

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import layer_footprints, layer_relations, subregions


def disc(shape, center, radius):
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    return (rr - center[0]) ** 2 + (cc - center[1]) ** 2 <= radius**2


def test_footprints_threshold_is_strict():
    vis = np.array([[[0.05, 0.0501], [0.0, 1.0]], [[0.2, 0.0], [0.0, 0.0]]])
    fp = layer_footprints(vis)
    assert fp.dtype == bool
    np.testing.assert_array_equal(fp[0], [[False, True], [False, True]])
    np.testing.assert_array_equal(layer_footprints(vis, threshold=0.3)[1], [[False, False]] * 2)


def test_footprints_reject_bad_input():
    with pytest.raises(DVRInputError, match="visible"):
        layer_footprints(np.zeros((4, 4)))
    with pytest.raises(DVRInputError, match="threshold"):
        layer_footprints(np.zeros((1, 4, 4)), threshold=1.0)


def test_subregions_two_overlapping_rectangles():
    fp = np.zeros((2, 4, 6), bool)
    fp[0, :, 0:4] = True
    fp[1, 1:3, 2:6] = True
    rmap = subregions(fp)
    kinds = [(r.kind, tuple(sorted(r.layers))) for r in rmap.regions]
    # row-major first pixels: L0 (0,0), empty (0,4), overlay (1,2), L1 (1,4), empty (3,4);
    # the two empty corners are separated by L1
    assert kinds == [
        ("plain", (0,)),
        ("empty", ()),
        ("overlay", (0, 1)),
        ("plain", (1,)),
        ("empty", ()),
    ]
    assert [r.area for r in rmap.regions] == [12, 2, 4, 4, 2]
    assert sum(r.area_fraction for r in rmap.regions) == pytest.approx(1.0)
    overlay = rmap.regions[2]
    assert overlay.bbox == (1, 2, 3, 4)
    assert overlay.centroid == pytest.approx((1.5, 2.5))
    assert rmap.region_id.dtype == np.int32
    assert rmap.layer_set.dtype == np.uint32
    assert rmap.layer_set[1, 2] == 3
    assert rmap.layer_set[0, 5] == 0
    assert all(r.id == i for i, r in enumerate(rmap.regions))
    for r in rmap.regions:
        assert np.count_nonzero(rmap.region_id == r.id) == r.area


def test_subregions_same_set_split_into_components():
    fp = np.zeros((1, 3, 7), bool)
    fp[0, :, 0:2] = True
    fp[0, :, 5:7] = True
    rmap = subregions(fp)
    plain = [r for r in rmap.regions if r.kind == "plain"]
    assert len(plain) == 2
    assert {r.bbox for r in plain} == {(0, 0, 3, 2), (0, 5, 3, 7)}


def test_subregions_diagonal_is_one_component_8_connectivity():
    fp = np.eye(4, dtype=bool)[None]
    rmap = subregions(fp)
    assert [r.kind for r in rmap.regions].count("plain") == 1


def test_empty_input_gives_single_empty_region():
    rmap = subregions(np.zeros((0, 5, 3), bool))
    assert len(rmap.regions) == 1
    (r,) = rmap.regions
    assert (r.kind, r.layers, r.area, r.area_fraction) == ("empty", frozenset(), 15, 1.0)
    assert r.centroid == pytest.approx((2.0, 1.0))
    assert not np.any(rmap.region_id)
    assert layer_relations(np.zeros((0, 5, 3), bool)) == {}


def test_subregions_rejects_bad_footprints():
    with pytest.raises(DVRInputError, match="footprints"):
        subregions(np.zeros((2, 0, 3), bool))
    with pytest.raises(DVRInputError, match="footprints"):
        subregions(np.full((1, 2, 2), 0.5))
    with pytest.raises(DVRInputError, match="32 layers"):
        subregions(np.zeros((33, 2, 2), bool))


def test_relation_overlap_two_discs():
    shape = (21, 31)
    fp = np.stack([disc(shape, (10, 10), 6), disc(shape, (10, 18), 6)])
    rel = layer_relations(fp)[(0, 1)]
    assert rel.kind == "overlap"
    assert rel.encloser is None
    assert rel.intersection == np.count_nonzero(fp[0] & fp[1])


def test_relation_enclose_big_disc_encloses_small():
    shape = (25, 25)
    fp = np.stack([disc(shape, (12, 13), 3), disc(shape, (12, 12), 10)])
    rel = layer_relations(fp)[(0, 1)]
    assert rel.kind == "enclose"
    assert rel.encloser == 1
    assert rel.enclosed == 0


def test_relation_separate_disjoint_discs():
    shape = (15, 30)
    fp = np.stack([disc(shape, (7, 6), 4), disc(shape, (7, 22), 4)])
    rel = layer_relations(fp)[(0, 1)]
    assert rel.kind == "separate"
    assert rel.intersection == 0


def test_relation_touch_shared_edge_and_diagonal_gap():
    fp = np.zeros((3, 8, 10), bool)
    fp[0, 1:5, 0:4] = True
    fp[1, 1:5, 4:8] = True  # shares the edge col 3|4 with layer 0
    fp[2, 5:7, 8:10] = True  # only diagonally adjacent to layer 1's corner (4, 7)
    rels = layer_relations(fp)
    assert rels[(0, 1)].kind == "touch"
    assert rels[(1, 2)].kind == "touch"
    assert rels[(0, 2)].kind == "separate"


def test_relation_tolerance_decides_enclose_vs_overlap():
    fp = np.zeros((2, 10, 20), bool)
    fp[0, 0:10, 0:10] = True  # 100 px
    fp[1, 2:7, 1:11] = True  # 50 px, 5 px (10 %) stick out of layer 0
    assert layer_relations(fp)[(0, 1)].kind == "overlap"
    rel = layer_relations(fp, tolerance=0.1)[(0, 1)]
    assert (rel.kind, rel.encloser) == ("enclose", 0)


def test_relations_skip_empty_layers_and_validate_tolerance():
    fp = np.zeros((3, 4, 4), bool)
    fp[0, :2] = True
    fp[2, 2:] = True
    assert list(layer_relations(fp)) == [(0, 2)]
    with pytest.raises(DVRInputError, match="tolerance"):
        layer_relations(fp, tolerance=0.5)


def test_regions_512_six_layers_partition_the_image():
    shape = (512, 512)
    rng = np.random.default_rng(1)
    centers = rng.integers(100, 412, size=(6, 2))
    fp = np.stack(
        [disc(shape, c, r) for c, r in zip(centers, (60, 80, 100, 120, 140, 160), strict=True)]
    )
    rmap = subregions(fp)
    assert sum(r.area for r in rmap.regions) == fp.shape[1] * fp.shape[2]
    bits = (fp.astype(np.uint32) << np.arange(6, dtype=np.uint32)[:, None, None]).sum(0)
    assert np.array_equal(rmap.layer_set, bits)
    for region in rmap.regions:
        mask = rmap.region_id == region.id
        assert mask.sum() == region.area
        expected = sum(1 << k for k in region.layers)
        assert np.all(rmap.layer_set[mask] == expected)


def test_region_ids_follow_first_pixels_whatever_the_label_numbering():
    from dvr_perception.measures.regions import _raster_ordered

    raster = np.array([[1, 1, 2], [3, 2, 2]])
    shuffled = np.array([[3, 3, 1], [2, 1, 1]])  # same components, other numbering
    for labels in (raster, shuffled):
        region_id, first = _raster_ordered(labels)
        assert region_id.tolist() == [[0, 0, 1], [2, 1, 1]]
        assert first.tolist() == [0, 2, 3]


def _pixel_relations(fp, tol):
    """Brute-force reference: areas, overlaps and 8-neighbour adjacency pixel by pixel."""
    k, h, w = fp.shape
    out = {}
    for i in range(k):
        for j in range(i + 1, k):
            ai, aj = int(fp[i].sum()), int(fp[j].sum())
            if not ai or not aj:
                continue
            x = int((fp[i] & fp[j]).sum())
            adjacent = any(
                fp[i, r, c] and fp[j, rr, cc]
                for r in range(h)
                for c in range(w)
                for rr in range(max(r - 1, 0), min(r + 2, h))
                for cc in range(max(c - 1, 0), min(c + 2, w))
            )
            small = min(ai, aj)
            if not adjacent:
                kind = "separate"
            elif small - x <= tol * small:
                kind = "enclose"
            elif x <= tol * small:
                kind = "touch"
            else:
                kind = "overlap"
            out[(i, j)] = (kind, x)
    return out


@pytest.mark.parametrize("k", [2, 5, 18])
def test_relations_equal_a_pixel_by_pixel_reference(k):
    """Random blobs: the layer-set counting gives the brute-force areas, overlaps, adjacency."""
    rng = np.random.default_rng(k)
    fp = np.zeros((k, 14, 17), bool)
    for layer in range(k):
        r, c = rng.integers(0, 14), rng.integers(0, 17)
        fp[layer] = disc((14, 17), (r, c), rng.integers(1, 5))
    fp[-1] = False  # an empty layer is skipped
    got = {key: (rel.kind, rel.intersection) for key, rel in layer_relations(fp).items()}
    assert got == _pixel_relations(fp, 0.02)
    if k == 2:
        assert got == {}  # one layer left: no pair
    else:
        assert {kind for kind, _ in got.values()} >= {"separate", "overlap"}
