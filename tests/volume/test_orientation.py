"""Patient geometry end to end: one CT block stored in many orders renders the same.

The block is written as a DICOM series (pydicom; slices head first, file names and instance
numbers shuffled, HU through RescaleIntercept), a coronal DICOM series, an NRRD with a
negative z direction, a canonical NRRD, a NIfTI with a flipped s-form (nibabel) and a VTI with
a direction matrix.  Every copy must load to the same voxels at the same patient positions
and render the same from three views, one of them oblique; an asymmetric marker must appear
on the side of the image its patient coordinates say.
"""

from __future__ import annotations

import math
from dataclasses import replace

import nibabel
import numpy as np
import pydicom
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera, parse_patient_view, patient_angles, patient_view
from dvr_perception.rays.engine import analyze
from dvr_perception.rays.vtk_reference import compare_images
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.volume import Volume, load_volume, save_volume
from dvr_perception.volume.orient import canonical

SPACING = (0.8, 0.9, 1.5)
ORIGIN = (-12.0, -20.0, 30.0)
MARKER_HU = 1500
SPEC = StructureSpec(
    (
        Structure("tissue", 0.25, (0.8, 0.7, 0.6), range=(-200, 300)),
        Structure("marker", 0.95, (1.0, 0.1, 0.1), range=(1000, 2000)),
    ),
    rendering=RenderSettings(shade=False),
)
#: The body nearly transparent, so the marker shows from every side.
MARKER_SPEC = StructureSpec(
    (
        Structure("tissue", 0.02, (0.8, 0.7, 0.6), range=(-200, 300)),
        Structure("marker", 0.95, (1.0, 0.1, 0.1), range=(1000, 2000)),
    ),
    rendering=RenderSettings(shade=False),
)
VIEWS = (("anterior", 0, 0), ("left", 35, 25), ("superior", 0, 0))


def _block() -> Volume:
    """A 22 x 20 x 16 HU block in canonical LPS order with a marker at patient left-anterior."""
    z, y, x = np.mgrid[:16, :20, :22].astype(float)
    data = np.full((16, 20, 22), -1000, np.int16)
    body = ((x - 10.5) / 8) ** 2 + ((y - 9.5) / 7) ** 2 + ((z - 7.5) / 6) ** 2 <= 1
    data[body] = 40
    data[((x - 15) ** 2 + (y - 6) ** 2 + (z - 10) ** 2) <= 4] = MARKER_HU  # +x left, -y anterior
    return Volume(data, spacing=SPACING, origin=ORIGIN, name="block")


def _write_dicom(path, ds_values, *, position, orientation, spacing, instance, series_uid):
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = CTImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = pydicom.Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = CTImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    ds.SeriesInstanceUID = series_uid
    ds.StudyInstanceUID = "1.2.826.0.1.3680043.8.498.1"
    ds.InstanceNumber = instance
    ds.ImagePositionPatient = [float(v) for v in position]
    ds.ImageOrientationPatient = [float(v) for v in orientation]
    ds.PixelSpacing = [float(spacing[0]), float(spacing[1])]  # row spacing, column spacing
    ds.SliceThickness = 1.0
    ds.RescaleIntercept = -1024
    ds.RescaleSlope = 1
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = ds_values.shape
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.PixelData = (ds_values.astype(np.int32) + 1024).astype("<u2").tobytes()
    ds.save_as(path, enforce_file_format=True)


def _write_axial_series(folder, vol: Volume, *, seed: int, uid="1.2.3.4.5.1") -> None:
    """One file per slice, head first, shuffled file names and instance numbers."""
    folder.mkdir()
    rng = np.random.default_rng(seed)
    nz = vol.data.shape[0]
    names = rng.permutation(nz)
    numbers = rng.permutation(nz) + 1
    for i, k in enumerate(range(nz - 1, -1, -1)):  # z descending, as scanners often store
        pos = np.add(vol.origin, (0.0, 0.0, k * vol.spacing[2]))
        _write_dicom(
            folder / f"IM{names[i]:04d}",
            vol.data[k],
            position=pos,
            orientation=(1, 0, 0, 0, 1, 0),
            spacing=(vol.spacing[1], vol.spacing[0]),
            instance=int(numbers[i]),
            series_uid=uid,
        )


