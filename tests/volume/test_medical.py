"""DICOM, NIfTI and MGZ files that other tools wrote: pydicom's and nibabel's bundled test files.

Only files shipped inside the wheels are used (``pydicom.data`` files that are downloaded on
demand are not).  Every value is checked against what pydicom or nibabel read independently:
HU through the rescale, geometry from ImagePositionPatient / the affine.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import nibabel
import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file
from pydicom.pixels import apply_rescale
from pydicom.uid import generate_uid
from scipy import ndimage

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.rays import memory
from dvr_perception.volume import Volume, load_volume, medical

NIBABEL_DATA = Path(nibabel.__file__).parent / "tests" / "data"


def _shipped(name: str) -> Path:
    """A pydicom test file that is inside the installed package (never downloaded)."""
    path = Path(pydicom.data.__file__).parent / "test_files" / name
    assert path.is_file(), f"{name} is not shipped with pydicom {pydicom.__version__}"
    assert Path(get_testdata_file(name)) == path
    return path


def _value_at(vol: Volume, world) -> float:
    """Voxel value of ``vol`` at a world (LPS) point that must lie on its grid."""
    q = (vol.to_frame(world) - np.asarray(vol.origin)) / np.asarray(vol.spacing)
    idx = np.round(q).astype(int)
    np.testing.assert_allclose(q, idx, atol=1e-4)
    return vol.data[idx[2], idx[1], idx[0]]


def _series(folder: Path, source: Path, zs, *, series_uid="1.2.3.9.1", names=None, edit=None):
    """Copies of one pydicom test file as a series: slice k at z = zs[k], pixels untouched."""
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(7)
    numbers = rng.permutation(len(zs)) + 1
    for k, z in enumerate(zs):
        ds = pydicom.dcmread(source)
        ds.SeriesInstanceUID = series_uid
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.InstanceNumber = int(numbers[k])
        ipp = [float(v) for v in ds.get("ImagePositionPatient", [0.0, 0.0, 0.0])]
        ds.ImagePositionPatient = [ipp[0], ipp[1], float(z)]
        if "ImageOrientationPatient" not in ds:
            ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        if edit is not None:
            edit(ds, k)
        ds.save_as(folder / (names[k] if names else f"s{k}.dcm"))


def test_multiframe_rtdose_geometry_and_dose_scaling():
    path = _shipped("rtdose.dcm")
    ds = pydicom.dcmread(path)
    vol = load_volume(path)
    n = int(ds.NumberOfFrames)
    assert vol.dims == (int(ds.Columns), int(ds.Rows), n)
    offsets = [float(v) for v in ds.GridFrameOffsetVector]
    assert vol.spacing == pytest.approx((*map(float, ds.PixelSpacing[::-1]), offsets[1]))
    assert vol.origin == pytest.approx([float(v) for v in ds.ImagePositionPatient])
    dose = ds.pixel_array * float(ds.DoseGridScaling)
    np.testing.assert_allclose(vol.data, dose, rtol=1e-6)
    # the RLE-compressed copy decodes to the same dose grid
    rle = load_volume(_shipped("rtdose_rle.dcm"))
    np.testing.assert_array_equal(rle.data, vol.data)


def test_ct_series_hu_and_position_order(tmp_path):
    src = _shipped("CT_small.dcm")
    ref = pydicom.dcmread(src)
    hu = apply_rescale(ref.pixel_array, ref)  # pydicom's own HU
    zs = [-70.0, -75.0, -60.0, -65.0]  # neither file order nor instance numbers sort them
    _series(tmp_path / "ct", src, zs, names=["b", "d", "a", "c"])
    vol = load_volume(tmp_path / "ct")
    assert vol.dims == (128, 128, 4)
    assert vol.spacing == pytest.approx((*map(float, ref.PixelSpacing[::-1]), 5.0))
    x0, y0, _ = (float(v) for v in ref.ImagePositionPatient)
    assert vol.origin == pytest.approx((x0, y0, -75.0))
    assert vol.data.dtype == np.int16
    for z in zs:  # each slice in its place, in HU
        np.testing.assert_array_equal(vol.data[round((z + 75.0) / 5.0)], hu)
    assert _value_at(vol, (x0 + 3 * vol.spacing[0], y0, -60.0)) == hu[0, 3]


@pytest.mark.parametrize("name", ["MR_small_jp2klossless.dcm", "JPGExtended.dcm"])
def test_compressed_series_decodes_like_pydicom(tmp_path, name):
    """JPEG 2000 lossless (openjpeg) and JPEG extended (libjpeg) series from pydicom's data."""
    src = _shipped(name)
    ref = pydicom.dcmread(src)
    assert ref.file_meta.TransferSyntaxUID.is_compressed
    expected = apply_rescale(ref.pixel_array, ref)
    _series(tmp_path / "jpeg", src, [12.0, 10.0, 14.0])
    vol = load_volume(tmp_path / "jpeg")
    assert vol.dims == (int(ref.Columns), int(ref.Rows), 3)
    assert vol.spacing[2] == pytest.approx(2.0)
    assert vol.origin[2] == pytest.approx(10.0)
    for k in range(3):
        np.testing.assert_array_equal(vol.data[k], expected)


