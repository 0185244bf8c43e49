"""The ParaView plugin and the pvbatch script, run in ParaView's own pvpython/pvbatch.

Every test starts ParaView in a subprocess with the environment of ``dvr-perception pvbatch``
(``paraview_env``) and compares what ParaView computes with the library in this venv.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from dvr_perception._files import read_png
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import classify_structures, curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import load_spec
from dvr_perception.volume import load_volume
from tests.plugin.conftest import CROSS_ENV_ABS, assert_no_vtk_messages

REPO = Path(__file__).resolve().parents[2]
PLUGIN = REPO / "dvr_perception" / "paraview" / "dvr_perception_plugin.py"
MARK = "@@RESULT@@ "  # the line the pvpython scripts print their JSON result on
SIZE = 40
VIEW = (30.0, 20.0, 1.2)
SPEC = REPO / "state_files" / "neghip.json"

PRELUDE = f"""
import json, sys
from paraview.simple import *
LoadPlugin({str(PLUGIN)!r}, ns=globals())
def emit(obj):
    print({MARK!r} + json.dumps(obj), flush=True)
"""


@pytest.fixture(scope="module")
def neghip(shared_data):
    return shared_data / "neghip.nhdr"


@pytest.fixture(scope="module")
def library(neghip):
    """The library's numbers for neghip, its preset spec, VIEW and SIZE x SIZE."""
    vol, spec = load_volume(neghip), load_spec(SPEC)
    az, el, zoom = VIEW
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE, height=SIZE)
    curv, boundary = curvature_volume(vol, spec, sigma=1.0)
    result = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    return {
        "E_v": visibility(result, spec).E_v,
        "E_s": shape(result, spec).E_s,
        "E_t": transparency(result, spec).E_t,
        "ids": classify_structures(vol, spec).reshape(-1),
        "boundary": boundary.reshape(-1),
        "curvature": curv.reshape(-1),
        "alpha": np.asarray(result.accumulated),
    }


def test_plugin_loads_with_its_filters_and_properties(paraview, tmp_path):
    code = (
        PRELUDE
        + """
out = {}
src = Wavelet()
src.UpdatePipeline()  # the array-list domain needs the input's data information
for name in ("StructuralLayers", "PerceptionMeasures"):
    f = globals()[name](Input=src)
    hints = f.SMProxy.GetHints()
    menu = hints.FindNestedElementByName("ShowInMenu") if hints else None
    props = {}
    for p in f.ListProperties():
        prop = f.GetProperty(p)
        rng = prop.SMProperty.FindDomain("vtkSMDoubleRangeDomain") or \\
            prop.SMProperty.FindDomain("vtkSMIntRangeDomain")
        value = f.GetPropertyValue(p)
        value = value.GetData() if hasattr(value, "GetData") else value
        value = value[0] if isinstance(value, list) and len(value) == 1 else value
        props[p] = {
            "value": value if isinstance(value, (int, float, str, type(None))) else str(value),
            "range": [rng.GetMinimum(0), rng.GetMaximum(0)] if rng else None,
            "files": bool(prop.SMProperty.FindDomain("vtkSMFileListDomain")),
        }
    out[name] = {"label": f.SMProxy.GetXMLLabel(),
                 "menu": menu.GetAttribute("category") if menu else None, "props": props}
emit(out)
"""
    )
    got = paraview.result(paraview.run(code, tmp_path))
    sl, pm = got["StructuralLayers"], got["PerceptionMeasures"]
    assert (sl["label"], pm["label"]) == ("Structural Layers", "Perception Measures")
    assert sl["menu"] == pm["menu"] == "DVR Perception"
    common = {"Input", "ScalarArray", "SpecFile", "SpecJSON", "Sigma"}
    assert common <= set(sl["props"])
    assert common <= set(pm["props"])
    view = {"CameraJSON", "UseSpecView", "Azimuth", "Elevation", "Zoom", "Width", "Height"}
    assert view <= set(pm["props"])
    assert not view & set(sl["props"])
    p = pm["props"]
    assert p["SpecFile"]["files"]
    assert sl["props"]["SpecFile"]["files"]
    assert p["ScalarArray"]["value"] == "RTData"  # the array-list domain picked the input's array
    assert p["Sigma"]["value"] == 1.0
    assert p["Sigma"]["range"][0] > 0
    assert (p["Width"]["value"], p["Height"]["value"], p["UseSpecView"]["value"]) == (512, 512, 1)
    assert p["Width"]["range"][0] >= 1
    assert p["Azimuth"]["range"] == [-180.0, 180.0]
    assert p["Zoom"]["value"] == 1.0
    assert p["Zoom"]["range"][0] > 0


