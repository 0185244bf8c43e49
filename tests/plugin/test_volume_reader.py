"""The plugin's reader "DVR Perception volume": files in patient LPS inside ParaView (issue 21).

One pvpython run reads the same asymmetric object stored three ways -- a canonical NRRD, an
NRRD with a negative z ``space directions`` (slices stored top first; header written by hand
here), and an oblique NRRD (rotated 30 degrees about z) -- renders them with ParaView's GPU ray
caster at two views and runs *Perception Measures* on them.  ParaView's own NRRD reader on the
negative-z file is the control: it shows the object mirrored, so the comparison can fail.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dvr_perception._files import read_png
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.vtk_reference import compare_images
from dvr_perception.volume import Volume, load_volume, save_volume

REPO = Path(__file__).resolve().parents[2]
PLUGIN = REPO / "dvr_perception" / "paraview" / "dvr_perception_plugin.py"
MARK = "@@RESULT@@ "
N = 24
SPACING = (1.0, 1.0, 1.5)
ORIGIN = (-12.0, -12.0, -18.0)
VIEWS = ((30.0, 20.0), (-120.0, -35.0))
SHOT = 64  # ParaView screenshots
SIZE = 32  # Perception Measures images
TURN = np.radians(30.0)
SPEC = {
    "version": 1,
    "background": [0.0, 0.0, 0.0],
    "structures": [
        {"name": "slab", "range": [100, 140], "importance": 0.3, "color": [0.3, 0.5, 0.9]},
        {"name": "ball", "range": [180, 220], "importance": 0.6, "color": [0.9, 0.4, 0.2]},
        {"name": "marker", "range": [240, 255], "importance": 0.9, "color": [0.9, 0.9, 0.2]},
    ],
    "rendering": {"shade": True},
}


def asymmetric_object() -> np.ndarray:
    """``[z, y, x]`` uint8: a ball high up, a slab low at the back, a marker high, front left."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N]
    d = np.zeros((N, N, N), np.uint8)
    d[(x - 9) ** 2 + (y - 12) ** 2 + (z - 14) ** 2 < 36] = 200
    d[3:7, 13:20, 4:20] = 120
    d[16:20, 3:7, 16:20] = 250
    return d


def write_negative_z(path: Path, data: np.ndarray) -> None:
    """The object with its slices stored top first: ``space directions`` z is negative."""
    top = ORIGIN[2] + (N - 1) * SPACING[2]
    header = (
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 24 24 24\nspace: left-posterior-superior\n"
        f"space directions: (1,0,0) (0,1,0) (0,0,-{SPACING[2]})\n"
        f"space origin: ({ORIGIN[0]},{ORIGIN[1]},{top})\nendian: little\nencoding: raw\n\n"
    )
    path.write_bytes(header.encode("ascii") + np.ascontiguousarray(data[::-1]).tobytes())


SCRIPT = """
import json, os, sys, time
from paraview.simple import *
import paraview.simple as pvs
LoadPlugin(sys.argv[1], ns=globals())
MARK = sys.argv[3]
sys.path.insert(0, os.path.dirname(sys.argv[1]))
import batch_measure
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.io import spec_from_dict
job = json.load(open(sys.argv[2]))
spec = spec_from_dict(job["spec"], source="spec")
view = CreateView("RenderView")
view.OrientationAxesVisibility = 0
view.UseColorPaletteForBackground = 0
view.Background = [0.0, 0.0, 0.0]
out, t0 = {}, time.time()
for name, path in job["files"].items():
    if name == "paraview_own":
        reader, array = NrrdReader(FileName=path), "ImageFile"
    else:
        reader, array = DVRPerceptionvolume(FileName=path), "scalars"
    reader.UpdatePipeline()
    rec = {"bounds": list(reader.GetDataInformation().GetBounds()), "E": []}
    if not job["cameras"].get(name):  # read only: the values that reach ParaView
        import hashlib
        import numpy as np
        from vtkmodules.util.numpy_support import vtk_to_numpy
        image = servermanager.Fetch(reader)
        if image.GetPointData().GetScalars() is None:  # the reader failed: say why
            impl = getattr(reader.GetClientSideObject(), "_impl", None)
            out[name] = {"error": getattr(impl, "error_message", "") or "no data"}
            continue
        values = vtk_to_numpy(image.GetPointData().GetScalars())
        rec.update(dims=list(image.GetDimensions()), origin=list(image.GetOrigin()),
                   sum=int(values.astype(np.int64).sum()), first=values[0].item(),
                   sha1=hashlib.sha1(values.astype("<f8").tobytes()).hexdigest())
        out[name] = rec
        continue
    display = Show(reader, view)
    display.SetRepresentationType("Volume")
    ColorBy(display, ("POINTS", array))
    # GPU: ParaView's default (Smart) here; "Ray Cast Only" is the CPU ray caster
    display.VolumeRenderingMode = "Ray Cast Only" if name.endswith("_cpu") else "GPU Based"
    display.ScalarOpacityUnitDistance = min(job["spacing"])
    display.Shade = 1
    batch_measure.set_transfer_functions(pvs, display, array, spec)
    for k, cam in enumerate(job["cameras"][name]):
        camera = Camera.from_dict(cam, source="camera")
        batch_measure.set_camera(view, camera)
        batch_measure.save_screenshot(pvs, view, camera, f"{name}_{k}.png")
    Hide(reader, view)
    for az, el in job["views"] if name in job["measure"] else ():
        pm = PerceptionMeasures(Input=reader, SpecJSON=json.dumps(job["spec"]), UseSpecView=0,
                                Azimuth=az, Elevation=el, Width=job["size"], Height=job["size"])
        pm.UpdatePipeline()
        fd = servermanager.Fetch(pm).GetFieldData()
        rec["E"].append([fd.GetArray(t).GetValue(0) for t in ("E_v", "E_s", "E_t")])
        Delete(pm)
    rec["t"] = time.time() - t0
    out[name] = rec
print(MARK + json.dumps(out), flush=True)
"""