def test_enhanced_multiframe_sorted_along_the_normal(tmp_path):
    """Enhanced CT frames stored top first, each with its own rescale intercept."""
    src = pydicom.dcmread(_shipped("CT_small.dcm"))
    rows, cols = 8, 6
    raw = np.arange(4 * rows * cols, dtype=np.uint16).reshape(4, rows, cols) * 3
    ds = pydicom.Dataset()
    ds.file_meta = src.file_meta
    ds.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"  # Enhanced CT
    for key in ("PatientName", "StudyInstanceUID", "Modality"):
        setattr(ds, key, src.get(key))
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.SeriesInstanceUID = generate_uid()
    ds.Rows, ds.Columns, ds.NumberOfFrames = rows, cols, 4
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    shared = pydicom.Dataset()
    ori, pix = pydicom.Dataset(), pydicom.Dataset()
    ori.ImageOrientationPatient = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0]  # sagittal: normal +x
    pix.PixelSpacing = [1.5, 0.5]
    shared.PlaneOrientationSequence = [ori]
    shared.PixelMeasuresSequence = [pix]
    ds.SharedFunctionalGroupsSequence = [shared]
    frames = []
    xs = [30.0, 24.0, 27.0, 21.0]  # frame f at x = xs[f]
    for f, x in enumerate(xs):
        item, pos, tr = pydicom.Dataset(), pydicom.Dataset(), pydicom.Dataset()
        pos.ImagePositionPatient = [x, -5.0, 40.0]
        tr.RescaleIntercept, tr.RescaleSlope, tr.RescaleType = -1000 - f, 1, "HU"
        item.PlanePositionSequence = [pos]
        item.PixelValueTransformationSequence = [tr]
        frames.append(item)
    ds.PerFrameFunctionalGroupsSequence = frames
    ds.PixelData = raw.astype("<u2").tobytes()
    path = tmp_path / "enhanced.dcm"
    ds.save_as(path, enforce_file_format=True)
    vol = load_volume(path)
    # canonical LPS: index x along +x (the normal), y along +y (rows), z along +z (columns up)
    assert vol.dims == (4, cols, rows)
    assert vol.spacing == pytest.approx((3.0, 0.5, 1.5))
    assert vol.origin == pytest.approx((21.0, -5.0, 40.0 - 1.5 * (rows - 1)))
    for f, x in enumerate(xs):
        hu = raw[f].astype(int) - 1000 - f
        # frame pixel (r, c) lies at (x, -5 + 0.5 c, 40 - 1.5 r)
        for r, c in ((0, 0), (rows - 1, 2), (3, cols - 1)):
            assert _value_at(vol, (x, -5.0 + 0.5 * c, 40.0 - 1.5 * r)) == hu[r, c]


def test_several_series_are_listed_and_one_is_picked(tmp_path):
    src = _shipped("CT_small.dcm")
    _series(tmp_path / "mixed", src, [0.0, 2.0, 4.0], series_uid="1.2.3.9.1")
    _series(tmp_path / "other", src, [0.0, 3.0], series_uid="1.2.3.9.2")
    for f in (tmp_path / "other").iterdir():
        shutil.move(f, tmp_path / "mixed" / f"o_{f.name}")
    (tmp_path / "mixed" / "README.txt").write_text("not DICOM")
    with pytest.raises(
        DVRInputError, match=r"2 DICOM series.*--series.*1\.2\.3\.9\.1.*1\.2\.3\.9\.2"
    ):
        load_volume(tmp_path / "mixed")
    assert load_volume(tmp_path / "mixed", series="1.2.3.9.1").dims[2] == 3
    assert load_volume(tmp_path / "mixed", series="1.2.3.9.2").spacing[2] == pytest.approx(3.0)
    with pytest.raises(DVRInputError, match=r"--series '9\.9' not found"):
        load_volume(tmp_path / "mixed", series="9.9")


