"""The generated head phantom: determinism, ranges, nesting and the four footprint relations."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from scipy import ndimage

from dvr_perception.errors import DVRInputError
from dvr_perception.structures import make_phantom
from dvr_perception.structures.spec import Lighting, StructureSpec


@pytest.fixture(scope="module")
def phantom():
    return make_phantom()


def _footprint(vol, spec, name):
    """Projection along z (the default view direction) of the structure's ground-truth mask."""
    return (vol.labels == spec.names.index(name) + 1).any(axis=0)


def _relation(a, b):
    if not (a & ~b).any() or not (b & ~a).any():
        return "enclose"
    if (a & b).any():
        return "overlap"
    if (ndimage.binary_dilation(a) & b).any():  # 4-neighbour dilation by one pixel
        return "touch"
    return "separate"


def test_basic_properties(phantom):
    vol, spec = phantom
    assert vol.data.shape == (128, 128, 128)
    assert vol.data.dtype == np.uint8
    assert vol.spacing == (1.0, 1.0, 1.0)
    assert vol.name == "phantom"
    assert isinstance(spec, StructureSpec)
    assert 4 <= len(spec.structures) <= 6
    assert spec.names[0] == "skin"
    assert spec.background == (0.0, 0.0, 0.0)
    assert all(s.lighting == Lighting() for s in spec.structures)
    assert len({s.colour for s in spec.structures}) == len(spec.structures)
    imp = [s.importance for s in spec.structures]
    assert imp == sorted(imp)
    assert imp[0] == min(imp)
    assert set(np.unique(vol.labels)) == set(range(len(spec.structures) + 1))


def test_ranges_are_disjoint_and_hold_their_material(phantom):
    vol, spec = phantom
    ranges = [s.range for s in spec.structures]
    for (_, hi), (lo, _) in itertools.pairwise(ranges):
        assert hi <= lo
    for i, s in enumerate(spec.structures):
        lo, hi = s.range
        in_range = (vol.data >= lo) & (vol.data <= hi)
        assert in_range.sum() > 50, s.name
        core = ndimage.binary_erosion(vol.labels == i + 1, iterations=2)
        assert core.any(), s.name
        assert in_range[core].mean() > 0.98, s.name  # away from boundaries: inside its range
    # background air is below every structure
    air = ndimage.binary_erosion(vol.labels == 0, iterations=2)
    assert vol.data[air].max() < ranges[0][0]


def test_shells_enclose_the_inner_objects(phantom):
    vol, spec = phantom
    lab = vol.labels
    filled = {n: ndimage.binary_fill_holes(lab == i + 1) for i, n in enumerate(spec.names)}
    inner = lab >= 3
    assert not filled["skin"][lab == 0].all()
    assert filled["skin"][lab >= 2].all()
    assert filled["skull"][inner].all()
    # the shells are closed: skull voxels separate the brain from the outside
    # flood from the corner through air and skin never reaches the brain or what is inside it
    reach = ndimage.binary_propagation(lab == 0, mask=(lab <= 1))
    assert reach[0, 0, 0]
    assert not (reach & ndimage.binary_dilation(lab >= 3)).any()
    for name in ("tumour", "ventricle", "calcification"):
        obj = lab == spec.names.index(name) + 1
        ring = ndimage.binary_dilation(obj, iterations=2) & ~obj
        assert set(np.unique(lab[ring])) == {3}, name  # embedded in brain only


@pytest.mark.parametrize("size", [48, 64, 128])
def test_footprint_relations_in_default_view(size):
    vol, spec = make_phantom(size=size) if size != 128 else make_phantom()
    fp = {n: _footprint(vol, spec, n) for n in spec.names}
    for other in spec.names[1:]:
        assert _relation(fp["skin"], fp[other]) == "enclose"
    assert _relation(fp["ventricle"], fp["tumour"]) == "overlap"
    assert _relation(fp["tumour"], fp["calcification"]) == "touch"
    assert _relation(fp["ventricle"], fp["calcification"]) == "separate"
    # overlap in projection only: ventricle and tumour do not touch in 3-D
    lab = vol.labels
    vent = lab == spec.names.index("ventricle") + 1
    tum = lab == spec.names.index("tumour") + 1
    assert not (ndimage.binary_dilation(vent, iterations=3) & tum).any()


def test_relation_helper_on_hand_checked_masks():
    a = np.zeros((5, 6), bool)
    b = np.zeros((5, 6), bool)
    a[1:3, 1:3] = True
    b[1:3, 3:5] = True
    assert _relation(a, b) == "touch"
    b[:] = False
    b[1:3, 4:6] = True
    assert _relation(a, b) == "separate"
    b[1:3, 2:4] = True
    assert _relation(a, b) == "overlap"
    b[:] = True
    assert _relation(a, b) == "enclose"


def test_deterministic_and_seeds_differ_only_in_noise():
    v0a, s0 = make_phantom(size=48, seed=0)
    v0b, _ = make_phantom(size=48, seed=0)
    v1, s1 = make_phantom(size=48, seed=1)
    clean, _ = make_phantom(size=48, noise=0.0)
    np.testing.assert_array_equal(v0a.data, v0b.data)
    assert s0 == s1
    np.testing.assert_array_equal(v0a.labels, v1.labels)
    assert not np.array_equal(v0a.data, v1.data)
    diff = v0a.data.astype(int) - clean.data.astype(int)
    head = clean.data > 10  # away from the clipped air
    assert abs(diff[head].mean()) < 0.2
    assert 4.0 < diff[head].std() < 6.2  # 0.02 * 255 = 5.1
    assert np.abs(diff).max() <= 6 * 5.1


def test_speed_at_default_size():
    make_phantom(size=32)
    t0 = time.perf_counter()
    vol, _ = make_phantom()
    assert time.perf_counter() - t0 < 2.0
    assert vol.data.shape == (128, 128, 128)


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"size": 8}, "size must be an integer in"),
        ({"size": 64.0}, "size must be an integer in"),
        ({"size": True}, "size must be an integer in"),
        ({"seed": -1}, "seed must be a non-negative integer"),
        ({"noise": -0.1}, "noise must be a number in"),
        ({"noise": float("nan")}, "noise must be a number in"),
        ({"noise": "x"}, "noise must be a number in"),
    ],
)
def test_bad_parameters(kwargs, pattern):
    with pytest.raises(DVRInputError, match=pattern):
        make_phantom(**kwargs)


def test_the_voxels_alone_come_from_volume_and_equal_make_phantoms():
    from dvr_perception.volume import phantom_volume
    from dvr_perception.volume.phantom import PHANTOM_MATERIALS

    vol = phantom_volume(size=24, seed=3)
    ref, spec = make_phantom(size=24, seed=3)
    np.testing.assert_array_equal(vol.data, ref.data)
    np.testing.assert_array_equal(vol.labels, ref.labels)
    assert spec.names == tuple(m[0] for m in PHANTOM_MATERIALS)


@pytest.mark.parametrize("where", ["dvr_perception.volume", "dvr_perception.volume.phantom"])
def test_the_old_make_phantom_paths_warn_and_still_work(where):
    import importlib

    module = importlib.import_module(where)
    with pytest.warns(DeprecationWarning, match=r"dvr_perception\.make_phantom"):
        old = module.make_phantom
    assert old is make_phantom
    vol, spec = old(size=16)
    assert vol.dims == (16, 16, 16)
    assert len(spec.structures) == 6
