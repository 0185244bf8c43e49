"""Tests for the VTK reference renderer (checks the conventions in docs/vtk_conventions.md)."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.vtk_reference import (
    compare_images,
    render_vtk,
    time_vtk_frames,
    vtk_clipping_range,
    vtk_frame_timer,
)
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume

pytestmark = pytest.mark.vtk_render
ORANGE = (1.0, 0.5, 0.25)
NAVY = (0.0, 0.0, 0.5)


def _opaque_spec(**rendering) -> StructureSpec:
    solid = Structure("solid", 1.0, ORANGE, range=(100, 300), edge=0.0)
    return StructureSpec((solid,), background=NAVY, rendering=RenderSettings(**rendering))


def _top_view(size=32) -> Camera:
    """Parallel view down -z onto a 16^3 volume; pixel size 0.5, image covers [-0.5, 15.5]."""
    return Camera(
        position=(7.5, 7.5, 60.0),
        focal_point=(7.5, 7.5, 7.5),
        parallel_projection=True,
        parallel_scale=8.0,
        width=size,
        height=size,
    )


def test_opaque_block_is_a_square_where_expected(vtk_can_render):
    data = np.zeros((16, 16, 16), np.uint8)
    data[:, 4:12, 4:12] = 200  # x and y in [4, 11]; value 100 is crossed at 3.5 and 11.5
    out = render_vtk(Volume(data), _opaque_spec(shade=False), _top_view())
    assert out.image.shape == (32, 32, 3)
    assert out.image.dtype == np.float32
    assert out.mapper == "fixed_point"
    bright = out.image[..., 0] > 0.5
    # pixel j has its centre at world -0.5 + (j + 0.5) * 0.5: columns/rows 8..23 are inside
    assert np.flatnonzero(bright[16]).tolist() == list(range(8, 24))
    assert np.flatnonzero(bright[:, 16]).tolist() == list(range(8, 24))
    np.testing.assert_allclose(out.image[16, 16], ORANGE, atol=2 / 255)
    np.testing.assert_allclose(out.image[2, 2], NAVY, atol=1 / 255)
    assert out.alpha[16, 16] == pytest.approx(1.0, abs=1 / 255)
    assert out.alpha[2, 2] == pytest.approx(0.0, abs=1 / 255)


def test_blob_at_plus_x_plus_y_shows_upper_right(vtk_can_render):
    data = np.zeros((20, 20, 30), np.uint8)  # z, y, x
    data[8:12, 14:18, 22:27] = 255
    vol = Volume(data)
    cam = Camera.from_view(vol.bounds, width=48, height=32)
    out = render_vtk(vol, _opaque_spec(shade=False), cam)
    assert out.image.shape == (32, 48, 3)
    rows, cols = np.nonzero(out.alpha > 0.5)
    assert rows.size > 0
    assert rows.max() < 16
    assert cols.min() > 24


def test_alpha_of_a_translucent_slab_counts_samples(vtk_can_render):
    # 11 slices -> box z in [0, 10]; near plane at z = 15.4 puts samples at 9.4, ..., 0.4: 10
    data = np.full((11, 16, 16), 150, np.uint8)
    data[0, 0, 0], data[-1, -1, -1] = 0, 250
    spec = StructureSpec(
        (Structure("s", 0.1, (1, 1, 1), range=(100, 200), edge=0.1),),
        rendering=RenderSettings(shade=False),
    )
    cam = Camera(
        position=(7.5, 7.5, 50.0),
        focal_point=(7.5, 7.5, 5.0),
        parallel_projection=True,
        parallel_scale=10.0,
        width=24,
        height=24,
    )
    out = render_vtk(Volume(data), spec, cam)
    assert out.clipping_range == pytest.approx((34.6, 58.2))
    assert out.alpha[12, 12] == pytest.approx(1 - 0.9**10, abs=2 / 255)
    assert out.alpha[0, 0] == pytest.approx(0.0, abs=1 / 255)  # outside the volume


def test_interpolated_index_is_rounded_up(vtk_can_render):
    # values 3*z; samples at z = 9.4, ..., 0.4 give 28.2, 25.2, ...: VTK looks up ceil -> 29
    z = np.arange(11, dtype=np.uint8)
    data = np.broadcast_to((3 * z)[:, None, None], (11, 16, 16)).copy()
    cam = Camera(
        position=(7.5, 7.5, 50.0),
        focal_point=(7.5, 7.5, 5.0),
        parallel_projection=True,
        parallel_scale=10.0,
        width=16,
        height=16,
    )
    hits = []
    for k in (28, 29):
        spec = StructureSpec(
            (Structure("k", 0.5, (1, 1, 1), range=(k - 1, k + 1), edge=0.5),),
            rendering=RenderSettings(shade=False),
        )
        hits.append(float(render_vtk(Volume(data), spec, cam).alpha[8, 8]))
    assert hits[0] == pytest.approx(0.0, abs=1 / 255)
    assert hits[1] == pytest.approx(0.5, abs=2 / 255)


def test_shading_headlight_with_white_ambient(vtk_can_render):
    data = np.zeros((16, 16, 16), np.uint8)
    data[4:12] = 200  # slab facing the camera: normal +z at z = 11 and 12, zero at z = 10
    vol = Volume(data)
    light = Lighting(ambient=0.3, diffuse=0.5, specular=0.1, specular_power=16)
    spec = StructureSpec(
        (Structure("s", 1.0, (1, 1, 1), range=(100, 300), edge=0.0, lighting=light),),
        rendering=RenderSettings(shade=True),
    )
    cam = _top_view(16)
    # samples are anchored at the near plane; the first one whose value exceeds 100 is opaque
    zs = (cam.position[2] - vtk_clipping_range(vol, cam)[0]) - np.arange(1, 40)
    z = zs[np.argmax(200 * np.clip(12 - zs, 0, 1) > 100)]
    w_zero = 11 - z if z < 11 else 0.0  # trilinear weight of the zero-normal corner (z = 10)
    # D = Ka + Kd * n.l, S = Ks * (n.h)^16 (white), both interpolated from the corners
    expected = 0.3 + (1 - w_zero) * (0.5 + 0.1)
    out = render_vtk(vol, spec, cam)
    np.testing.assert_allclose(out.image[8, 8], expected, atol=3 / 255)
    ambient_only = StructureSpec(
        (Structure("s", 1.0, (1, 1, 1), range=(100, 300), edge=0.0, lighting=Lighting(0.3, 0, 0)),),
    )
    np.testing.assert_allclose(render_vtk(vol, ambient_only, cam).image[8, 8], 0.3, atol=2 / 255)


def test_clipping_range_formula_matches_vtk(vtk_can_render):
    vol = Volume(np.full((8, 12, 10), 150, np.uint8), spacing=(1.0, 0.5, 2.0), origin=(3, -2, 1))
    spec = _opaque_spec(shade=False)
    for cam in (
        Camera.from_view(vol.bounds, azimuth=40, elevation=25, width=16, height=16),
        Camera.from_view(vol.bounds, azimuth=-70, elevation=5, zoom=1.5, width=16, height=12),
    ):
        got = render_vtk(vol, spec, cam).clipping_range
        assert vtk_clipping_range(vol, cam) == pytest.approx(got, rel=1e-9)


def test_fixed_point_and_gpu_agree_on_a_smooth_volume(vtk_can_render):
    g = np.linspace(-1, 1, 32)
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    data = (250 * np.exp(-3 * (xx**2 + 1.5 * yy**2 + zz**2))).astype(np.uint8)
    vol = Volume(data)
    spec = StructureSpec(
        (
            Structure("shell", 0.1, (0.9, 0.6, 0.3), range=(40, 120), edge=0.3),
            Structure("core", 0.8, (0.9, 0.9, 1.0), range=(150, 255), edge=0.2),
        ),
        rendering=RenderSettings(shade=False),
    )
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=64, height=64)
    fp = render_vtk(vol, spec, cam)
    gpu = render_vtk(vol, spec, cam, mapper="gpu")
    assert gpu.mapper == "gpu"
    assert gpu.image.shape == fp.image.shape
    cmp = compare_images(fp.image, gpu.image)
    print(f"fixed_point vs gpu: {cmp}")
    assert cmp["ssim"] > 0.9  # measured 0.99 with VTK 9.7 / llvmpipe
    assert cmp["mean_abs_diff"] < 0.02


def test_bad_inputs_raise_one_clear_error(vtk_can_render):
    vol = Volume(np.zeros((4, 4, 4), np.uint8))
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    with pytest.raises(DVRInputError, match="mapper"):
        render_vtk(vol, _opaque_spec(), cam, mapper="raycast")
    with pytest.raises(DVRInputError, match="Volume"):
        render_vtk(vol.data, _opaque_spec(), cam)
    with pytest.raises(DVRInputError, match="frames"):
        time_vtk_frames(vol, _opaque_spec(), cam, frames=0)
    with pytest.raises(DVRInputError, match="same shape"):
        compare_images(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)))


def test_time_vtk_frames_and_compare_images(vtk_can_render):
    vol = Volume(np.arange(16**3, dtype=np.uint16).reshape(16, 16, 16) % 300)
    spec = _opaque_spec(shade=True)
    seconds = time_vtk_frames(vol, spec, Camera.from_view(vol.bounds, width=32, height=32))
    assert 0 < seconds < 5
    a = np.zeros((16, 16, 3))
    b = a.copy()
    b[:8] = 0.5
    cmp = compare_images(a, b)
    assert cmp["mean_abs_diff"] == pytest.approx(0.25)
    assert cmp["ssim"] < 0.9
    assert compare_images(b, b)["ssim"] == pytest.approx(1.0)


def test_vtk_frame_timer_renders_frame_after_frame(vtk_can_render):
    vol = Volume(np.arange(16**3, dtype=np.uint16).reshape(16, 16, 16) % 300)
    cam = Camera.from_view(vol.bounds, width=32, height=32)
    with vtk_frame_timer(vol, _opaque_spec(), cam) as frame:
        times = [frame() for _ in range(3)]
    assert all(0 < t < 5 for t in times)