def test_dicom_headers_are_checked_before_pixels(tmp_path, monkeypatch):
    src = _shipped("rtdose.dcm")
    ds = pydicom.dcmread(src)
    ds.NumberOfFrames = 10**7  # header claims far more frames than the file holds
    ds.GridFrameOffsetVector = [0.0, 1.0]
    ds.save_as(tmp_path / "huge.dcm")
    monkeypatch.setattr(medical, "_pixels", lambda *a: pytest.fail("pixel data was read"))
    memory.set_limit("64M")
    try:
        with pytest.raises(DVRInputError, match=r"huge\.dcm: field 'Rows x Columns x Number"):
            load_volume(tmp_path / "huge.dcm")
    finally:
        memory.set_limit(None)
    with pytest.raises(DVRInputError, match=r"colour DICOM image .*'SamplesPerPixel' is 3.*RGB"):
        load_volume(_shipped("SC_rgb_rle_2frame.dcm"))
    with pytest.raises(DVRInputError, match=r"CT_small\.dcm: a single 2-D image"):
        load_volume(_shipped("CT_small.dcm"))


def test_duplicate_and_uneven_slices_are_one_clear_error(tmp_path):
    src = _shipped("CT_small.dcm")
    _series(tmp_path / "dup", src, [0.0, 2.0, 2.0])
    with pytest.raises(DVRInputError, match="two slices share the position 2 mm"):
        load_volume(tmp_path / "dup")
    _series(tmp_path / "gap", src, [0.0, 2.0, 5.0])
    with pytest.raises(DVRInputError, match="slice spacing varies from 2 to 3 mm"):
        load_volume(tmp_path / "gap")


def test_nibabel_nifti_positions_match_its_affine():
    """nibabel's anatomical.nii (radiological, x flipped) read by VTK's reader + the s-form."""
    path = NIBABEL_DATA / "anatomical.nii"
    img = nibabel.load(str(path))
    data = np.asarray(img.dataobj)
    vol = load_volume(path)
    assert not vol.oblique
    flip = np.array([-1.0, -1.0, 1.0])
    for ijk in ((0, 0, 0), (5, 17, 3), (32, 40, 24), (20, 3, 11)):
        world = flip * (img.affine @ (*ijk, 1))[:3]  # RAS -> LPS
        assert _value_at(vol, world) == data[ijk]


def test_mgz_written_by_nibabel(tmp_path):
    rng = np.random.default_rng(3)
    data = rng.integers(0, 200, (5, 6, 7)).astype(np.uint8)  # nibabel order [i, j, k]
    affine = np.array([[-1.0, 0, 0, 10], [0, 0, 2.0, -20], [0, -1.5, 0, 30], [0, 0, 0, 1]])
    nibabel.save(nibabel.MGHImage(data, affine), str(tmp_path / "brain.mgz"))
    vol = load_volume(tmp_path / "brain.mgz")
    assert vol.name == "brain"
    assert not vol.oblique
    assert sorted(vol.spacing) == pytest.approx([1.0, 1.5, 2.0])
    flip = np.array([-1.0, -1.0, 1.0])
    for ijk in ((0, 0, 0), (4, 5, 6), (2, 1, 3)):
        assert _value_at(vol, flip * (affine @ (*ijk, 1))[:3]) == data[ijk]
    # nibabel's own test.mgz is 4-D with two frames: refused, naming the field
    with pytest.raises(DVRInputError, match=r"test\.mgz: MGH field 'dims': expected a 3-D"):
        load_volume(NIBABEL_DATA / "test.mgz")


def test_missing_extra_names_it(tmp_path, monkeypatch):
    monkeypatch.setattr(medical, "available", lambda module="pydicom": False)
    with pytest.raises(DVRInputError, match=r"pip install 'dvr-perception\[medical\]'"):
        load_volume(_shipped("rtdose.dcm"))
    (tmp_path / "x.mgz").write_bytes(b"\0" * 400)
    with pytest.raises(DVRInputError, match=r"x\.mgz.*nibabel.*dvr-perception\[medical\]"):
        load_volume(tmp_path / "x.mgz")


