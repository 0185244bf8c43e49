"""``VolumeReader`` (the ParaView reader's library side) and filters fed images with a direction."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception._vtk import vtk_to_numpy
from dvr_perception.filters import StructuralLayers, VolumeReader
from dvr_perception.structures.io import spec_from_dict, spec_to_dict
from dvr_perception.volume import Volume, save_volume, to_vtk_image
from dvr_perception.volume.convert import image_direction
from dvr_perception.volume.orient import file_order

N = 12


def _object() -> np.ndarray:
    """``[z, y, x]`` values 0..N**3-1 shuffled (seeded): any re-ordering shows."""
    rng = np.random.default_rng(21)
    return rng.permutation(N**3).astype(np.int16).reshape(N, N, N)


def _read(path, **kw):
    r = VolumeReader()
    r.file_name = str(path)
    for k, v in kw.items():
        setattr(r, k, v)
    ok = r.Update()
    return r, ok, r.GetOutputDataObject(0)


def _values(image) -> np.ndarray:
    x0, x1, y0, y1, z0, z1 = image.GetExtent()
    arr = vtk_to_numpy(image.GetPointData().GetScalars())
    return arr.reshape(z1 - z0 + 1, y1 - y0 + 1, x1 - x0 + 1)


def test_reader_gives_a_negative_z_nrrd_in_canonical_order(tmp_path):
    data = _object()
    save_volume(Volume(data, spacing=(1, 1, 2), origin=(-5, -5, 0)), tmp_path / "c.nrrd")
    header = (
        "NRRD0004\ntype: int16\ndimension: 3\nsizes: 12 12 12\nspace: LPS\n"
        "space directions: (1,0,0) (0,1,0) (0,0,-2)\nspace origin: (-5,-5,22)\n"
        "endian: little\nencoding: raw\n\n"
    )
    raw = np.ascontiguousarray(data[::-1]).astype("<i2").tobytes()
    (tmp_path / "negz.nrrd").write_bytes(header.encode() + raw)
    _, ok_c, canon = _read(tmp_path / "c.nrrd")
    reader, ok_n, negz = _read(tmp_path / "negz.nrrd")
    assert ok_c
    assert ok_n, reader.error_message
    np.testing.assert_array_equal(_values(negz), data)
    np.testing.assert_array_equal(_values(canon), data)
    assert negz.GetOrigin() == canon.GetOrigin() == (-5.0, -5.0, 0.0)
    assert negz.GetSpacing() == (1.0, 1.0, 2.0)
    np.testing.assert_array_equal(image_direction(negz), np.eye(3))
    assert negz.GetPointData().GetScalars().GetName() == "scalars"


def test_reader_keeps_an_oblique_rotation_and_serves_pieces(tmp_path):
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    data = _object()
    save_volume(Volume(data, origin=(1, 2, 3), direction=rot), tmp_path / "o.nrrd")
    reader, ok, out = _read(tmp_path / "o.nrrd")
    assert ok, reader.error_message
    np.testing.assert_allclose(image_direction(out), rot, atol=1e-12)
    np.testing.assert_array_equal(_values(out), data)
    reader = VolumeReader()
    reader.file_name = str(tmp_path / "o.nrrd")
    reader.UpdateExtent((2, 5, 0, N - 1, 7, 9))  # a piece, as an MPI rank asks for it
    piece = reader.GetOutputDataObject(0)
    assert piece.GetExtent() == (2, 5, 0, N - 1, 7, 9)
    np.testing.assert_array_equal(_values(piece), data[7:10, :, 2:6])
    np.testing.assert_allclose(image_direction(piece), rot, atol=1e-12)


def test_reader_reports_one_error_naming_the_file(tmp_path):
    reader, ok, _ = _read(tmp_path / "missing.nrrd")
    assert not ok
    assert reader.error_message == f"{tmp_path / 'missing.nrrd'}: file not found"
    reader, ok, _ = _read("")
    assert not ok
    assert "FileName" in reader.error_message
    (tmp_path / "bad.nrrd").write_bytes(b"NRRD0004\ntype: int16\n\n")
    reader, ok, _ = _read(tmp_path / "bad.nrrd")
    assert not ok
    assert str(tmp_path / "bad.nrrd") in reader.error_message


@pytest.mark.parametrize(
    "flip", [np.diag([1.0, 1.0, -1.0]), np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]])]
)
def test_structural_layers_puts_its_arrays_on_the_voxels_of_a_directed_image(flip):
    """An image with a flipped/permuted direction gets the arrays in its own point order."""
    z, y, x = np.mgrid[0:16, 0:16, 0:16]
    data = np.zeros((16, 16, 16), np.uint8)
    data[(x - 6) ** 2 + (y - 8) ** 2 + (z - 10) ** 2 < 16] = 200  # ball: left, high
    data[2:5, 9:14, 3:13] = 100  # slab: low, at the back
    spec = spec_from_dict(
        {
            "version": 1,
            "structures": [
                {"name": "slab", "range": [80, 120], "importance": 0.5, "color": [0, 0, 1]},
                {"name": "ball", "range": [180, 220], "importance": 0.9, "color": [1, 0, 0]},
            ],
        },
        source="spec",
    )
    # the same voxels stored another way: file order, and the direction that says so
    image = to_vtk_image(Volume(file_order(data, flip)))
    image.SetDirectionMatrix(*flip.ravel())

    def layers(img):
        f = StructuralLayers()
        f.spec_json = json.dumps(spec_to_dict(spec))
        f.SetInputDataObject(img)
        assert f.Update(), f.error_message
        pd = f.GetOutputDataObject(0).GetPointData()
        return {k: vtk_to_numpy(pd.GetArray(k)).copy() for k in ("structure_id", "curvature")}

    plain, directed = layers(to_vtk_image(Volume(data))), layers(image)
    for key in ("structure_id", "curvature"):
        expect = file_order(plain[key].reshape(data.shape), flip).reshape(-1)
        np.testing.assert_array_equal(directed[key], expect, err_msg=key)
    assert not np.array_equal(directed["structure_id"], plain["structure_id"])
    assert set(np.unique(plain["structure_id"])) == {-1, 0, 1}


def test_reader_gives_native_values_of_a_big_endian_mgz(tmp_path):
    """nibabel hands MGH data over big-endian; VTK arrays must get native values."""
    import nibabel  # the medical extra, installed with dev

    data = np.arange(60, dtype=np.float32).reshape(3, 4, 5)  # nibabel order: [x, y, z]
    nibabel.save(nibabel.MGHImage(data, np.eye(4)), tmp_path / "t.mgz")
    reader, ok, out = _read(tmp_path / "t.mgz")
    assert ok, reader.error_message
    got = _values(out)
    assert got.dtype.isnative
    # RAS identity -> LPS: x and y flipped into canonical order
    np.testing.assert_array_equal(got, data.transpose(2, 1, 0)[:, ::-1, ::-1])
