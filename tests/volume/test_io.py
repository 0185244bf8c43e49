"""Round trips through every writable format, the readers' error messages, the shared data."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from dvr_perception._vtk import (
    numpy_to_vtk,
    vtkImageData,
    vtkXMLImageDataWriter,
)
from dvr_perception.errors import DVRInputError
from dvr_perception.volume import Volume, load_volume, save_volume

WRITABLE = [".vti", ".nhdr", ".nrrd", ".mha", ".mhd", ".nii", ".nii.gz", ".vtk"]
SPACING = (0.5, 1.5, 2.25)
ORIGIN = (-3.0, 4.5, 10.0)


def _random(dtype, seed=0) -> Volume:
    rng = np.random.default_rng(seed)
    data = (rng.random((7, 6, 5)) * 200 - (50 if np.dtype(dtype).kind != "u" else 0)).astype(dtype)
    return Volume(data, spacing=SPACING, origin=ORIGIN, name="orig")


@pytest.mark.parametrize("ext", WRITABLE)
@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.float32])
def test_round_trip_is_exact(tmp_path, ext, dtype):
    vol = _random(dtype)
    path = tmp_path / f"vol{ext}"
    save_volume(vol, path)
    back = load_volume(path)
    assert back.data.dtype == vol.data.dtype
    assert back.data.shape == (7, 6, 5)
    np.testing.assert_array_equal(back.data, vol.data)
    assert back.spacing == SPACING
    assert back.origin == ORIGIN
    assert back.name == "vol"
    assert back.source == str(path)


@pytest.mark.parametrize("dtype", ["int8", "uint16", "uint32", "int32", "float64"])
def test_nhdr_round_trip_other_dtypes_and_raw_beside(tmp_path, dtype):
    vol = _random(dtype)
    save_volume(vol, tmp_path / "v.nhdr")
    raw = tmp_path / f"v_5x6x7_{dtype}.raw"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["v.nhdr", raw.name])
    np.testing.assert_array_equal(load_volume(tmp_path / "v.nhdr").data, vol.data)
    headerless = load_volume(raw)  # the data file is itself a valid NAME_XxYxZ_DTYPE.raw
    np.testing.assert_array_equal(headerless.data, vol.data)
    assert headerless.name == "v"
    assert headerless.spacing == (1.0, 1.0, 1.0)


def test_save_replaces_existing_file_and_leaves_no_temporaries(tmp_path):
    path = tmp_path / "a.vti"
    save_volume(_random(np.uint8, seed=1), path)
    save_volume(_random(np.uint8, seed=2), path)
    np.testing.assert_array_equal(load_volume(path).data, _random(np.uint8, seed=2).data)
    assert [p.name for p in tmp_path.iterdir()] == ["a.vti"]


def test_save_errors(tmp_path):
    vol = _random(np.uint8)
    with pytest.raises(DVRInputError, match=r"cannot write format '\.png'"):
        save_volume(vol, tmp_path / "a.png")
    with pytest.raises(DVRInputError, match="does not exist"):
        save_volume(vol, tmp_path / "missing" / "a.vti")
    with pytest.raises(DVRInputError, match="must be a Volume"):
        save_volume(np.zeros((3, 3, 3)), tmp_path / "a.vti")
    assert list(tmp_path.iterdir()) == []


def test_name_override_and_stems(tmp_path):
    save_volume(_random(np.uint8), tmp_path / "head.nii.gz")
    assert load_volume(tmp_path / "head.nii.gz").name == "head"
    assert load_volume(tmp_path / "head.nii.gz", name="x").name == "x"


def test_dicom_series(tmp_path, dicom_writer):
    data = (np.arange(3 * 4 * 5, dtype=np.uint16) * 7).reshape(3, 4, 5)
    dicom_writer(tmp_path / "series", data, spacing=(0.5, 0.75, 2.0))
    vol = load_volume(tmp_path / "series")
    assert vol.dims == (5, 4, 3)
    assert vol.spacing == (0.5, 0.75, 2.0)
    assert vol.name == "series"
    # patient LPS: rows top-down (+y posterior), slices by ascending z, origin the first IPP
    np.testing.assert_array_equal(vol.data, data)
    assert vol.origin == (0.0, 0.0, 10.0)


def test_dicom_series_vtk_fallback(tmp_path, dicom_writer, monkeypatch):
    """Without the medical extra a folder is read by VTK (with a warning naming the extra)."""
    from dvr_perception.errors import DVRWarning
    from dvr_perception.volume import medical

    data = (np.arange(3 * 4 * 5, dtype=np.uint16) * 7).reshape(3, 4, 5)
    dicom_writer(tmp_path / "series", data, spacing=(0.5, 0.75, 2.0))
    monkeypatch.setattr(medical, "available", lambda module="pydicom": False)
    with pytest.warns(DVRWarning, match=r"dvr-perception\[medical\]"):
        vol = load_volume(tmp_path / "series")
    # VTK/ParaView convention: rows bottom-up, slices in descending position
    np.testing.assert_array_equal(vol.data, data[::-1, ::-1])
    with pytest.raises(DVRInputError, match=r"dvr-perception\[medical\]"):
        load_volume(tmp_path / "series" / "slice000.dcm")
    # the files' bytes bound what VTK reads: over the memory limit it never starts
    from dvr_perception import _memory

    monkeypatch.setattr(_memory, "limit", lambda value=None: 1024)  # bytes
    from dvr_perception import _vtk as vtk_module

    monkeypatch.setattr(vtk_module, "vtkDICOMImageReader", None)  # fails if VTK is asked
    with pytest.warns(DVRWarning), pytest.raises(DVRInputError, match="memory limit") as info:
        load_volume(tmp_path / "series")
    assert str(tmp_path / "series") in str(info.value)


def test_empty_dicom_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DVRInputError, match="no files"):
        load_volume(tmp_path / "empty")


# --- errors -------------------------------------------------------------------------------


def _raises(path, pattern):
    with pytest.raises(DVRInputError, match=pattern) as info:
        load_volume(path)
    assert str(path) in str(info.value)
    return str(info.value)


def test_missing_and_unknown(tmp_path):
    _raises(tmp_path / "nope.nhdr", "file not found")
    (tmp_path / "a.xyz").write_bytes(b"1234")
    _raises(tmp_path / "a.xyz", r"unknown volume format '\.xyz'")


def test_raw_errors(tmp_path):
    p = tmp_path / "t_4x4x4_uint16.raw"
    p.write_bytes(b"\0" * 100)
    _raises(p, "truncated: expected 128 bytes, found 100")
    p = tmp_path / "t_4x4x3_uint8.raw"
    p.write_bytes(b"\0" * 64)
    _raises(p, r"size mismatch: dims \(4, 4, 3\) need 48 bytes, found 64")
    p = tmp_path / "t_4x4x4_bool.raw"
    p.write_bytes(b"\0" * 64)
    _raises(p, "unsupported raw dtype 'bool'")
    p = tmp_path / "t_2x2x2_complex64.raw"
    p.write_bytes(b"\0" * 64)
    _raises(p, "unsupported raw dtype 'complex64'")
    p = tmp_path / "noname.raw"
    p.write_bytes(b"\0" * 8)
    _raises(p, "NAME_XxYxZ_DTYPE.raw")
    p = tmp_path / "t_0x4x4_uint8.raw"
    p.write_bytes(b"")
    _raises(p, "empty")


def test_nonfinite_voxels_name_the_file(tmp_path):
    data = np.ones((3, 3, 3), "<f4")
    data[1, 1, 1] = np.nan
    data[0, 0, 0] = np.inf
    p = tmp_path / "f_3x3x3_float32.raw"
    data.tofile(p)
    msg = _raises(p, r"2 voxel\(s\) are NaN or infinite")
    assert "'f'" in msg


def _nhdr(tmp_path, body, nbytes):
    (tmp_path / "d.raw").write_bytes(b"\1" * nbytes)
    p = tmp_path / "h.nhdr"
    p.write_text("NRRD0004\n" + body + "encoding: raw\ndata file: d.raw\n")
    return p


def test_nhdr_errors(tmp_path):
    p = _nhdr(tmp_path, "type: uchar\ndimension: 3\nsizes: 4 5 6\n", 100)
    _raises(p, "truncated: expected 120 bytes, found 100")
    p = _nhdr(tmp_path, "type: block\ndimension: 3\nsizes: 4 5 6\n", 120)
    _raises(p, "unsupported type 'block'")
    p = _nhdr(tmp_path, "type: uchar\ndimension: 2\nsizes: 4 5\n", 20)
    _raises(p, "'dimension': expected 3")
    p = _nhdr(tmp_path, "type: uchar\ndimension: 3\nsizes: 4 x 6\n", 20)
    _raises(p, "'sizes': expected 3 integers")
    p = _nhdr(tmp_path, "type: uchar\ndimension: 3\nsizes: 4 0 6\n", 0)
    _raises(p, "empty")
    p = _nhdr(tmp_path, "dimension: 3\nsizes: 4 5 6\n", 120)
    _raises(p, "no 'type' field")
    p = tmp_path / "bad.nhdr"
    p.write_text("hello\n")
    _raises(p, "not a NRRD file")


def test_nhdr_defaults_and_small_first_axis(tmp_path):
    # vtkNrrdReader would read an x size < 10 as vector components; we must not
    values = np.arange(4 * 5 * 6, dtype="<u2")
    (tmp_path / "d.raw").write_bytes(values.tobytes())
    p = tmp_path / "h.nhdr"
    p.write_text(
        "NRRD0004\n# c\ntype: unsigned short\ndimension: 3\nsizes: 4 5 6\n"
        "spacings: 2 1 3\nendian: little\nencoding: raw\ndata file: d.raw\n"
    )
    vol = load_volume(p)
    assert vol.dims == (4, 5, 6)
    assert vol.spacing == (2.0, 1.0, 3.0)
    assert vol.origin == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(vol.data.ravel(), values)


def test_vtk_polydata_is_rejected(tmp_path):
    p = tmp_path / "poly.vtk"
    p.write_text(
        "# vtk DataFile Version 3.0\ntri\nASCII\nDATASET POLYDATA\n"
        "POINTS 3 float\n0 0 0 1 0 0 0 1 0\nPOLYGONS 1 4\n3 0 1 2\n"
    )
    _raises(p, "field 'DATASET': holds 'POLYDATA'; expected STRUCTURED_POINTS")


def test_corrupt_vti_is_one_error(tmp_path):
    p = tmp_path / "c.vti"
    p.write_text("<VTKFile type='ImageData'> garbage")
    msg = _raises(p, "malformed VTK XML")
    assert "\n" not in msg


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN"])
def test_nrrd_nonfinite_spacings_are_refused(tmp_path, value):
    (tmp_path / "d.raw").write_bytes(bytes(8))
    p = tmp_path / "h.nhdr"
    p.write_text(
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\n"
        f"spacings: 1 {value} 1\nencoding: raw\ndata file: d.raw\n"
    )
    _raises(p, "field 'spacings': expected finite numbers")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            '<ImageData WholeExtent="0 99999 0 99999 0 99999" Spacing="1 1 1">'
            '<Piece><PointData><DataArray type="UInt8"/>',
            "field 'WholeExtent': sizes 100000",
        ),
        ('<ImageData WholeExtent="0 9 0 9 0 ' + "9" * 5000 + '">', "is too long"),
        ('<ImageData WholeExtent="0 9 0 9">', "field 'WholeExtent': expected 6 integers"),
        ('<ImageData WholeExtent="0 9 0 9 5 1">', "empty extent"),
        ('<ImageData WholeExtent="0 9 0 9 0 9" Spacing="1 nan 1">', "'Spacing'"),
        ('<ImageData WholeExtent="0 9 0 9 0 9"><DataArray type="Complex">', "unsupported type"),
    ],
)
def test_vti_headers_are_checked_before_reading(tmp_path, text, expected):
    p = tmp_path / "h.vti"
    whole = re.search(r'WholeExtent="([^"]*)"', text)
    piece = f'<Piece Extent="{whole.group(1)}">' if whole else "<Piece>"
    array = re.search(r"<DataArray[^>]*?/?>", text)
    array = array.group(0).rstrip("/>") + ' format="ascii"/>' if array else ""
    tag = re.match(r"<ImageData[^>]*>", text).group(0)
    p.write_text(
        f'<?xml version="1.0"?><VTKFile type="ImageData">{tag}{piece}<PointData>{array}'
        "</PointData></Piece></ImageData></VTKFile>"
    )
    msg = _raises(p, expected)
    assert str(p) in msg


@pytest.mark.parametrize(
    ("lines", "expected"),
    [
        (["DATASET STRUCTURED_POINTS", "DIMENSIONS 100000 100000 100000", "SPACING 1 1 1",
          "POINT_DATA 1000000000000000", "SCALARS s unsigned_char", "LOOKUP_TABLE default"],
         "field 'DIMENSIONS': sizes 100000"),
        (["DATASET STRUCTURED_POINTS", "DIMENSIONS 4 4", "POINT_DATA 16"], "expected 3 integers"),
        (["DATASET STRUCTURED_POINTS", "DIMENSIONS 4 4 4", "SPACING 1 0 1", "POINT_DATA 64"],
         "'SPACING'"),
        (["DATASET STRUCTURED_POINTS", "DIMENSIONS 4 4 4", "POINT_DATA 64",
          "SCALARS s quaternion"], "unsupported type"),
        (["DATASET UNSTRUCTURED_GRID"], "expected STRUCTURED_POINTS"),
    ],
)  # fmt: skip
def test_legacy_vtk_headers_are_checked_before_reading(tmp_path, lines, expected):
    p = tmp_path / "h.vtk"
    p.write_text("\n".join(["# vtk DataFile Version 3.0", "t", "BINARY", *lines, ""]))
    msg = _raises(p, expected)
    assert str(p) in msg


def test_multicomponent_image_is_rejected(tmp_path):
    image = vtkImageData()
    image.SetDimensions(3, 3, 3)
    arr = numpy_to_vtk(np.zeros((27, 3), np.float32), deep=True)
    arr.SetName("rgb")
    image.GetPointData().SetScalars(arr)
    writer = vtkXMLImageDataWriter()
    writer.SetInputData(image)
    writer.SetFileName(str(tmp_path / "rgb.vti"))
    writer.Write()
    _raises(tmp_path / "rgb.vti", "point array 'rgb' has 3 components")


# --- shared data --------------------------------------------------------------------------


def _manifest(shared: Path) -> list[tuple[str, tuple[int, int, int], str, tuple | None]]:
    rows = []
    for line in (shared / "MANIFEST.md").read_text().splitlines():
        m = re.match(
            r"\| `(\w+)_(\d+)x(\d+)x(\d+)_(\w+)\.raw` \(\+`\w+\.nhdr`\).*?\| (\w+) \| ([^|]+) \|",
            line,
        )
        if m:
            spacing = m.group(7).split("(")[0].strip()
            sp = None if spacing in ("\u2013", "-") else tuple(float(s) for s in spacing.split(","))
            dims = (int(m.group(2)), int(m.group(3)), int(m.group(4)))
            rows.append((m.group(1), dims, m.group(5), sp))
    return rows


@pytest.mark.shared_data
def test_all_shared_volumes_load(shared_data):
    rows = _manifest(shared_data)
    assert len(rows) == 16
    for name, dims, dtype, spacing in rows:
        vol = load_volume(shared_data / f"{name}.nhdr")
        assert vol.name == name
        assert vol.dims == dims, name
        assert vol.spacing == (spacing or (1.0, 1.0, 1.0)), name
        raw = shared_data / f"{name}_{dims[0]}x{dims[1]}x{dims[2]}_{dtype}.raw"
        ref = np.fromfile(raw, dtype=np.dtype(dtype).newbyteorder("<"))
        assert vol.data.dtype == np.dtype(dtype)
        np.testing.assert_array_equal(vol.data.ravel(), ref, err_msg=name)


@pytest.mark.shared_data
def test_shared_raw_and_vtk_nrrd_reader_agree(shared_data):
    from dvr_perception._vtk import vtkNrrdReader
    from dvr_perception.volume import from_vtk_image

    via_raw = load_volume(shared_data / "headsq_quarter_64x64x93_uint16.raw")
    assert via_raw.name == "headsq_quarter"
    reader = vtkNrrdReader()
    reader.SetFileName(str(shared_data / "headsq_quarter.nhdr"))
    reader.Update()
    via_vtk = from_vtk_image(reader.GetOutput())
    ours = load_volume(shared_data / "headsq_quarter.nhdr")
    np.testing.assert_array_equal(ours.data, via_raw.data)
    np.testing.assert_array_equal(ours.data, via_vtk.data)
    assert ours.spacing == via_vtk.spacing == (3.2, 3.2, 1.5)


@pytest.mark.parametrize("ext", [".mha", ".vti", ".nii", ".nii.gz", ".vtk"])
def test_truncated_vtk_formats_are_one_error(tmp_path, ext, capfd):
    path = tmp_path / f"t{ext}"
    save_volume(_random(np.uint8), path)
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) * 2 // 3])
    # every format's data is checked complete before anything is read (nothing printed)
    msg = _raises(path, "truncated")
    assert "0x" not in msg
    assert "ERR" not in capfd.readouterr().err


@pytest.mark.parametrize("dtype", ["int8", "uint8", "int16", "uint16", "int32", "uint32",
                                   "int64", "float32", "float64"])  # fmt: skip
@pytest.mark.parametrize("kind", ["vti-ascii", "vti", "vtk-ascii", "vtk", "mha", "mha-zlib"])
def test_our_readers_read_what_vtks_readers_read(tmp_path, kind, dtype):
    """The formats VTK no longer opens for us: the voxels and geometry VTK's readers give."""
    from vtkmodules.vtkIOImage import vtkMetaImageReader, vtkMetaImageWriter
    from vtkmodules.vtkIOLegacy import vtkStructuredPointsReader, vtkStructuredPointsWriter
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    from dvr_perception.volume import from_vtk_image
    from dvr_perception.volume.convert import to_vtk_image

    ext = kind.split("-")[0]
    if ext == "mha" and dtype == "int64":
        with pytest.raises(DVRInputError, match="cannot store 64-bit integers"):
            save_volume(_random(dtype), tmp_path / "v.mha")
        return  # VTK's writer would write half the voxels (and its reader read garbage)
    vol = _random(dtype)
    path = tmp_path / f"v.{ext}"
    writer, reader = {
        "vti": (vtkXMLImageDataWriter, vtkXMLImageDataReader),
        "vtk": (vtkStructuredPointsWriter, vtkStructuredPointsReader),
        "mha": (vtkMetaImageWriter, vtkMetaImageReader),
    }[ext]
    writer, reader = writer(), reader()
    if kind == "vti-ascii":
        writer.SetDataModeToAscii()
    if kind == "vtk":
        writer.SetFileTypeToBinary()
    if ext == "mha":
        writer.SetCompression(kind == "mha-zlib")
    writer.SetInputData(to_vtk_image(vol))
    writer.SetFileName(str(path))
    writer.Write()
    if kind == "vtk-ascii" and dtype == "uint8":  # VTK writes colour scalars in [0, 1] ...
        with pytest.raises(DVRInputError, match="ASCII colour scalars are not supported"):
            load_volume(path)  # ... that its own reader turns back into bytes: refused
        return
    reader.SetFileName(str(path))
    reader.Update()
    theirs = from_vtk_image(reader.GetOutput(), oriented=False)
    ours = load_volume(path)
    assert ours.data.dtype == theirs.data.dtype
    np.testing.assert_array_equal(ours.data, theirs.data)
    assert (ours.spacing, ours.origin) == (theirs.spacing, theirs.origin) == (SPACING, ORIGIN)
    if "ascii" not in kind:
        np.testing.assert_array_equal(ours.data, vol.data)