def _write_coronal_series(folder, vol: Volume) -> None:
    """Coronal slices (normal -y: from posterior to anterior), rows running inferior."""
    folder.mkdir()
    ny = vol.data.shape[1]
    nz = vol.data.shape[0]
    for j in range(ny):
        image = vol.data[::-1, j, :]  # rows: z from top to bottom; columns: +x
        pos = np.add(vol.origin, (0.0, j * vol.spacing[1], (nz - 1) * vol.spacing[2]))
        _write_dicom(
            folder / f"cor{(j * 7) % ny:03d}.dcm",
            image,
            position=pos,
            orientation=(1, 0, 0, 0, 0, -1),  # normal = x cross (-z) = +y
            spacing=(vol.spacing[2], vol.spacing[0]),
            instance=ny - j,
            series_uid="1.2.3.4.5.2",
        )


def _write_nrrd_negative_z(path, vol: Volume) -> None:
    nz = vol.data.shape[0]
    top = vol.origin[2] + (nz - 1) * vol.spacing[2]
    sx, sy, sz = vol.spacing
    head = [
        "NRRD0004",
        "type: short",
        "dimension: 3",
        f"sizes: {vol.dims[0]} {vol.dims[1]} {vol.dims[2]}",
        "space: left-posterior-superior",
        f"space directions: ({sx},0,0) (0,{sy},0) (0,0,{-sz})",
        f"space origin: ({vol.origin[0]},{vol.origin[1]},{top})",
        "endian: little",
        "encoding: raw",
    ]
    payload = np.ascontiguousarray(vol.data[::-1]).astype("<i2").tobytes()
    path.write_bytes(("\n".join(head) + "\n\n").encode() + payload)