def _dicom_series(folder: Path) -> Path:
    """pydicom's CT_small as a 3-slice series, head first, in a sub-folder; names unsorted."""
    import pydicom
    from pydicom.data import get_testdata_file

    series = folder / "ct"
    series.mkdir(parents=True)
    for name, z in (("b.dcm", 6.0), ("a.dcm", 0.0), ("c.dcm", 3.0)):
        ds = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
        ds.SeriesInstanceUID = "1.2.3.21"
        ds.SOPInstanceUID = pydicom.uid.generate_uid()
        ds.ImagePositionPatient = [-10.0, -20.0, z]
        ds.save_as(series / name)
    return series


def _jpeg_series(folder: Path, name: str, zs) -> Path:
    """Copies of a JPEG-compressed pydicom test file as a series (slice k at ``zs[k]``), with a
    CT rescale (slope 1, intercept -1024) so the values are HU; the pixel data stay as stored."""
    import pydicom
    from pydicom.data import get_testdata_file

    folder.mkdir(parents=True)
    for k, z in enumerate(zs):
        ds = pydicom.dcmread(get_testdata_file(name))
        assert ds.file_meta.TransferSyntaxUID.is_compressed
        ds.SeriesInstanceUID = "1.2.3.21.7"
        ds.SOPInstanceUID = pydicom.uid.generate_uid()
        ds.ImagePositionPatient = [0.0, 0.0, float(z)]
        ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.save_as(folder / f"s{k}.dcm")
    return folder


def _rotated(camera: Camera, rot: np.ndarray, about) -> Camera:
    """``camera`` moved with the rotation ``rot`` about the point ``about`` (world)."""
    d = camera.to_dict()
    o = np.asarray(about, float)
    for key in ("position", "focal_point"):
        d[key] = (o + rot @ (np.asarray(d[key], float) - o)).tolist()
    d["view_up"] = (rot @ np.asarray(d["view_up"], float)).tolist()
    return Camera.from_dict(d, source="rotated")


