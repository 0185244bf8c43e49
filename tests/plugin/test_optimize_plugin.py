"""The plugin's Optimize Transfer Function filter, ``apply_result.py`` and ``batch_optimize.py``.

Run in ParaView's own pvpython/pvbatch (environment of ``dvr-perception pvbatch``, a private
Xvfb when there is no display) at small sizes with one iteration per stage.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dvr_perception._files import read_png
from dvr_perception.cli.pvbatch import virtual_display
from dvr_perception.export.vtk import GPU_TABLE_SAMPLES, to_vtk_transfer_functions
from dvr_perception.structures.io import spec_from_dict
from tests.plugin.conftest import assert_no_vtk_messages

REPO = Path(__file__).resolve().parents[2]
PLUGIN_DIR = REPO / "dvr_perception" / "paraview"
MARK = "@@RESULT@@ "  # must match conftest.MARK
SIZE = 40
VIEW = (30.0, 20.0, 1.2)
SPEC = REPO / "state_files" / "neghip.json"


@pytest.fixture(scope="module")
def neghip(shared_data):
    return shared_data / "neghip.nhdr"


def _with_display(paraview):
    """A context manager yielding the ParaView environment with an X display."""
    from contextlib import contextmanager

    @contextmanager
    def cm():
        with virtual_display() as display:
            yield dict(paraview.env, DISPLAY=display)

    return cm()


def _nodes(fn, node_size):
    """Flat ``[x, v..]`` node list of a VTK transfer function (4 values of each node)."""
    out, node = [], [0.0] * node_size
    for i in range(fn.GetSize()):
        fn.GetNodeValue(i, node)
        out += node[:4]
    return out


def test_optimize_filter_runs_and_apply_optimized_sets_the_luts(paraview, tmp_path, neghip):
    az, el, zoom = VIEW
    preset = tmp_path / "preset.json"
    code = f"""
import json, sys
sys.path.insert(0, {str(PLUGIN_DIR)!r})
from paraview.simple import *
LoadPlugin({str(PLUGIN_DIR / "dvr_perception_plugin.py")!r}, ns=globals())
from apply_result import apply_optimized
reader = OpenDataFile({str(neghip)!r})
opt = OptimizeTransferFunction(Input=reader)
hints = opt.SMProxy.GetHints()
menu = hints.FindNestedElementByName("ShowInMenu") if hints else None
defaults = {{}}
for p in ("Stages", "Weights", "Seed", "MaxIterations", "Resolution", "Width", "UseSpecView",
          "Region"):
    v = opt.GetPropertyValue(p)
    defaults[p] = list(v) if not isinstance(v, (str, int, float)) else v
