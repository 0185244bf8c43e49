"""The TransferFunctionOptimizer filter: output like PerceptionMeasures, field data, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception._vtk import vtk_to_numpy, vtkOutputWindow, vtkStringOutputWindow
from dvr_perception.errors import DVRInputError
from dvr_perception.filters import TransferFunctionOptimizer
from dvr_perception.optimize import optimize
from dvr_perception.rays.camera import Camera
from dvr_perception.structures import make_phantom
from dvr_perception.structures.io import spec_from_dict, spec_to_dict
from dvr_perception.volume import from_vtk_image, to_vtk_image

SIZE = 32
STAGES = ("opacity", "lighting")
MAX_ITER = 2


@pytest.fixture(scope="module")
def phantom():
    vol, spec = make_phantom(size=SIZE)
    return vol, spec, to_vtk_image(vol)


@pytest.fixture(scope="module")
def filtered(phantom):
    _, spec, image = phantom
    f = TransferFunctionOptimizer()
    f.SetInputDataObject(image)
    f.spec_json = json.dumps(spec_to_dict(spec))
    f.width = f.height = SIZE
    f.SetStages(",".join(STAGES))
    f.SetWeights(1.0, 1.0, 0.5)
    f.seed = 3
    f.max_iter = MAX_ITER
    progress = []
    f.AddObserver("ProgressEvent", lambda obj, _evt: progress.append(obj.GetProgress()))
    f.Update()
    return f, f.GetOutputDataObject(0), progress


def _field(out, name):
    arr = out.GetFieldData().GetAbstractArray(name)
    assert arr is not None, f"missing field array {name}"
    if hasattr(arr, "GetValue") and arr.GetClassName() == "vtkStringArray":
        return [arr.GetValue(i) for i in range(arr.GetNumberOfValues())]
    return vtk_to_numpy(arr)


def test_output_image_and_field_data(filtered, phantom):
    f, out, progress = filtered
    assert f.error_message == ""
    assert out.GetDimensions() == (SIZE, SIZE, 1)
    pd = out.GetPointData()
    for name in ("rgba", "luminance", "visibility_deviation", "shape_deviation",
                 "transparency_deviation", "layer_set", "region_id"):  # fmt: skip
        assert pd.GetAbstractArray(name) is not None, name
    names = _field(out, "structure_names")
    spec = phantom[1]
    assert names == list(spec.names)
    k = len(names)
    for name in ("opacity", "ambient", "diffuse", "specular", "specular_power", "visible_share",
                 "target_share", "assigned_share", "perceived_transparency",
                 "expected_opacity"):  # fmt: skip
        assert _field(out, name).shape == (k,), name
    why = _field(out, "why")  # the optimiser's reason, one line per structure
    assert len(why) == k
    assert all(line.startswith(f"{n}: opacity") for n, line in zip(names, why, strict=True))
    assert all("share of the picture" in line for line in why)
    assert _field(out, "color").shape == (k, 3)
    assert _field(out, "light_direction").shape == (1, 3)
    opt = spec_from_dict(json.loads(_field(out, "optimized_spec_json")[0]))
    np.testing.assert_allclose(_field(out, "opacity"), [s.render_opacity for s in opt.structures])
    np.testing.assert_allclose(_field(out, "color"), [s.colour for s in opt.structures])
    assert max(progress) == pytest.approx(1.0)
    assert any(0.2 < p < 0.9 for p in progress)  # reported from the optimiser's callback
    # the curvature volume and the first analyses report from inside (issue 19)
    prep = progress[: next(i for i, p in enumerate(progress) if p >= 0.2)]
    assert len([p for p in prep if 0.0 < p < 0.2]) >= 3
    assert prep == sorted(prep)


def test_terms_equal_optimize(filtered, phantom):
    f, out, _ = filtered
    _, spec, image = phantom
    vol = from_vtk_image(image)
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE, height=SIZE)
    res = optimize(vol, spec, cam, stages=STAGES, weights=(1.0, 1.0, 0.5), seed=3,
                   max_iter=MAX_ITER)  # fmt: skip
    for term in ("E_v", "E_s", "E_t", "E"):
        assert _field(out, term)[0] == pytest.approx(res.final[term], abs=1e-6), term
        assert _field(out, f"initial_{term}")[0] == pytest.approx(res.initial[term], abs=1e-9)
    assert _field(out, "status")[0] == res.status
    assert spec_to_dict(f.result.spec) == spec_to_dict(res.spec)


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        (lambda f: f.SetWeights(0, 0, 0), "weights"),
        (lambda f: f.SetWeights(1, -1, 1), "weights"),
        (lambda f: f.SetStages("opacity,shine"), "stage"),
        (lambda f: setattr(f, "max_iter", 0), "max_iter"),
        (lambda f: setattr(f, "seed", -2), "seed"),
        (lambda f: setattr(f, "region", "rect,1,2,3"), "region"),
        (lambda f: setattr(f, "region", "square,1,2,3,4"), "region"),
        (lambda f: setattr(f, "region", "circle,1,nan,3"), "region"),
    ],
)
def test_bad_parameters_are_refused(setting, message):
    f = TransferFunctionOptimizer()
    with pytest.raises(DVRInputError, match=message):
        setting(f)  # a bad value is refused when set (the Parameter converters)


def test_bad_input_reported_through_vtk_no_crash(phantom):
    _, _spec, image = phantom
    window = vtkStringOutputWindow()
    old = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(window)
    try:
        f = TransferFunctionOptimizer()
        f.SetInputDataObject(image)
        f.width = f.height = 16
        f.max_iter = 1
        f.Update()  # no spec at all
        assert "no structure spec" in f.error_message
        f.spec_json = "{not json"
        f.Update()
        assert "spec_json" in f.error_message
        assert "spec_json" in window.GetOutput()
        assert f.GetOutputDataObject(0).GetNumberOfPoints() == 0
    finally:
        vtkOutputWindow.SetInstance(old)


def test_region_reaches_the_optimiser(monkeypatch, phantom):
    import dvr_perception.optimize as opt_mod

    _, spec, image = phantom
    seen = {}
    real = opt_mod.optimize

    def spy(*args, **kwargs):
        seen["region"] = kwargs.get("region")
        return real(*args, **kwargs)

    monkeypatch.setattr(opt_mod, "optimize", spy)
    f = TransferFunctionOptimizer()
    f.SetInputDataObject(image)
    f.spec_json = json.dumps(spec_to_dict(spec))
    f.width = f.height = 24
    f.max_iter = 1
    f.SetStages("opacity")
    results = []

    def keep(*args, **kwargs):
        results.append(spy(*args, **kwargs))
        return results[-1]

    monkeypatch.setattr(opt_mod, "optimize", keep)
    f.Update()
    assert f.GetOutputDataObject(0).GetFieldData().GetAbstractArray("lens_E") is None
    f.region = "rect, 4, 4, 16, 12"
    f.Update()
    assert f.error_message == ""
    assert seen["region"] == ("rect", 4.0, 4.0, 16.0, 12.0)
    # the lens's own terms beside the whole image's: what the optimiser minimised
    out, res = f.GetOutputDataObject(0), results[-1]
    assert _field(out, "lens_region") == ["rect,4,4,16,12"]
    for term in ("E_v", "E_s", "E_t", "E"):
        assert _field(out, f"lens_{term}")[0] == pytest.approx(res.final[term], abs=1e-12)
        assert _field(out, f"lens_initial_{term}")[0] == pytest.approx(res.initial[term])
        assert _field(out, f"initial_{term}")[0] == pytest.approx(res.initial["whole"][term])
    assert res.initial["E"] != pytest.approx(res.initial["whole"]["E"], abs=1e-6)
    window = vtkStringOutputWindow()
    old = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(window)
    try:
        f.region = "circle,100,100,3"  # outside the 24 x 24 output: refused when run
        f.Update()
    finally:
        vtkOutputWindow.SetInstance(old)
    assert "region" in f.error_message
    assert "covers no pixel" in window.GetOutput()
