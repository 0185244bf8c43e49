"""Mean curvature: known answers for planes, spheres, cylinders; boundary extraction."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.curvature import classify_structures, curvature_volume, mean_curvature
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.volume import Volume


def _grid(n, nz=None, dz=1.0):
    nz = n if nz is None else nz
    z, y, x = np.mgrid[:nz, :n, :n].astype(np.float64)
    return z * dz - (nz - 1) * dz / 2, y - (n - 1) / 2, x - (n - 1) / 2


def _soft(d, width=1.5):
    """Smooth 0..1 profile, 1 inside (d < 0); its iso-surfaces are the level sets of d."""
    return 1.0 / (1.0 + np.exp(d / width))


def test_constant_is_zero():
    h = mean_curvature(np.full((8, 9, 10), 7, np.uint16))
    assert h.dtype == np.float32
    assert h.shape == (8, 9, 10)
    assert np.all(h == 0)


def test_linear_ramp_is_flat():
    z, y, x = _grid(20)
    h = mean_curvature(3 * x + 2 * y - z + 100)
    assert np.all(np.isfinite(h))
    # away from the grid border (edge values are replicated there) the planes stay flat
    assert float(h[5:-5, 5:-5, 5:-5].max()) < 1e-3


@pytest.mark.parametrize("radius", [10, 15, 20])
def test_sphere_is_one_over_r(radius):
    z, y, x = _grid(2 * radius + 12)
    r = np.sqrt(x**2 + y**2 + z**2)
    h = mean_curvature(_soft(r - radius))
    near = np.abs(r - radius) <= 1.0
    assert near.sum() > 100
    np.testing.assert_allclose(h[near], 1.0 / radius, rtol=0.1)
    # per voxel the iso-surface through it has radius r: much tighter than 10 %
    np.testing.assert_allclose(h[near] * r[near], 1.0, rtol=0.01)


def test_blurred_binary_ball():
    from scipy import ndimage

    radius = 12
    z, y, x = _grid(2 * radius + 12)
    r = np.sqrt(x**2 + y**2 + z**2)
    ball = ndimage.gaussian_filter((r <= radius).astype(np.float32), 2.0)
    h = mean_curvature(ball)
    near = np.abs(r - radius) <= 1.0
    assert abs(float(np.median(h[near])) * radius - 1) < 0.05


@pytest.mark.parametrize("radius", [10, 15])
def test_cylinder_is_one_over_2r(radius):
    _z, y, x = _grid(2 * radius + 12, nz=12)
    rho = np.sqrt(x**2 + y**2)
    h = mean_curvature(_soft(rho - radius))
    near = np.abs(rho - radius) <= 1.0
    np.testing.assert_allclose(h[near], 1.0 / (2 * radius), rtol=0.1)


def test_sign_does_not_matter():
    z, y, x = _grid(30)
    r = np.sqrt(x**2 + y**2 + z**2)
    f = _soft(r - 10)
    np.testing.assert_allclose(mean_curvature(f), mean_curvature(-f), atol=1e-6)


def test_anisotropic_spacing_in_world_units():
    radius = 12
    n = 2 * radius + 12
    z, y, x = _grid(n, nz=n // 2, dz=2.0)  # z voxels twice as long
    r = np.sqrt(x**2 + y**2 + z**2)
    h = mean_curvature(_soft(r - radius), spacing=(1, 1, 2))
    near = np.abs(r - radius) <= 0.5
    np.testing.assert_allclose(h[near], 1.0 / radius, rtol=0.1)
    np.testing.assert_allclose(h[near] * r[near], 1.0, rtol=0.07)
    # ignoring the spacing would be badly wrong
    wrong = mean_curvature(_soft(r - radius))
    assert float(np.max(np.abs(wrong[near] * radius - 1))) > 0.2


def test_scales_with_world_units():
    z, y, x = _grid(36)
    r = np.sqrt(x**2 + y**2 + z**2)
    f = _soft(r - 12)
    near = np.abs(r - 12) <= 1.0
    h = mean_curvature(f, spacing=(0.5, 0.5, 0.5))  # sphere of radius 6 world units
    np.testing.assert_allclose(h[near], 1.0 / 6, rtol=0.1)


def test_never_nan_on_noise_and_flat_regions():
    rng = np.random.default_rng(1)
    f = np.zeros((20, 20, 20), np.float32)
    f[5:15, 5:15, 5:15] = rng.random((10, 10, 10))
    h = mean_curvature(f)
    assert np.all(np.isfinite(h))
    assert np.all(h[0] == 0)  # far from the noise the field is exactly flat


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"spacing": (1, 0, 1)}, "spacing must be three positive numbers"),
        ({"spacing": (1, 1)}, "spacing must be three positive numbers"),
        ({"sigma": 0}, "sigma must be a positive number"),
        ({"sigma": float("nan")}, "sigma must be a positive number"),
    ],
)
def test_bad_parameters(kwargs, message):
    with pytest.raises(DVRInputError, match=message):
        mean_curvature(np.zeros((4, 4, 4)), **kwargs)


def test_bad_data():
    with pytest.raises(DVRInputError, match="3-D array"):
        mean_curvature(np.zeros((4, 4)))
    with pytest.raises(DVRInputError, match="NaN or infinite"):
        mean_curvature(np.full((3, 3, 3), np.nan))


def _spec(*ranges):
    return StructureSpec(
        tuple(Structure(f"s{i}", 0.5, (1.0, 1.0, 1.0), range=r) for i, r in enumerate(ranges))
    )


def test_classify_touching_ranges():
    data = np.array([0, 10, 15, 20, 25, 30, 31, 40], np.uint8).reshape(2, 2, 2)
    ids = classify_structures(Volume(data), _spec((20, 30), (10, 20)))
    # 10,15 -> s1; 20 (shared edge) -> upper s0; 30 (top of last range) -> s0; 31, 40 -> none
    assert ids.ravel().tolist() == [-1, 1, 1, 0, 0, 0, -1, -1]


def test_classify_labels_take_precedence():
    data = np.full((2, 2, 2), 25, np.uint8)
    labels = np.zeros((2, 2, 2), np.uint8)
    labels[0, 0, 0] = 4
    spec = StructureSpec(
        (
            Structure("r", 0.5, (1.0, 1.0, 1.0), range=(20, 30)),
            Structure("l", 0.5, (1.0, 1.0, 1.0), label=4),
        ),
        labels_file="x",
    )
    ids = classify_structures(Volume(data, labels=labels), spec)
    assert ids[0, 0, 0] == 1
    assert np.count_nonzero(ids == 0) == 7
    with pytest.raises(DVRInputError, match="no label volume"):
        classify_structures(Volume(data), spec)


def test_curvature_volume_on_a_ball():
    radius = 10
    z, y, x = _grid(2 * radius + 10)
    r = np.sqrt(x**2 + y**2 + z**2)
    data = (200 * _soft(r - radius)).astype(np.float32)
    vol = Volume(data)
    curv, boundary = curvature_volume(vol, _spec((100, 255)))
    assert curv.dtype == np.float32
    assert boundary.dtype == bool
    # the boundary is the one-voxel shell on both sides of the 100 iso-surface
    assert np.all(np.abs(r[boundary] - radius) < 1.8)
    assert np.all(curv[~boundary] == 0)
    np.testing.assert_allclose(curv[boundary], 1.0 / radius, rtol=0.2)


def test_curvature_volume_labels_use_indicator():
    radius = 8
    z, y, x = _grid(2 * radius + 10)
    r = np.sqrt(x**2 + y**2 + z**2)
    labels = (r <= radius).astype(np.uint8) * 2
    vol = Volume(np.zeros(labels.shape, np.uint8), labels=labels)
    spec = StructureSpec((Structure("ball", 1.0, (1.0, 0.0, 0.0), label=2),), labels_file="l")
    curv, boundary = curvature_volume(vol, spec, sigma=2.0)
    assert boundary.sum() > 0
    assert abs(float(np.median(curv[boundary])) * radius - 1) < 0.15


def test_curvature_volume_no_boundary():
    vol = Volume(np.full((4, 4, 4), 50, np.uint8))
    curv, boundary = curvature_volume(vol, _spec((0, 100)))
    assert not boundary.any()
    assert not curv.any()