rng = opt.GetProperty("MaxIterations").SMProperty.FindDomain("vtkSMIntRangeDomain")
opt.SpecFile = {str(SPEC)!r}
opt.UseSpecView, opt.Azimuth, opt.Elevation, opt.Zoom = 0, {az}, {el}, {zoom}
opt.Width, opt.Height, opt.MaxIterations = {SIZE}, {SIZE}, 1
opt.UpdatePipeline()
fd = servermanager.Fetch(opt).GetFieldData()
view = CreateView("RenderView")
display = Show(reader, view)
display.SetRepresentationType("Volume")
ColorBy(display, ("POINTS", reader.PointData.keys()[0]))
apply_optimized(opt, display, preset_path={str(preset)!r})
imported = ImportPresets({str(preset)!r})  # what Choose Preset > Import does
lut2 = GetColorTransferFunction("imported")
lut2.ApplyPreset("preset", False)
pwf2 = GetOpacityTransferFunction("imported")
pwf2.ApplyPreset("preset", False)  # the dialog's "use preset opacity"
print({MARK!r} + json.dumps({{
    "label": opt.SMProxy.GetXMLLabel(),
    "menu": menu.GetAttribute("category") if menu else None,
    "defaults": defaults,
    "max_iter_range": [rng.GetMinimum(0), rng.GetMaximum(0)] if rng else None,
    "initial_E": fd.GetArray("initial_E").GetValue(0),
    "E": fd.GetArray("E").GetValue(0),
    "dims": list(servermanager.Fetch(opt).GetDimensions()),
    "spec": fd.GetAbstractArray("optimized_spec_json").GetValue(0),
    "rgb": list(display.LookupTable.RGBPoints),
    "points": list(display.ScalarOpacityFunction.Points),
    "material": [display.Ambient, display.Diffuse, display.Specular, display.SpecularPower],
    "range": list(reader.PointData[reader.PointData.keys()[0]].GetRange()),
    "imported": bool(imported),
    "imported_rgb": list(lut2.RGBPoints),
    "imported_points": list(pwf2.Points),
}}), flush=True)
"""
    with _with_display(paraview) as env:
        got = paraview.result(paraview.run(code, tmp_path, env=env))
    assert got["label"] == "Optimize Transfer Function"
    assert got["menu"] == "DVR Perception"
    d = got["defaults"]
    assert d["Stages"] == "opacity,lighting,colour"
    assert d["Weights"] == [1.0, 1.0, 1.0]
    assert (d["Seed"], d["MaxIterations"], d["Resolution"], d["UseSpecView"]) == (0, 10, 0, 1)
    assert d["Region"] == ""  # whole image
    assert got["max_iter_range"][0] == 1
    assert got["dims"] == [SIZE, SIZE, 1]
    # the optimiser never returns something worse than its start
    assert got["E"] <= got["initial_E"] + 1e-9
    # apply_optimized: ParaView's LUT/opacity nodes are the optimised spec's VTK functions, with
    # the nodes one GPU table entry (1/4096 of the data range) apart at least
    spec = spec_from_dict(json.loads(got["spec"]))
    ctf, otf = to_vtk_transfer_functions(spec, samples=GPU_TABLE_SAMPLES, scalar_range=got["range"])
    for nodes in (got["rgb"], got["points"]):
        xs = np.asarray(nodes).reshape(-1, 4)[:, 0]
        assert np.diff(xs).min() >= (got["range"][1] - got["range"][0]) / GPU_TABLE_SAMPLES - 1e-9
    np.testing.assert_allclose(got["rgb"], _nodes(ctf, 6), atol=1e-9)
    np.testing.assert_allclose(got["points"], _nodes(otf, 4), atol=1e-9)
    # a few values through the piecewise-linear opacity (midpoint 0.5, sharpness 0)
    ops = [otf.GetValue(x) for x in np.linspace(0, 255, 7)]
    pts = np.asarray(got["points"]).reshape(-1, 4)
    np.testing.assert_allclose(ops, np.interp(np.linspace(0, 255, 7), pts[:, 0], pts[:, 1]))
    top = max(spec.structures, key=lambda s: s.importance).lighting
    expected = [top.ambient, top.diffuse, top.specular, top.specular_power]
    assert got["material"] == pytest.approx(expected)
    exported = json.loads(preset.read_text())[0]
    assert exported["RGBPoints"] == pytest.approx(got["rgb"])
    assert exported["Points"] == pytest.approx(got["points"])
    # the preset imports into ParaView (ImportPresets, as Choose Preset > Import) and applies
    assert got["imported"]
    assert got["imported_rgb"] == pytest.approx(got["rgb"])
    assert got["imported_points"] == pytest.approx(got["points"])


def test_batch_optimize_writes_before_after_screenshots_and_json(paraview, tmp_path, neghip):
    out = tmp_path / "opt_out"
    view = ",".join(str(v) for v in VIEW)
    argv = [str(neghip), "--structures", str(SPEC), f"--view={view}", "--size", str(SIZE)]
    argv += ["--max-iter", "1", "--out", str(out)]
    with _with_display(paraview) as env:
        proc = paraview.call(
            [str(paraview.pvbatch), str(PLUGIN_DIR / "batch_optimize.py"), *argv],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
    assert proc.returncode == 0, proc.stderr
    assert_no_vtk_messages(proc.stdout + proc.stderr)
    result = json.loads((out / "result.json").read_text())
    assert set(result["files"]) == {
        "before.png",
        "after.png",
        "image.png",
        "visibility_deviation.png",
        "shape_deviation.png",
        "transparency_deviation.png",
        "optimized_spec.json",
        "optimized_preset.json",
        "result.json",
    }
    saved = json.loads((out / "optimized_spec.json").read_text())
    assert saved == result["optimized_spec"]
    for key in ("E_v", "E_s", "E_t", "E"):
        assert np.isfinite(result["initial"][key])
        assert np.isfinite(result["final"][key])
    assert result["final"]["E"] <= result["initial"]["E"] + 1e-9
    assert {s["name"] for s in result["optimized_spec"]["structures"]} == {
        "diffuse lobes",
        "inner lobes",
        "peaks",
    }
    assert [line.split(":")[0] for line in result["why"]] == ["diffuse lobes", "inner lobes",
                                                             "peaks"]  # fmt: skip
    assert all("share of the picture" in line for line in result["why"])
    before, after = read_png(out / "before.png"), read_png(out / "after.png")
    assert before.shape[:2] == after.shape[:2] == (SIZE, SIZE)
    assert before[..., :3].max() > 8  # not blank
    assert after[..., :3].max() > 8


BAD_OPTIMIZER_INPUTS = f"""
import sys
from paraview.simple import *
LoadPlugin({str(PLUGIN_DIR / "dvr_perception_plugin.py")!r}, ns=globals())
reader = OpenDataFile(sys.argv[1])
spec = {str(SPEC)!r}
def case(name, **kw):
    sys.stderr.write(f"@@CASE {{name}}\\n"); sys.stderr.flush()
    params = dict(Width=16, Height=16, MaxIterations=1)
    params.update(kw)
    f = OptimizeTransferFunction(**params)
    f.UpdatePipeline()
    ok = servermanager.Fetch(f).GetFieldData().GetArray("E") is not None
    sys.stderr.write(f"@@END {{name}} ok={{ok}}\\n"); sys.stderr.flush()