def test_plugin_path_autoloads_with_pvsite(paraview, tmp_path):
    env = dict(paraview.env, PV_PLUGIN_PATH=str(PLUGIN.parent))
    code = f"""
from paraview.simple import *
names = ("PerceptionMeasures", "StructuralLayers")
print({MARK!r} + str(sorted(n for n in names if n in globals())))
"""
    proc = paraview.run(code, tmp_path, env=env)
    assert proc.returncode == 0, proc.stdout
    assert_no_vtk_messages(proc.stdout)
    assert f"{MARK}['PerceptionMeasures', 'StructuralLayers']" in proc.stdout


def test_filters_in_paraview_match_the_library(paraview, tmp_path, neghip, library):
    az, el, zoom = VIEW
    code = (
        PRELUDE
        + f"""
from vtkmodules.util.numpy_support import vtk_to_numpy
reader = OpenDataFile({str(neghip)!r})
layers = StructuralLayers(Input=reader, SpecFile={str(SPEC)!r})
layers.UpdatePipeline()
vol = servermanager.Fetch(layers)
pd = vol.GetPointData()
np_ = {{n: vtk_to_numpy(pd.GetArray(n)).tolist() for n in ("structure_id", "boundary")}}
curv = vtk_to_numpy(pd.GetArray("curvature")).tolist()
pm = PerceptionMeasures(Input=reader, SpecFile={str(SPEC)!r}, UseSpecView=0, Azimuth={az},
                        Elevation={el}, Zoom={zoom}, Width={SIZE}, Height={SIZE})
progress = []
algo = pm.GetClientSideObject()
algo.AddObserver("ProgressEvent", lambda o, e: progress.append(o.GetProgress()))
pm.UpdatePipeline()
img = servermanager.Fetch(pm)
fd = img.GetFieldData()
alpha = vtk_to_numpy(img.GetPointData().GetArray("rgba"))[:, 3]
emit({{"E": {{k: fd.GetArray(k).GetValue(0) for k in ("E_v", "E_s", "E_t")}},
      "dims": list(img.GetDimensions()), "progress": progress, "curvature": curv,
      "alpha": alpha.tolist(), **np_}})
"""
    )
    got = paraview.result(paraview.run(code, tmp_path))
    # Structural Layers: ParaView's NRRD reader + the plugin give the library's classification
    np.testing.assert_array_equal(got["structure_id"], library["ids"])
    np.testing.assert_array_equal(got["boundary"], library["boundary"])
    np.testing.assert_allclose(got["curvature"], library["curvature"], atol=1e-6, rtol=0)
    # Perception Measures: the same three numbers as the library in this venv
    for k in ("E_v", "E_s", "E_t"):
        assert got["E"][k] == pytest.approx(library[k], abs=CROSS_ENV_ABS), k
    assert got["dims"] == [SIZE, SIZE, 1]
    engine_alpha = library["alpha"][::-1].reshape(-1)  # VTK rows start at the bottom
    np.testing.assert_allclose(got["alpha"], engine_alpha, atol=1e-6)
    # progress is reported through VTK progress events: increasing, with steps, ending at 1
    prog = got["progress"]
    assert prog[-1] == 1.0
    assert len({round(p, 3) for p in prog if 0 < p < 1}) >= 3
    assert all(b >= a for a, b in itertools.pairwise(prog))
    # and from inside the long steps (issue 19): the curvature volume (0.05 to 0.3) and the
    # ray analysis (0.3 to 0.7) each move the bar more than once
    assert len({round(p, 4) for p in prog if 0.05 < p < 0.3}) >= 2, prog
    assert len({round(p, 4) for p in prog if 0.3 < p < 0.7}) >= 2, prog


def test_batch_script_writes_rendering_measure_images_and_json(
    paraview, tmp_path, neghip, library, capsys
):
    from dvr_perception.cli import main

    out = tmp_path / "pv_out"
    view = ",".join(str(v) for v in VIEW)
    argv = ["pvbatch", str(neghip), "--structures", str(SPEC), f"--view={view}", "-v"]
    assert main([*argv, "--size", str(SIZE), "--out", str(out)]) == 0
    assert_no_vtk_messages(capsys.readouterr().err)  # -v: pvbatch's own output on stderr
    result = json.loads((out / "result.json").read_text())
    for k in ("E_v", "E_s", "E_t"):
        assert result[k] == pytest.approx(library[k], abs=CROSS_ENV_ABS), k
    assert set(result["structures"]) == {"diffuse lobes", "inner lobes", "peaks"}
    names = ("screenshot", "image", "visibility_deviation", "shape_deviation")
    images = {n: read_png(out / f"{n}.png") for n in (*names, "transparency_deviation")}
    assert all(im.shape[:2] == (SIZE, SIZE) for im in images.values())
    assert set(result["files"]) == {f"{n}.png" for n in images} | {"result.json"}
    # ParaView's own rendering covers about the pixels the engine's rays hit
    shot = images["screenshot"][..., :3].max(axis=-1) > 8
    hit = library["alpha"] > 0.03
    overlap = (shot & hit).sum() / max(1, (shot | hit).sum())
    assert hit.sum() > 50
    assert overlap > 0.7
    # the deviation maps are colour-mapped (not blank) and black where no ray hit anything
    dev = images["visibility_deviation"][..., :3]
    assert dev[library["alpha"] > 0.03].max() > 30
    assert dev[library["alpha"] == 0].max() == 0