def test_vti_extent_not_from_zero_and_scalars_naming_no_array(tmp_path):
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    from dvr_perception.volume import from_vtk_image

    data = np.arange(24, dtype=np.uint16).tobytes()
    path = tmp_path / "e.vti"
    path.write_text(
        '<VTKFile type="ImageData" byte_order="LittleEndian"><ImageData WholeExtent="2 5 -1 1 '
        '3 4" Origin="1 2 3" Spacing="0.5 2 4" Direction="0 1 0 1 0 0 0 0 -1"><Piece '
        'Extent="2 5 -1 1 3 4"><PointData Scalars="nothing"><DataArray type="UInt16" Name="v" '
        f'format="ascii">{" ".join(map(str, range(24)))}</DataArray></PointData></Piece>'
        "</ImageData></VTKFile>"
    )
    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    theirs = from_vtk_image(reader.GetOutput())
    ours = load_volume(path)
    np.testing.assert_array_equal(ours.data, theirs.data)
    assert ours.origin == theirs.origin
    assert ours.spacing == theirs.spacing == (2.0, 0.5, 4.0)  # the permutation applied
    assert ours.data.tobytes() != data  # ... to the data order too


@pytest.mark.parametrize("mode", [0, 1, 2])  # ascii, binary, appended
def test_vti_with_field_data_loads(tmp_path, mode):
    from vtkmodules.vtkCommonCore import vtkDoubleArray

    from dvr_perception.volume.convert import to_vtk_image

    vol = _random(np.float32)
    image = to_vtk_image(vol)
    time = vtkDoubleArray()
    time.SetName("TimeValue")
    time.InsertNextValue(2.5)
    image.GetFieldData().AddArray(time)  # as ParaView saves a time step
    writer = vtkXMLImageDataWriter()
    writer.SetInputData(image)
    writer.SetDataMode(mode)
    writer.SetFileName(str(tmp_path / "f.vti"))
    writer.Write()
    assert b"<FieldData>" in (tmp_path / "f.vti").read_bytes()
    np.testing.assert_array_equal(load_volume(tmp_path / "f.vti").data, vol.data)
