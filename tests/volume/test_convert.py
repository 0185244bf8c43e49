"""VTK <-> numpy conversion: layout, zero copy, array selection and its errors."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from dvr_perception._vtk import numpy_to_vtk, vtk_to_numpy, vtkImageData, vtkNrrdReader
from dvr_perception.errors import DVRInputError
from dvr_perception.volume import Volume, from_vtk_image, to_vtk_image
from dvr_perception.volume.convert import vtk_errors


def _image(values, dims=(2, 3, 4), name="a"):
    image = vtkImageData()
    image.SetDimensions(*dims)
    arr = numpy_to_vtk(np.asarray(values), deep=True)
    arr.SetName(name)
    image.GetPointData().AddArray(arr)
    return image


def test_to_vtk_layout_and_zero_copy():
    data = np.arange(24, dtype=np.uint16).reshape(2, 3, 4)  # z=2, y=3, x=4
    vol = Volume(data, spacing=(0.5, 1.0, 2.0), origin=(1.0, 2.0, 3.0))
    image = to_vtk_image(vol, name="density")
    assert image.GetDimensions() == (4, 3, 2)
    assert image.GetSpacing() == (0.5, 1.0, 2.0)
    assert image.GetOrigin() == (1.0, 2.0, 3.0)
    scalars = image.GetPointData().GetScalars()
    assert scalars.GetName() == "density"
    # point id = x + 4*(y + 3*z): voxel [z=1, y=2, x=3] is point 23
    assert scalars.GetTuple1(image.ComputePointId([3, 2, 1])) == data[1, 2, 3] == 23
    assert np.shares_memory(vtk_to_numpy(scalars), vol.data)


def test_to_vtk_keeps_buffer_alive():
    image = to_vtk_image(Volume(np.full((3, 3, 3), 7, np.int32)))
    gc.collect()
    assert vtk_to_numpy(image.GetPointData().GetScalars()).tolist() == [7] * 27


def test_round_trip_copies():
    vol = Volume(np.arange(60, dtype=np.float32).reshape(3, 4, 5), origin=(-1.0, 0.0, 2.5))
    image = to_vtk_image(vol)
    back = from_vtk_image(image, name="b", source="mem")
    np.testing.assert_array_equal(back.data, vol.data)
    assert not np.shares_memory(back.data, vol.data)
    assert (back.name, back.source, back.origin) == ("b", "mem", (-1.0, 0.0, 2.5))


def test_extent_shifts_origin():
    image = vtkImageData()
    image.SetExtent(2, 3, 0, 1, 5, 6)
    image.SetSpacing(2.0, 1.0, 0.5)
    image.GetPointData().SetScalars(numpy_to_vtk(np.arange(8, dtype=np.uint8), deep=True))
    vol = from_vtk_image(image)
    assert vol.origin == (4.0, 0.0, 2.5)
    assert vol.data[1, 1, 1] == 7


def test_array_selection():
    image = _image(np.arange(24, dtype=np.int16), name="first")
    image.GetPointData().AddArray(numpy_to_vtk(np.ones(24, np.float64), deep=True))
    image.GetPointData().GetArray(1).SetName("second")
    with pytest.raises(DVRInputError, match="no point scalars among 2 point arrays"):
        from_vtk_image(image)
    assert from_vtk_image(image, array="second").data.dtype == np.float64
    with pytest.raises(DVRInputError, match=r"no point array named 'third'.*'first', 'second'"):
        from_vtk_image(image, array="third")
    only = _image(np.arange(24, dtype=np.int16), name="only")  # single array, not active
    assert from_vtk_image(only).data[3, 2, 1] == 23  # dims (x, y, z) = (2, 3, 4)


def test_errors():
    with pytest.raises(DVRInputError, match="3 components"):
        from_vtk_image(_image(np.zeros((24, 3), np.uint8), name="rgb"), array="rgb")
    cells = vtkImageData()
    cells.SetDimensions(3, 3, 3)
    cells.GetCellData().SetScalars(numpy_to_vtk(np.zeros(8, np.float32), deep=True))
    with pytest.raises(DVRInputError, match="only cell data"):
        from_vtk_image(cells, source="cells.vti")
    with pytest.raises(DVRInputError, match="expected vtkImageData"):
        from_vtk_image(np.zeros((3, 3, 3)))
    with pytest.raises(DVRInputError, match="must be a Volume"):
        to_vtk_image(np.zeros((3, 3, 3)))
    nan = _image(np.array([np.nan] + [0.0] * 23))
    with pytest.raises(DVRInputError, match=r"^mem.vti: .*NaN or infinite"):
        from_vtk_image(nan, source="mem.vti")


def test_direction_matrix_is_honoured():
    """A swap of x and y plus a flipped z: every point keeps its world position."""
    values = np.arange(24, dtype=np.uint8)
    image = _image(values)  # dims x=2, y=3, z=4
    image.GetPointData().SetActiveScalars("a")
    image.SetSpacing(1.0, 2.0, 3.0)
    image.SetOrigin(10.0, 20.0, 30.0)
    image.SetDirectionMatrix(0, 1, 0, 1, 0, 0, 0, 0, -1)
    vol = from_vtk_image(image)
    assert not vol.oblique
    assert vol.dims == (3, 2, 4)
    assert vol.spacing == (2.0, 1.0, 3.0)
    for pid in (0, 5, 17, 23):
        world = image.GetPoint(pid)  # VTK applies the direction matrix
        idx = np.round((np.subtract(world, vol.origin)) / vol.spacing).astype(int)
        assert np.allclose(vol.origin + idx * np.asarray(vol.spacing), world)
        assert vol.data[idx[2], idx[1], idx[0]] == values[pid]
    # back to VTK with the direction: the same world points
    again = to_vtk_image(vol, with_direction=True)
    assert again.GetDimensions() == (3, 2, 4)


def test_vtk_errors_context(tmp_path):
    reader = vtkNrrdReader()
    reader.SetFileName(str(tmp_path / "x.nhdr"))
    with (
        pytest.raises(DVRInputError, match=r"^.*x\.nhdr: VTK could not process") as info,
        vtk_errors(reader, str(tmp_path / "x.nhdr")),
    ):
        reader.Update()
    assert "0x" not in str(info.value)
    with vtk_errors(reader, "fine") as messages:
        pass
    assert messages == []