def test_batch_script_measures_a_slicer_segmentation(paraview, tmp_path):
    """``pvbatch --structures X.seg.nrrd``: the segments are the structures (no screenshot)."""
    from dvr_perception.cli import main
    from dvr_perception.structures.slicer import write_segmentation
    from dvr_perception.volume import Volume, save_volume

    labels = np.zeros((20, 20, 20), np.uint8)
    labels[3:17, 3:17, 3:17] = 2
    labels[7:13, 7:13, 7:13] = 9
    save_volume(Volume((labels * 10).astype(np.int16), origin=(1, 2, 3)), tmp_path / "ct.nrrd")
    segments = [
        {"name": "Kidney", "color": (0.8, 0.3, 0.3), "label": 2},
        {"name": "Stone", "color": (1.0, 1.0, 0.2), "label": 9},
    ]
    write_segmentation(tmp_path / "s.seg.nrrd", labels, segments, origin=(1, 2, 3))
    out = tmp_path / "pv_seg"
    argv = ["pvbatch", str(tmp_path / "ct.nrrd"), "--structures", str(tmp_path / "s.seg.nrrd")]
    assert main([*argv, "--size", "24", "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text(encoding="utf-8"))
    assert list(result["structures"]) == ["Kidney", "Stone"]
    assert result["E_v"] > 0
    assert "screenshot.png" not in result["files"]


BAD_INPUTS = f"""
reader = OpenDataFile(sys.argv[1])
spec = {str(SPEC)!r}
def case(name, **kw):
    sys.stderr.write(f"@@CASE {{name}}\\n"); sys.stderr.flush()
    params = dict(Width=32, Height=32)
    params.update(kw)
    f = PerceptionMeasures(**params)
    f.UpdatePipeline()
    ok = servermanager.Fetch(f).GetFieldData().GetArray("E_v") is not None
    sys.stderr.write(f"@@END {{name}} ok={{ok}}\\n"); sys.stderr.flush()
    return f
case("polydata", Input=Sphere(), SpecFile=spec)
case("missing_spec", Input=reader, SpecFile="/no/such/dir/spec.json")
f = case("sigma", Input=reader, SpecFile=spec, Sigma=-2.0)
case("width", Input=reader, SpecFile=spec, Width=5)  # documented range 16-4096
case("camera", Input=reader, SpecFile=spec, CameraJSON="{{not json")
sys.stderr.write("@@CASE fixed\\n")
f.Sigma = 1.0
f.UpdatePipeline()
ok = servermanager.Fetch(f).GetFieldData().GetArray("E_v") is not None
sys.stderr.write(f"@@END fixed ok={{ok}}\\n@@SURVIVED\\n")
"""


def test_bad_input_is_an_error_message_in_paraview_not_a_crash(paraview, tmp_path, neghip):
    cases = paraview.cases(PRELUDE + BAD_INPUTS, tmp_path, neghip)
    expected = {
        "polydata": "is of type vtkPolyData, but a vtkImageData is required",
        "missing_spec": "/no/such/dir/spec.json",
        "sigma": "Perception Measures: Sigma: expected a number in [0.1, 10], got -2.0",
        "width": "Perception Measures: Width: expected an integer in [16, 4096], got 5",
        "camera": "camera_json: not valid JSON",
    }
    paraview.assert_errors(cases, expected)
    assert "not found" in cases["missing_spec"]
    assert "@@END fixed ok=True" in cases["fixed"], cases["fixed"]


def test_pvbatch_reports_a_bad_spec_from_inside_paraview_in_one_line(
    paraview, tmp_path, neghip, capsys
):
    from dvr_perception.cli import main

    bad = tmp_path / "bad_spec.json"
    bad.write_text('{"version": 1, "structures": "none"}')
    assert main(["pvbatch", str(neghip), "--structures", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("dvr-perception: error: ")
    assert "bad_spec.json" in err[0]
    # ParaView wrote into a staging folder that is gone again: --out holds what it held
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_spec.json"]


def test_pvbatch_into_a_folder_another_run_writes_is_refused(paraview, tmp_path, neghip, capsys):
    from dvr_perception._files import output_folder
    from dvr_perception.cli import main

    out = tmp_path / "out"
    with output_folder(out) as staged:  # another run holds the folder's lock
        (staged.path / "theirs.txt").write_text("x")
        assert main(["pvbatch", str(neghip), "--structures", str(SPEC), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        assert "another dvr-perception run" in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["theirs.txt"]