@pytest.fixture(scope="module")
def pv_run(paraview, display, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reader")
    data = asymmetric_object()
    save_volume(Volume(data, spacing=SPACING, origin=ORIGIN), tmp / "canonical.nrrd")
    write_negative_z(tmp / "negz.nrrd", data)
    c, s = np.cos(TURN), np.sin(TURN)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    oblique = Volume(data, spacing=SPACING, origin=ORIGIN, direction=rot)
    save_volume(oblique, tmp / "oblique.nrrd")
    canonical = load_volume(tmp / "canonical.nrrd")
    cams = [Camera.from_view(canonical.bounds, azimuth=a, elevation=e, width=SHOT, height=SHOT)
            for a, e in VIEWS]  # fmt: skip
    files = {n: str(tmp / f"{n}.nrrd") for n in ("canonical", "negz", "oblique")}
    files["paraview_own"] = files["negz"]
    files["canonical_cpu"], files["oblique_cpu"] = files["canonical"], files["oblique"]
    cameras = {n: [c.to_dict() for c in cams] for n in files}
    # the oblique volume seen by the canonical cameras turned with it: the same picture
    cameras["oblique"] = [_rotated(c, rot, ORIGIN).to_dict() for c in cams]
    files["canonical_turned"], cameras["canonical_turned"] = files["canonical"], cameras["oblique"]
    measure = ["canonical", "negz", "oblique", "paraview_own"]
    files["dicom"] = str(_dicom_series(tmp / "study") / "b.dcm")  # one file: its series
    cameras["dicom"] = []
    # compressed series: 12-bit JPEG extended and JPEG-LS, which need pylibjpeg-libjpeg
    for key, name in JPEG_FILES.items():
        files[key] = str(_jpeg_series(tmp / key, name, [2.0, 0.0, 4.0]) / "s0.dcm")
        cameras[key] = []
    job = {"spec": SPEC, "files": files, "cameras": cameras, "views": VIEWS, "size": SIZE,
           "spacing": list(SPACING), "measure": measure}  # fmt: skip
    (tmp / "job.json").write_text(json.dumps(job), encoding="utf-8")
    (tmp / "script.py").write_text(SCRIPT, encoding="utf-8")
    proc = paraview.call(
        [str(paraview.pvpython), str(tmp / "script.py"), str(PLUGIN), str(tmp / "job.json"), MARK],
        env=dict(paraview.env, DISPLAY=display), cwd=tmp, capture_output=True, text=True,
        timeout=300, check=False,
    )  # fmt: skip
    got = paraview.result(proc, clean=False)
    (tmp / "result.json").write_text(json.dumps(got, indent=1), encoding="utf-8")
    images = {n: [read_png(tmp / f"{n}_{k}.png")[..., :3] / 255.0 for k in range(len(VIEWS))]
              for n in files if cameras[n]}  # fmt: skip
    return got, images, tmp


#: pydicom test files (greyscale, JPEG-compressed) read as series in ParaView.
JPEG_FILES = {"jpeg_extended": "JPGExtended.dcm", "jpeg_ls": "MR_small_jpeg_ls_lossless.dcm"}


def _ssim(a, b) -> float:
    return compare_images(a, b)["ssim"]


def test_negative_z_nrrd_renders_and_measures_as_the_canonical_one(pv_run):
    got, images, _tmp = pv_run
    assert got["negz"]["bounds"] == pytest.approx(got["canonical"]["bounds"])
    for k in range(len(VIEWS)):
        canon = images["canonical"][k]
        assert canon.max() > 0.3  # not blank
        assert (canon.max(axis=-1) > 0.05).mean() > 0.05
        assert _ssim(images["negz"][k], canon) >= 0.99, k
        np.testing.assert_allclose(got["negz"]["E"][k], got["canonical"]["E"][k], atol=1e-6)
    # the control: ParaView's own NRRD reader keeps file order, a mirror image
    assert _ssim(images["paraview_own"][0], images["canonical"][0]) < 0.9
    assert not np.allclose(got["paraview_own"]["E"][0], got["canonical"]["E"][0], atol=1e-3)


def test_oblique_nrrd_in_paraview_gpu_rotated_cpu_ray_caster_not(pv_run):
    """What ParaView 5.11 does with the direction matrix of an oblique file (kept by the reader).

    Its GPU ray caster (the default) rotates the volume: seen by the cameras turned with it,
    the picture is the canonical one up to where the rays sample (SSIM 0.982 and 0.988
    measured).  Its CPU ray caster ("Ray Cast Only") ignores the matrix: it draws the volume
    in its own frame (origin + spacing x index), the canonical picture for unturned cameras.
    The engine always renders in the volume's frame, so the orbit views measure the same.
    """
    got, images, _tmp = pv_run
    for k in range(len(VIEWS)):
        assert _ssim(images["oblique"][k], images["canonical"][k]) >= 0.97, k
        assert _ssim(images["oblique_cpu"][k], images["canonical_cpu"][k]) >= 0.99, k
        np.testing.assert_allclose(got["oblique"]["E"][k], got["canonical"]["E"][k], atol=1e-6)
    # the turned cameras do see something else in the canonical volume (the test can fail)
    assert _ssim(images["canonical_turned"][0], images["canonical"][0]) < 0.95


def test_dicom_file_opens_its_series_in_patient_order(pv_run):
    """One file of a series: the reader reads the series (pydicom in ParaView's Python)."""
    got, _images, tmp = pv_run
    ref = load_volume(tmp / "study")  # the venv's reader: sorted by position, in HU
    rec = got["dicom"]
    assert rec["dims"] == [128, 128, 3]
    assert rec["origin"] == pytest.approx(ref.origin)
    assert ref.origin[2] == 0.0
    assert rec["sum"] == int(ref.data.astype(np.int64).sum())
    assert rec["first"] == int(ref.data[0, 0, 0])


@pytest.mark.parametrize("key", sorted(JPEG_FILES))
def test_jpeg_compressed_dicom_series_decodes_in_paraview_as_pydicom_reports(pv_run, key):
    """pvpython (numpy 1.24) decodes JPEG series with the pylibjpeg plug-ins of ``.pvdeps``:
    every voxel is the HU value pydicom gives (its ``apply_rescale`` on the decoded pixels)."""
    import hashlib

    import pydicom
    from pydicom.data import get_testdata_file
    from pydicom.pixels import apply_rescale

    got, _images, tmp = pv_run
    ds = pydicom.dcmread(tmp / key / "s0.dcm")
    assert "JPEG" in ds.file_meta.TransferSyntaxUID.name
    hu = apply_rescale(ds.pixel_array, ds)
    original = pydicom.dcmread(get_testdata_file(JPEG_FILES[key])).pixel_array
    np.testing.assert_array_equal(hu, original.astype(np.float64) - 1024)  # HU, not raw
    expected = np.stack([hu] * 3)  # the same image at z = 0, 2, 4
    rec = got[key]
    assert "error" not in rec, rec["error"]
    assert rec["dims"] == [int(ds.Columns), int(ds.Rows), 3]
    assert rec["origin"] == pytest.approx([0.0, 0.0, 0.0])
    assert rec["first"] == expected[0, 0, 0]
    assert rec["sum"] == int(expected.sum())
    assert rec["sha1"] == hashlib.sha1(expected.astype("<f8").tobytes()).hexdigest()