case("polydata", Input=Sphere(), SpecFile=spec)
case("missing_spec", Input=reader, SpecFile="/no/such/dir/opt_spec.json")
case("weights", Input=reader, SpecFile=spec, Weights=[0.0, 0.0, 0.0])
case("stages", Input=reader, SpecFile=spec, Stages="opacity,bogus")
case("resolution", Input=reader, SpecFile=spec, Resolution=4)
case("max_iter", Input=reader, SpecFile=spec, MaxIterations=0)
case("zoom", Input=reader, SpecFile=spec, Zoom=50.0)
case("region", Input=reader, SpecFile=spec, Region="rect,1,2")
case("region_outside", Input=reader, SpecFile=spec, Region="circle,100,100,3")
sys.stderr.write("@@SURVIVED\\n")
"""


def test_optimize_filter_reports_bad_input_without_crashing(paraview, tmp_path, neghip):
    cases = paraview.cases(BAD_OPTIMIZER_INPUTS, tmp_path, neghip)
    expected = {
        "polydata": "is of type vtkPolyData, but a vtkImageData is required",
        "missing_spec": "/no/such/dir/opt_spec.json",
        "weights": "weights: expected three numbers (w_v, w_s, w_t) >= 0, not all zero",
        "stages": "stages: unknown or missing stage(s) ['bogus']",
        "resolution": "resolution: expected 0 (default) or an integer >= 8, got 4",
        "max_iter": "Optimize Transfer Function: MaxIterations: expected an integer in [1, 1000]",
        "zoom": "Optimize Transfer Function: Zoom: expected a number in [0.1, 10], got 50.0",
        "region": "region: expected '' (whole image), 'rect,x0,y0,x1,y1' or 'circle,cx,cy,r'",
        "region_outside": "covers no pixel of the 16 x 16 image",
    }
    paraview.assert_errors(cases, expected)