def _write_nifti_flipped(path, vol: Volume) -> None:
    """RAS s-form with x flipped (radiological storage): index x runs to patient right."""
    data_xyz = vol.data[:, :, ::-1].transpose(2, 1, 0)  # nibabel order [x, y, z]
    sx, sy, sz = vol.spacing
    leftmost = vol.origin[0] + (vol.dims[0] - 1) * sx  # LPS x of the first stored column
    affine = np.array(
        [
            [sx, 0, 0, -leftmost],  # RAS x = -LPS x: stored columns run to the patient's right
            [0, -sy, 0, -vol.origin[1]],
            [0, 0, sz, vol.origin[2]],
            [0, 0, 0, 1],
        ]
    )
    img = nibabel.Nifti1Image(data_xyz.astype(np.int16), affine)
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
    nibabel.save(img, str(path))


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    d = tmp_path_factory.mktemp("orient")
    vol = _block()
    _write_axial_series(d / "dicom_axial", vol, seed=21)
    _write_coronal_series(d / "dicom_coronal", vol)
    _write_nrrd_negative_z(d / "negz.nrrd", vol)
    save_volume(vol, d / "canonical.nrrd")
    _write_nifti_flipped(d / "flipped.nii.gz", vol)
    flipped = Volume(
        vol.data[:, ::-1, ::-1].copy(),
        spacing=vol.spacing,
        origin=(
            vol.origin[0] + (vol.dims[0] - 1) * SPACING[0],
            vol.origin[1] + (vol.dims[1] - 1) * SPACING[1],
            vol.origin[2],
        ),
        direction=((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
    )
    save_volume(flipped, d / "rotated.vti")  # a VTK image with a 180-degree direction matrix
    return d, vol


COPIES = [
    "dicom_axial",
    "dicom_coronal",
    "negz.nrrd",
    "canonical.nrrd",
    "flipped.nii.gz",
    "rotated.vti",
]


@pytest.mark.parametrize("name", COPIES)
def test_every_storage_order_loads_to_the_same_patient_volume(stored, name):
    d, ref = stored
    vol = load_volume(d / name)
    assert not vol.oblique
    assert vol.oriented  # every copy records its patient orientation
    np.testing.assert_allclose(vol.spacing, ref.spacing, rtol=1e-6)
    np.testing.assert_allclose(vol.origin, ref.origin, atol=1e-4)
    np.testing.assert_array_equal(vol.data, ref.data)  # HU: the intercept was applied


@pytest.mark.parametrize("name", ["dicom_axial", "negz.nrrd", "flipped.nii.gz"])
def test_every_storage_order_renders_the_same(stored, name):
    d, ref = stored
    vol = load_volume(d / name)
    for view, az, el in VIEWS:
        cams = [patient_view(v, view, azimuth=az, elevation=el, width=40, height=40)
                for v in (ref, vol)]  # fmt: skip
        a, b = (analyze(v, SPEC, c).image for v, c in zip((ref, vol), cams, strict=True))
        assert compare_images(a, b)["ssim"] >= 0.99, (name, view)


def _marker_column(vol: Volume, cam: Camera) -> float:
    img = analyze(vol, MARKER_SPEC, cam).image
    red = (img[..., 0] > 0.4) & (img[..., 1] < 0.5 * img[..., 0])
    assert red.sum() >= 3, "the marker is not visible"
    return float(np.nonzero(red)[1].mean()) / cam.width


def test_marker_appears_on_its_patient_side(stored):
    """The marker sits at patient left (+x) and anterior (-y)."""
    d, _ = stored
    vol = load_volume(d / "dicom_axial")
    # from the front the patient's left is on the viewer's right; from behind on the left
    assert _marker_column(vol, patient_view(vol, "anterior", width=40, height=40)) > 0.55
    assert _marker_column(vol, patient_view(vol, "posterior", width=40, height=40)) < 0.45
    # seen from the left side the face (anterior) is on the image's left
    assert _marker_column(vol, patient_view(vol, "left", width=40, height=40)) < 0.45
    assert _marker_column(vol, patient_view(vol, "right", width=40, height=40)) > 0.55


def _oblique(angle_deg: float) -> Volume:
    a = math.radians(angle_deg)
    rot = ((math.cos(a), -math.sin(a), 0.0), (math.sin(a), math.cos(a), 0.0), (0.0, 0.0, 1.0))
    base = _block()
    return Volume(base.data, spacing=base.spacing, origin=base.origin, direction=rot)


def test_oblique_volume_keeps_its_rotation_and_renders_in_patient_terms(tmp_path):
    vol = _oblique(180.0 + 30.0)  # index x runs mostly to patient -x, index y to -y
    save_volume(vol, tmp_path / "oblique.nrrd")
    back = load_volume(tmp_path / "oblique.nrrd")
    assert back.oblique
    # canonical order: the smallest remaining rotation (30 degrees about z)
    np.testing.assert_allclose(np.asarray(back.direction)[:2, :2], [[0.866, -0.5], [0.5, 0.866]],
                               atol=1e-3)  # fmt: skip
    # every voxel keeps its patient position
    k, j, i = 10, 6, 15  # the marker centre in the written grid
    world = vol.to_world(np.add(vol.origin, np.multiply((i, j, k), vol.spacing)))
    q = (back.to_frame(world) - np.asarray(back.origin)) / np.asarray(back.spacing)
    idx = np.round(q).astype(int)
    np.testing.assert_allclose(q, idx, atol=1e-6)
    assert back.data[idx[2], idx[1], idx[0]] == MARKER_HU
    # the marker is at patient +x? world tells which side it must appear on
    side = world[0] - back.to_world(back.center)[0]
    col = _marker_column(back, patient_view(back, "anterior", width=40, height=40))
    assert (col - 0.5) * side > 0  # anterior view: patient left (+x) on the image right


def test_oblique_view_equals_the_rotated_axis_aligned_volume():
    """A 90-degree 'oblique' volume renders like its data rotated into axis order."""
    vol = _oblique(90.0)
    assert vol.oblique  # the constructor keeps what it is given; loaders canonicalise
    flat = canonical(vol)
    assert not flat.oblique
    for view, az, el in VIEWS:
        a = analyze(vol, SPEC, patient_view(vol, view, azimuth=az, elevation=el,
                                            width=40, height=40)).image  # fmt: skip
        b = analyze(flat, SPEC, patient_view(flat, view, azimuth=az, elevation=el,
                                             width=40, height=40)).image  # fmt: skip
        assert compare_images(a, b)["ssim"] >= 0.99, view


@pytest.mark.parametrize("view", ["anterior", "left", "inferior"])
def test_patient_angles_invert_the_patient_view_also_when_oblique(view):
    vol = _block()
    for v in (vol, _oblique(25.0)):
        for az, el in ((0.0, 0.0), (30.0, -10.0), (-120.0, 45.0)):
            cam = patient_view(v, view, azimuth=az, elevation=el, width=8, height=8)
            assert patient_angles(v, cam, view) == pytest.approx((az, el), abs=1e-6)
    # the anterior camera, seen from the posterior view, is half a turn round
    cam = patient_view(vol, "anterior", width=8, height=8)
    assert abs(patient_angles(vol, cam, "posterior")[0]) == pytest.approx(180.0)
    with pytest.raises(DVRInputError, match="unknown patient view"):
        patient_angles(vol, cam, "front")


def test_named_view_parsing_and_errors():
    assert parse_patient_view("Anterior,10,-5") == ("anterior", 10.0, -5.0, 1.0)
    assert parse_patient_view("-30,10,2") == (None, -30.0, 10.0, 2.0)
    with pytest.raises(DVRInputError, match=r"unknown view 'front'.*anterior"):
        parse_patient_view("front")
    with pytest.raises(DVRInputError, match="AZIMUTH,ELEVATION"):
        parse_patient_view("left,abc")
    vol = _block()
    cam = patient_view(vol, "superior", width=8, height=8)
    fwd, _, up = cam.basis()
    np.testing.assert_allclose(fwd, (0, 0, -1), atol=1e-12)  # looking down at the head
    np.testing.assert_allclose(up, (0, -1, 0), atol=1e-12)  # the face up


def test_reflection_and_shear_are_refused(tmp_path):
    with pytest.raises(DVRInputError, match="reflection"):
        Volume(np.zeros((2, 2, 2), np.uint8), direction=((1, 0, 0), (0, 1, 0), (0, 0, -1)))
    p = tmp_path / "shear.nrrd"
    p.write_bytes(
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nspace: left-posterior-superior\n"
        b"space directions: (1,0,0) (1,1,0) (0,0,1)\nencoding: raw\n\n" + bytes(8)
    )
    with pytest.raises(DVRInputError, match=r"shear.nrrd: .*not orthogonal"):
        load_volume(p)


def test_render_cli_named_view(stored, tmp_path):
    """``--view anterior`` through the CLI equals the API's patient view."""
    import contextlib
    import io

    from dvr_perception._vtk import vtk_to_numpy, vtkPNGReader
    from dvr_perception.cli import main
    from dvr_perception.structures.io import save_spec

    d, ref = stored
    save_spec(SPEC, tmp_path / "spec.json")
    out = tmp_path / "a.png"
    argv = ["render", str(d / "negz.nrrd"), "--structures", str(tmp_path / "spec.json"),
            "--view", "anterior", "--size", "32", "--out", str(out)]  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(argv) == 0
    reader = vtkPNGReader()
    reader.SetFileName(str(out))
    reader.Update()
    png = vtk_to_numpy(reader.GetOutput().GetPointData().GetScalars()).reshape(32, 32, -1)
    png = png[::-1, :, :3] / 255.0  # VTK's PNG rows are bottom-up
    want = analyze(ref, SPEC, patient_view(ref, "anterior", width=32, height=32)).image
    assert compare_images(png, want)["ssim"] >= 0.98


@pytest.mark.parametrize("ext", [".nii.gz", ".vti", ".nrrd"])
def test_oblique_round_trip(tmp_path, ext):
    """Writers keep an oblique direction; nibabel reads our NIfTI at the same positions."""
    vol = _oblique(25.0)
    save_volume(vol, tmp_path / f"ob{ext}")
    back = load_volume(tmp_path / f"ob{ext}")
    np.testing.assert_array_equal(back.data, vol.data)
    np.testing.assert_allclose(back.direction, vol.direction, atol=1e-6)
    np.testing.assert_allclose(back.origin, vol.origin, atol=1e-5)
    np.testing.assert_allclose(back.spacing, vol.spacing, rtol=1e-6)
    if ext == ".nii.gz":
        affine = nibabel.load(str(tmp_path / f"ob{ext}")).affine
        ijk = np.array([4.0, 7.0, 3.0])
        ras = (affine @ (*ijk, 1))[:3]
        lps = vol.to_world(np.asarray(vol.origin) + ijk * vol.spacing)
        np.testing.assert_allclose(ras * (-1, -1, 1), lps, atol=1e-4)
    with pytest.raises(DVRInputError, match="oblique direction"):
        save_volume(vol, tmp_path / "ob.mha")


def test_metaimage_transform_matrix(tmp_path):
    """An ITK-style .mha with a rotated TransformMatrix (y and z reversed) loads canonically."""
    ref = _block()
    stored = ref.data[::-1, ::-1, :]  # index y runs anterior, index z inferior
    nz, ny, _ = ref.data.shape
    top = ref.origin[2] + (nz - 1) * SPACING[2]
    back = ref.origin[1] + (ny - 1) * SPACING[1]
    head = (
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        "TransformMatrix = 1 0 0 0 -1 0 0 0 -1\n"
        f"Offset = {ref.origin[0]} {back} {top}\n"
        f"ElementSpacing = {SPACING[0]} {SPACING[1]} {SPACING[2]}\n"
        f"DimSize = {ref.dims[0]} {ref.dims[1]} {ref.dims[2]}\n"
        "ElementType = MET_SHORT\nElementDataFile = LOCAL\n"
    )
    path = tmp_path / "itk.mha"
    path.write_bytes(head.encode() + np.ascontiguousarray(stored).astype("<i2").tobytes())
    vol = load_volume(path)
    np.testing.assert_array_equal(vol.data, ref.data)
    np.testing.assert_allclose(vol.origin, ref.origin, atol=1e-6)


def test_world_camera_into_the_volume_frame():
    """A world camera (ParaView's) mapped into an oblique volume's frame = the patient view."""
    vol = _oblique(25.0)
    cam = patient_view(vol, "left", azimuth=10, elevation=20, width=8, height=8)
    d = np.asarray(vol.direction)
    world = Camera(
        position=tuple(vol.to_world(cam.position)),
        focal_point=tuple(vol.to_world(cam.focal_point)),
        view_up=tuple(d @ cam.view_up),
        width=8,
        height=8,
    )
    assert not np.allclose(world.position, cam.position)
    back = world.in_volume_frame(vol)
    np.testing.assert_allclose(back.position, cam.position, atol=1e-9)
    np.testing.assert_allclose(back.view_up, cam.view_up, atol=1e-12)
    assert _block().oblique is False
    assert world.in_volume_frame(_block()) is world


def test_mpi_pieces_refuse_a_direction_matrix():
    """ParaView pieces are placed by index extents: an image with a direction is one error."""
    from types import SimpleNamespace

    from dvr_perception.filters import PerceptionMeasures
    from dvr_perception.volume import to_vtk_image

    flipped = Volume(_block().data, direction=((-1, 0, 0), (0, -1, 0), (0, 0, 1)))
    image = to_vtk_image(flipped, with_direction=True)
    comm = SimpleNamespace(rank=0, size=2)
    with pytest.raises(DVRInputError, match="direction matrix cannot be split across MPI"):
        PerceptionMeasures().piece_inputs(image, comm, 0, image.GetExtent())


def test_pvbatch_forwards_series_and_checks_named_views(tmp_path):
    """``pvbatch`` passes --series and a named view on; MPI ranks take numeric views only."""
    import argparse
    import contextlib
    import io

    from dvr_perception.cli import main
    from dvr_perception.cli.pvbatch import _script_args

    args = argparse.Namespace(volume="d", structures=None, camera=None, size=None,
                              series="1.2.3", view="anterior,10,5", shade=None, sigma=1.0,
                              out="o")  # fmt: skip
    argv = _script_args(args)
    assert argv[argv.index("--series") + 1] == "1.2.3"
    assert "--view=anterior,10,5" in argv
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(["pvbatch", "phantom", "--view", "left", "--ranks", "2", "--out",
                     str(tmp_path / "o")])  # fmt: skip
    assert code == 2
    assert "named patient view needs --ranks 1" in err.getvalue()


def test_pvbatch_ranks_refuse_a_file_stored_flipped(stored, tmp_path, monkeypatch):
    """``--ranks N`` reads pieces in file order: a negative-z NRRD is one error, before any
    ParaView starts; the canonical NRRD passes this check."""
    import contextlib
    import io

    from dvr_perception.cli import main, pvbatch
    from dvr_perception.volume.io import header_axes

    d, _ref = stored
    assert header_axes(d / "negz.nrrd")[2, 2] < 0
    assert header_axes(d / "flipped.nii.gz") is None  # not a header this check reads
    monkeypatch.setattr(pvbatch, "find_paraview", lambda *a: pytest.fail("ParaView started"))
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(["pvbatch", str(d / "negz.nrrd"), "--ranks", "2", "--out",
                     str(tmp_path / "o")])  # fmt: skip
    assert code == 2
    assert "negz.nrrd stores its axes flipped, permuted or rotated" in err.getvalue()
    assert "(0,0,-" in err.getvalue()
    assert "Traceback" not in err.getvalue()
    pvbatch._check_file_order(str(d / "canonical.nrrd"))  # axis-aligned, positive: no error


def test_pvbatch_ranks_read_only_files_whose_axes_the_header_shows(tmp_path, monkeypatch):
    """``--ranks N``: NIfTI, DICOM, MGZ and raw files (orientation only our readers apply) are
    one error naming the file and ``--ranks 1``; a ``.vti`` is checked from its Direction."""
    import contextlib
    import io

    from dvr_perception.cli import main, pvbatch

    monkeypatch.setattr(pvbatch, "find_paraview", lambda *a: pytest.fail("ParaView started"))
    vol = Volume(np.zeros((3, 4, 5), np.uint8), spacing=(1.0, 1.0, 2.0))
    save_volume(vol, tmp_path / "lps.nii.gz")
    (tmp_path / "series").mkdir()
    (tmp_path / "series" / "1.dcm").write_bytes(b"\0" * 132 + b"DICM")
    for name in ("one.dcm", "brain.mgz", "v_5x4x3_uint8.raw"):
        (tmp_path / name).write_bytes(b"\0" * 64)
    for name in ("lps.nii.gz", "series", "one.dcm", "brain.mgz", "v_5x4x3_uint8.raw"):
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            code = main(["pvbatch", str(tmp_path / name), "--ranks", "2", "--out",
                         str(tmp_path / "o")])  # fmt: skip
        assert code == 2, name
        lines = err.getvalue().strip().splitlines()
        assert len(lines) == 1, lines
        assert f"--ranks: {tmp_path / name} is a" in lines[0]
        assert "run with --ranks 1" in lines[0]
    turned = Volume(vol.data, direction=((0, -1, 0), (1, 0, 0), (0, 0, 1)))
    save_volume(turned, tmp_path / "turned.vti")
    with pytest.raises(DVRInputError, match=r"turned.vti stores its axes flipped, permuted"):
        pvbatch._check_file_order(str(tmp_path / "turned.vti"))
    for name in ("lps.vti", "plain.vti", "plain.vtk"):
        save_volume(replace(vol, oriented=name == "lps.vti"), tmp_path / name)
        pvbatch._check_file_order(str(tmp_path / name))  # file order is LPS: no error


def test_orientation_code_declares_a_file_without_orientation(stored, tmp_path):
    """``--orientation LPI``: a plain file whose slice 0 is the top renders as its LPS copy."""
    import contextlib
    import io

    from dvr_perception._files import read_png
    from dvr_perception.cli import main
    from dvr_perception.structures.io import save_spec
    from dvr_perception.volume.orient import parse_orientation, reorient

    d, ref = stored
    top_first = ref.data[::-1]  # as cthead is stored: slice 0 at the top, no orientation
    labels = (top_first > 1000).astype(np.uint8)
    top_z = ref.origin[2] + (ref.dims[2] - 1) * SPACING[2]
    plain = Volume(top_first.copy(), spacing=SPACING, origin=(*ref.origin[:2], top_z),
                   labels=labels)  # fmt: skip
    fixed = reorient(plain, "lpi")
    np.testing.assert_array_equal(fixed.data, ref.data)
    np.testing.assert_allclose(fixed.origin, ref.origin)
    np.testing.assert_array_equal(fixed.labels, (ref.data > 1000).astype(np.uint8))
    assert not fixed.oblique
    np.testing.assert_array_equal(reorient(ref, "LPS").data, ref.data)
    for bad in ("LP", "LLS", "LPX", "XYZ", "LPSI"):
        with pytest.raises(DVRInputError, match="--orientation: expected three letters"):
            parse_orientation(bad)
    with pytest.raises(DVRInputError, match="oblique"):
        reorient(_oblique(30.0), "LPS")
    # through the CLI, on a plain NRRD (no 'space' field): the same image as the LPS copy
    raw = tmp_path / "plain.raw"
    raw.write_bytes(top_first.astype("<i2").tobytes())
    (tmp_path / "plain.nhdr").write_text(
        "NRRD0004\ntype: short\ndimension: 3\nsizes: 22 20 16\nspacings: 0.8 0.9 1.5\n"
        "endian: little\nencoding: raw\ndata file: plain.raw\n"
    )
    save_spec(SPEC, tmp_path / "spec.json")
    shots, errs = {}, {}
    for name, src, extra in (("lps", d / "canonical.nrrd", []),
                             ("plain", tmp_path / "plain.nhdr", ["--orientation", "LPI"]),
                             ("raw", tmp_path / "plain.nhdr", [])):  # fmt: skip
        out = tmp_path / f"{name}.png"
        argv = ["render", str(src), "--structures", str(tmp_path / "spec.json"), "--view",
                "anterior", "--size", "32", "--out", str(out), *extra]  # fmt: skip
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            assert main(argv) == 0
        shots[name], errs[name] = read_png(out)[..., :3] / 255.0, err.getvalue()
    assert compare_images(shots["plain"], shots["lps"])["ssim"] >= 0.99
    assert compare_images(shots["raw"], shots["lps"])["ssim"] < 0.95  # upside down without it
    # a patient view of the file without orientation says so, once, naming file and fix
    warned = [ln for ln in errs["raw"].splitlines() if "records no patient orientation" in ln]
    assert len(warned) == 1, errs["raw"]
    assert warned[0].startswith(f"dvr-perception: warning: {tmp_path / 'plain.nhdr'}: ")
    assert "taken as L, P, S" in warned[0]
    assert "--orientation LPI" in warned[0]
    assert "orientation" not in errs["lps"]  # the file has a 'space': no note
    assert "orientation" not in errs["plain"]  # --orientation given: no note
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        assert main([*argv[:4], "--view=20,10", *argv[6:]]) == 0  # not a patient view
    assert "orientation" not in err.getvalue()


def test_files_without_orientation_are_flagged(tmp_path):
    """``Volume.oriented`` is False exactly for files that record no patient orientation, and
    survives the re-orderings and copies (canonical, upsample, labels) until ``reorient``."""
    import re
    from dataclasses import replace

    from dvr_perception.volume.orient import orientation_note, reorient
    from dvr_perception.volume.resample import upsample

    vol = _block()
    raw = vol.data.astype("<i2").tobytes()
    nrrd = "NRRD0004\ntype: short\ndimension: 3\nsizes: 22 20 16\nencoding: raw\n"
    files = {
        "spacings.nrrd": "spacings: 0.8 0.9 1.5\n",
        "space_dimension.nrrd": "space dimension: 3\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n",
        "right_handed.nrrd": "space: 3D-right-handed\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n",
        "lps.nrrd": "space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n",
        "ras.nrrd": "space: RAS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n",
    }
    for name, fields in files.items():
        (tmp_path / name).write_bytes((nrrd + fields + "\n").encode() + raw)
    (tmp_path / "block_22x20x16_int16.raw").write_bytes(raw)
    save_volume(vol, tmp_path / "legacy.vtk")
    save_volume(vol, tmp_path / "direction.vti")
    text = (tmp_path / "direction.vti").read_bytes()
    no_dir = re.sub(rb' Direction="[^"]*"', b"", text, count=1)
    assert no_dir != text
    (tmp_path / "plain.vti").write_bytes(no_dir)
    img = nibabel.Nifti1Image(np.asarray(vol.data).T.copy(), np.eye(4))
    img.set_qform(None, code=0)
    img.set_sform(None, code=0)
    nibabel.save(img, str(tmp_path / "no_form.nii"))
    save_volume(vol, tmp_path / "itk.mha")  # writes a TransformMatrix
    mha = (tmp_path / "itk.mha").read_bytes()
    (tmp_path / "plain.mha").write_bytes(re.sub(rb"TransformMatrix = [^\n]*\n", b"", mha))
    expect = {"spacings.nrrd": False, "space_dimension.nrrd": False, "right_handed.nrrd": False,
              "lps.nrrd": True, "ras.nrrd": True, "block_22x20x16_int16.raw": False,
              "legacy.vtk": False, "direction.vti": True, "plain.vti": False,
              "no_form.nii": False, "itk.mha": True, "plain.mha": False}  # fmt: skip
    got = {name: load_volume(tmp_path / name).oriented for name in expect}
    assert got == expect
    plain = load_volume(tmp_path / "spacings.nrrd")
    np.testing.assert_array_equal(plain.data, vol.data)  # taken as L, P, S: as stored
    labelled = replace(plain, labels=(plain.data > 1000).astype(np.uint8))  # as attach_labels
    for copy in (canonical(plain), upsample(plain, (2, 1, 1)), labelled):
        assert copy.oriented is False
    assert "records no patient orientation" in orientation_note(plain)
    assert str(tmp_path / "spacings.nrrd") in orientation_note(plain)
    fixed = reorient(plain, "LPI")
    assert fixed.oriented
    assert orientation_note(fixed) is None
    assert reorient(labelled, "LPI").oriented
    assert Volume(vol.data).oriented  # in memory: what its direction says


@pytest.mark.parametrize("ext", [".nrrd", ".nhdr", ".vti", ".mha", ".mhd", ".nii", ".nii.gz"])
def test_saving_keeps_whether_a_volume_is_oriented(tmp_path, ext):
    """A re-saved file claims an orientation only if the volume had one: an unoriented volume
    reads back unoriented, an oriented one oriented, with the same voxels and geometry (NIfTI
    keeps no origin without a form: 0 then)."""
    from dvr_perception.volume.orient import reorient

    data = np.arange(60, dtype=np.int16).reshape(3, 4, 5)
    plain = Volume(data, spacing=(0.5, 0.75, 2.0), origin=(3.0, -4.0, 9.0), oriented=False)
    fixed = reorient(plain, "LPI")  # declared: slice 0 at the top, now oriented
    for vol, tag in ((plain, "plain"), (fixed, "fixed")):
        save_volume(vol, tmp_path / f"{tag}{ext}")
        back = load_volume(tmp_path / f"{tag}{ext}")
        assert back.oriented is vol.oriented, tag
        np.testing.assert_array_equal(back.data, vol.data)
        np.testing.assert_allclose(back.spacing, vol.spacing)
        keeps_origin = vol.oriented or ext not in (".nii", ".nii.gz")
        np.testing.assert_allclose(back.origin, vol.origin if keeps_origin else (0, 0, 0))
        assert not back.oblique
    head = (tmp_path / f"plain{ext}").read_bytes()[:600]
    for field in (b"space:", b"TransformMatrix", b"Direction"):
        assert field not in head
    if ext in (".nrrd", ".nhdr"):
        assert b"space dimension: 3" in head
        assert b"space: left-posterior-superior" in (tmp_path / f"fixed{ext}").read_bytes()