def test_undecodable_compressed_pixels_name_the_plugins_and_how_to_get_them(tmp_path, monkeypatch):
    """A JPEG-LS series whose decoder is missing: one error naming the missing plug-ins, with
    the pip extra in the pip environment and ``make paraview-setup`` inside ParaView."""
    import sys

    import pydicom.pixels.decoders.base as decoders

    _series(tmp_path / "ls", _shipped("MR_small_jpeg_ls_lossless.dcm"), [0.0, 1.0])
    assert load_volume(tmp_path / "ls").dims == (64, 64, 2)  # decodes with the plug-ins

    def no_plugin(*_a, **_k):
        raise RuntimeError("all plugins are missing dependencies")

    monkeypatch.setattr(decoders.Decoder, "as_array", no_plugin)
    real = medical.available
    monkeypatch.setattr(medical, "available", lambda m="pydicom": m != "libjpeg" and real(m))
    with pytest.raises(DVRInputError) as err:
        load_volume(tmp_path / "ls")
    text = str(err.value)
    assert text.startswith(str(tmp_path / "ls"))
    assert "(transfer syntax JPEG-LS Lossless Image Compression)" in text
    assert "missing here: pylibjpeg-libjpeg;" in text
    assert text.endswith("install them with pip install 'dvr-perception[medical]')")
    monkeypatch.setitem(sys.modules, "paraview", sys)  # as inside pvpython
    with pytest.raises(DVRInputError, match=r"from \.pvdeps: run make paraview-setup\)$"):
        load_volume(tmp_path / "ls")


def test_series_option_through_the_cli(tmp_path):
    """``--series`` in the CLI: the list of series when missing, exit status 2, no traceback."""
    import contextlib
    import io

    from dvr_perception.cli import main

    src = _shipped("CT_small.dcm")
    _series(tmp_path / "mixed", src, [0.0, 2.0, 4.0], series_uid="1.2.3.9.1")
    _series(tmp_path / "mixed", src, [0.0, 3.0], series_uid="1.2.3.9.2", names=["p", "q"])
    argv = ["render", str(tmp_path / "mixed"), "--size", "16", "--out", str(tmp_path / "a.png")]
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        assert main(argv) == 2
    assert "1.2.3.9.1 (3 file(s), CT)" in err.getvalue()
    assert "Traceback" not in err.getvalue()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([*argv, "--series", "1.2.3.9.2", "--view", "anterior"]) == 0
    assert (tmp_path / "a.png").stat().st_size > 0


def test_corrupt_dicom_files_give_one_clear_error(tmp_path):
    """Seeded byte flips and truncations of a real series: a volume or one DVRInputError."""
    src = _shipped("CT_small.dcm")
    _series(tmp_path / "good", src, [0.0, 2.0, 4.0])
    good = sorted((tmp_path / "good").iterdir())
    rng = np.random.default_rng(18)
    outcomes = {"volume": 0, "error": 0}
    for trial in range(40):
        folder = tmp_path / f"t{trial}"
        shutil.copytree(tmp_path / "good", folder)
        victim = folder / good[trial % 3].name
        blob = bytearray(victim.read_bytes())
        if trial % 4 == 0:
            blob = blob[: int(rng.integers(140, len(blob)))]
        else:
            for pos in rng.integers(128, 1200, size=int(rng.integers(1, 6))):
                blob[pos] = int(rng.integers(0, 256))
        victim.write_bytes(bytes(blob))
        message = ""
        try:
            load_volume(folder)
        except DVRInputError as exc:
            message = str(exc)
        outcomes["error" if message else "volume"] += 1
        assert not message or message.startswith(str(folder)), message  # names the file
    assert outcomes["error"] >= 5, outcomes  # the mutations do break files


def test_series_in_sub_folders_are_found_and_listed_with_their_folder(tmp_path):
    """A study folder: series in nested sub-folders (as scanners export), read recursively."""
    src = _shipped("CT_small.dcm")
    (tmp_path / "study" / "ct").mkdir(parents=True)
    _series(tmp_path / "study" / "ct" / "a", src, [0.0, 2.0], series_uid="1.2.3.9.1")
    _series(tmp_path / "study" / "ct" / "b", src, [4.0], series_uid="1.2.3.9.1", names=["z"])
    _series(tmp_path / "study" / "mr", src, [0.0, 3.0], series_uid="1.2.3.9.2")
    with pytest.raises(DVRInputError, match=r"2 DICOM series.*9\.1 \(3 file\(s\) in ct/a, ct/b"):
        load_volume(tmp_path / "study")
    vol = load_volume(tmp_path / "study", series="1.2.3.9.1")
    assert vol.dims[2] == 3  # slices from both sub-folders, sorted by position
    assert vol.spacing[2] == pytest.approx(2.0)


def test_dicom_folder_walk_and_series_bytes_are_bounded(tmp_path, monkeypatch):
    src = _shipped("CT_small.dcm")
    _series(tmp_path / "ct", src, [0.0, 2.0, 4.0])
    monkeypatch.setattr(medical, "MAX_FILES", 2)
    with pytest.raises(DVRInputError, match=r"ct: more than 2 files in the folder and its sub"):
        load_volume(tmp_path / "ct")
    monkeypatch.setattr(medical, "MAX_FILES", 20000)

    def bloat(ds, k):  # 400 KB of private data per file: the pixels fit, the files do not
        ds.add_new(0x00091010, "OB", bytes(400_000))

    _series(tmp_path / "big", src, [0.0, 2.0, 4.0], edit=bloat)
    memory.set_limit("1M")
    try:
        with pytest.raises(DVRInputError, match=r"big: the series' 3 DICOM files hold 1 MiB, m"):
            load_volume(tmp_path / "big")
        assert load_volume(tmp_path / "ct").dims == (128, 128, 3)  # 3 x 39 KB: read
    finally:
        memory.set_limit(None)


def test_colour_series_is_one_clear_error(tmp_path):
    src = _shipped("CT_small.dcm")

    def colour(ds, k):
        if k == 1:  # only the second file: every file is checked, not only the first
            ds.PhotometricInterpretation = "YBR_FULL"

    _series(tmp_path / "ybr", src, [0.0, 2.0, 4.0], edit=colour)
    with pytest.raises(DVRInputError, match=r"s1\.dcm: a colour DICOM image.*YBR_FULL.*grey"):
        load_volume(tmp_path / "ybr")


@pytest.mark.parametrize("step", [(0.0, 1.0), (0.5, -0.25)])
def test_tilted_gantry_series_is_resampled_onto_the_regular_grid(tmp_path, step):
    """Slices stepping ``step`` pixels (columns, rows) off the normal per slice, as a tilted
    gantry acquires them: each voxel of the result lies where its world position says."""
    src = _shipped("CT_small.dcm")
    ref = pydicom.dcmread(src)
    hu = apply_rescale(ref.pixel_array, ref).astype(np.float64)
    ps = [float(v) for v in ref.PixelSpacing]  # (between rows, between columns)
    x0, y0, _ = (float(v) for v in ref.ImagePositionPatient)

    def tilt(ds, k):  # slice k at z = 3k, moved k*step pixels in its plane
        ds.ImagePositionPatient = [x0 + k * step[0] * ps[1], y0 + k * step[1] * ps[0], 3.0 * k]

    _series(tmp_path / "tilt", src, [0.0, 3.0, 6.0, 9.0], edit=tilt)
    with pytest.warns(DVRWarning, match=r"tilted gantry \([0-9.]+ degrees.*resampled"):
        vol = load_volume(tmp_path / "tilt")
    assert vol.dims == (128, 128, 4)
    assert vol.spacing == pytest.approx((ps[1], ps[0], 3.0))
    assert vol.origin == pytest.approx((x0, y0, 0.0))
    assert not vol.oblique
    for k in range(4):
        # output pixel (row j, column i) of slice k is acquired pixel (j, i) - k * step
        shifted = ndimage.shift(hu, (k * step[1], k * step[0]), order=1, cval=hu.min())
        inner = (slice(4, -4), slice(4, -4))
        np.testing.assert_allclose(vol.data[k][inner], np.rint(shifted[inner]), atol=1.0)
    if step == (0.0, 1.0):  # whole pixels: exactly the acquired values, one row further down
        np.testing.assert_array_equal(vol.data[2, 2:], hu[:-2].astype(np.int16))

    # a tilt that changes from slice to slice is not a regular grid: one clear error
    def wobble(ds, k):
        ds.ImagePositionPatient = [x0, y0 + (k % 2) * ps[0], 3.0 * k]

    _series(tmp_path / "wobble", src, [0.0, 3.0, 6.0], edit=wobble)
    with pytest.raises(DVRInputError, match="neither on one line along the slice normal nor"):
        load_volume(tmp_path / "wobble")
