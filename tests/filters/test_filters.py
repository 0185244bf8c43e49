"""The VTK filters: outputs match the library, errors are reported through VTK, no crash."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from vtkmodules.vtkCommonDataModel import vtkPolyData

from dvr_perception._vtk import vtk_to_numpy, vtkLogger, vtkOutputWindow, vtkStringOutputWindow
from dvr_perception.filters import PerceptionMeasures, StructuralLayers
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.measures.luminance import LUMA_WEIGHTS
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import classify_structures, curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom
from dvr_perception.structures.io import spec_to_dict
from dvr_perception.structures.spec import Lighting
from dvr_perception.volume import from_vtk_image, to_vtk_image

SIZE = 48


@pytest.fixture(scope="module")
def phantom():
    vol, spec = make_phantom(size=SIZE)
    return vol, spec, to_vtk_image(vol)


@pytest.fixture(scope="module")
def spec_json(phantom):
    return json.dumps(spec_to_dict(phantom[1]))


@pytest.fixture(scope="module")
def library(phantom):
    """The library pipeline run directly on the filter's input (48 x 48 default view)."""
    _, spec, image = phantom
    vol = from_vtk_image(image)
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE, height=SIZE)
    res = _retry(lambda: analyze(vol, spec, cam, curvature=curv))  # as the filter: no cache
    return res, visibility(res, spec), shape(res, spec), transparency(res, spec)


def _retry(call, attempts: int = 3):
    for i in range(attempts):
        try:
            return call()
        except (ImportError, AttributeError, RuntimeError):  # kernels edited concurrently
            if i == attempts - 1:
                raise
    return None


def _point(image, name):
    arr = image.GetPointData().GetAbstractArray(name)
    assert arr is not None, f"missing point array {name}"
    return vtk_to_numpy(arr)


def _field(image, name):
    arr = image.GetFieldData().GetAbstractArray(name)
    assert arr is not None, f"missing field array {name}"
    return arr


def _update_capturing(algorithm):
    """Update ``algorithm``; return (success, error messages) seen by observers, quietly."""
    messages: list[str] = []

    def on_error(_obj, _event, data=None):
        messages.append(str(data))

    on_error.CallDataType = "string0"
    targets = [algorithm, algorithm.GetExecutive()]
    tags = [(t, t.AddObserver("ErrorEvent", on_error)) for t in targets]
    previous = vtkOutputWindow.GetInstance()
    capture = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(capture)
    verbosity = vtkLogger.GetCurrentVerbosityCutoff()
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    try:
        ok = algorithm.Update()
    finally:
        vtkLogger.SetStderrVerbosity(verbosity)
        vtkOutputWindow.SetInstance(previous)
        for t, tag in tags:
            t.RemoveObserver(tag)
    return bool(ok), messages


# -- StructuralLayers ----------------------------------------------------------------------------
def test_structural_layers_matches_library(phantom, spec_json):
    _, spec, image = phantom
    f = StructuralLayers()
    f.spec_json = spec_json
    f.SetInputDataObject(image)
    ok, errors = _update_capturing(f)
    assert ok, errors
    assert f.error_message == ""
    out = f.GetOutputDataObject(0)
    assert out.GetDimensions() == (SIZE, SIZE, SIZE)
    assert out.GetSpacing() == image.GetSpacing()
    assert out.GetOrigin() == image.GetOrigin()
    n = SIZE**3
    vol = from_vtk_image(image)
    ids = _point(out, "structure_id")
    boundary = _point(out, "boundary")
    curvature = _point(out, "curvature")
    assert ids.shape == boundary.shape == curvature.shape == (n,)
    assert (ids.dtype, boundary.dtype, curvature.dtype) == (np.int16, np.uint8, np.float32)
    np.testing.assert_array_equal(ids, classify_structures(vol, spec).reshape(-1))
    curv, bnd = curvature_volume(vol, spec, sigma=1.0)
    np.testing.assert_array_equal(boundary, bnd.reshape(-1).astype(np.uint8))
    np.testing.assert_array_equal(curvature, curv.reshape(-1))
    np.testing.assert_array_equal(_point(out, "scalars"), vol.data.reshape(-1))
    assert out.GetPointData().GetScalars().GetName() == "scalars"


def test_structural_layers_spec_file_and_sigma(phantom, spec_json, tmp_path):
    _, spec, image = phantom
    path = tmp_path / "spec.json"
    path.write_text(spec_json, encoding="utf-8")
    f = StructuralLayers()
    f.SetSpecFile(str(path))
    f.SetSigma(2.0)
    assert f.sigma == 2.0
    f.SetInputDataObject(image)
    ok, errors = _update_capturing(f)
    assert ok, errors
    curv, _ = curvature_volume(from_vtk_image(image), spec, sigma=2.0)
    np.testing.assert_array_equal(_point(f.GetOutputDataObject(0), "curvature"), curv.ravel())


# -- PerceptionMeasures --------------------------------------------------------------------------
def test_perception_measures_matches_library(phantom, spec_json, library):
    res, vis, shp, trn = library
    f = PerceptionMeasures()
    f.spec_json = spec_json
    f.width, f.height = SIZE, SIZE
    f.SetInputDataObject(phantom[2])
    ok, errors = _retry(lambda: _update_capturing(f))
    assert ok, errors
    out = f.GetOutputDataObject(0)
    assert out.GetDimensions() == (SIZE, SIZE, 1)
    for name, value in (("E_v", vis.E_v), ("E_s", shp.E_s), ("E_t", trn.E_t)):
        arr = _field(out, name)
        assert arr.GetNumberOfTuples() == 1
        assert arr.GetValue(0) == pytest.approx(value, abs=1e-9)
    # VTK rows are bottom-up: flip back to the engine's top-row-first order
    rgba = _point(out, "rgba").reshape(SIZE, SIZE, 4)[::-1]
    np.testing.assert_array_equal(rgba, res.rgba)
    assert out.GetPointData().GetScalars().GetName() == "rgba"
    for name, expected in (
        ("visibility_deviation", vis.deviation),
        ("shape_deviation", shp.deviation),
        ("transparency_deviation", trn.deviation),
        ("layer_set", trn.layer_set),
        ("region_id", trn.region_id),
    ):
        got = _point(out, name).reshape(SIZE, SIZE)[::-1]
        np.testing.assert_array_equal(got, expected)
    assert _point(out, "layer_set").dtype == np.uint32
    assert _point(out, "region_id").dtype == np.int32
    assert _point(out, "luminance").shape == (SIZE * SIZE,)

    names_arr = _field(out, "structure_names")
    names = [names_arr.GetValue(i) for i in range(names_arr.GetNumberOfValues())]
    assert tuple(names) == res.names
    for key, source in (
        ("visible_share", vis.per_structure),
        ("target_share", vis.per_structure),
        ("assigned_share", vis.per_structure),
        ("perceived_transparency", trn.per_structure),
        ("expected_opacity", trn.per_structure),
    ):
        arr = _field(out, key)
        assert arr.GetNumberOfTuples() == len(names)
        for i, n in enumerate(names):
            want = source[n][key]
            if want is None:
                assert math.isnan(arr.GetValue(i))
            else:
                assert arr.GetValue(i) == pytest.approx(want, abs=1e-12)


def test_perception_measures_camera_json_non_square(phantom, spec_json):
    vol, spec, image = phantom
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=15, width=40, height=24)
    f = PerceptionMeasures()
    f.spec_json = spec_json
    f.camera_json = json.dumps(cam.to_dict())
    f.SetInputDataObject(image)
    ok, errors = _retry(lambda: _update_capturing(f))
    assert ok, errors
    out = f.GetOutputDataObject(0)
    assert out.GetDimensions() == (40, 24, 1)
    res = _retry(
        lambda: analyze(
            from_vtk_image(image),
            spec,
            cam,
            curvature=curvature_volume(from_vtk_image(image), spec)[0],
            build_cache=False,
        )
    )
    np.testing.assert_array_equal(_point(out, "rgba").reshape(24, 40, 4)[::-1], res.rgba)


# -- errors ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", [StructuralLayers, PerceptionMeasures])
def test_missing_spec_file_is_reported(cls, phantom, tmp_path):
    missing = tmp_path / "nope.json"
    f = cls()
    f.spec_file = str(missing)
    f.SetInputDataObject(phantom[2])
    ok, errors = _update_capturing(f)
    assert not ok
    assert errors
    assert "spec file not found" in errors[0]
    assert str(missing) in errors[0]
    assert "spec file not found" in f.error_message
    assert f.GetOutputDataObject(0).GetNumberOfPoints() == 0


@pytest.mark.parametrize("cls", [StructuralLayers, PerceptionMeasures])
def test_malformed_spec_json_is_reported(cls, phantom, spec_json):
    f = cls()
    f.spec_json = '{"version": 1, "structures": [}'
    f.SetInputDataObject(phantom[2])
    ok, errors = _update_capturing(f)
    assert not ok
    assert "spec_json: not valid JSON" in errors[0]
    assert "line 1" in errors[0]
    # fixing the parameter makes the next update succeed
    f.spec_json = spec_json
    if isinstance(f, PerceptionMeasures):
        f.width = f.height = 16
    ok, errors = _retry(lambda: _update_capturing(f))
    assert ok, errors
    assert f.error_message == ""


def test_invalid_spec_content_names_the_field(phantom):
    f = StructuralLayers()
    f.spec_json = json.dumps(
        {"version": 1, "structures": [{"name": "a", "range": [0, 1], "importance": 1.5}]}
    )
    f.SetInputDataObject(phantom[2])
    ok, errors = _update_capturing(f)
    assert not ok
    assert errors[0].startswith("spec_json: structures[0]")


@pytest.mark.parametrize("cls", [StructuralLayers, PerceptionMeasures])
def test_no_spec_is_reported(cls, phantom):
    f = cls()
    f.SetInputDataObject(phantom[2])
    ok, errors = _update_capturing(f)
    assert not ok
    assert "no structure spec" in errors[0]


@pytest.mark.parametrize("cls", [StructuralLayers, PerceptionMeasures])
def test_polydata_input_is_reported(cls, spec_json):
    f = cls()
    f.spec_json = spec_json
    f.SetInputDataObject(vtkPolyData())
    ok, errors = _update_capturing(f)
    assert not ok
    assert any("vtkPolyData" in e and "vtkImageData is required" in e for e in errors), errors


def test_bad_camera_json_is_reported(phantom, spec_json):
    f = PerceptionMeasures()
    f.spec_json = spec_json
    f.camera_json = json.dumps({"position": [0, 0, 1], "fov": 30})
    f.SetInputDataObject(phantom[2])
    ok, errors = _update_capturing(f)
    assert not ok
    assert "camera_json: unknown camera field(s) ['fov']" in errors[0]


def test_parameters_validate_and_modify():
    f = PerceptionMeasures()
    before = f.GetMTime()
    f.SetView(30, 10)
    assert f.view == (30.0, 10.0, 1.0)
    assert f.GetMTime() > before
    before = f.GetMTime()
    f.view = (30, 10, 1)
    assert f.GetMTime() == before  # unchanged value: not modified
    with pytest.raises(ValueError, match="width: expected a positive integer"):
        f.width = 0
    with pytest.raises(ValueError, match="sigma: expected a positive number"):
        f.sigma = -1


def test_library_warnings_are_forwarded(phantom):
    f = StructuralLayers()
    f.spec_json = json.dumps(
        {
            "version": 1,
            "structures": [
                {"name": "x", "range": [300, 400], "importance": 0.5, "color": [1, 1, 1]}
            ],
        }
    )
    f.SetInputDataObject(phantom[2])
    warnings_seen: list[str] = []

    def on_warning(_obj, _event, data=None):
        warnings_seen.append(str(data))

    on_warning.CallDataType = "string0"
    f.AddObserver("WarningEvent", on_warning)
    ok, errors = _update_capturing(f)
    assert ok, errors
    assert any("holds no voxel" in w for w in warnings_seen), warnings_seen
    assert f.warning_messages == warnings_seen


def test_specular_highlights_are_not_reported_as_straight_alpha(phantom):
    # White structures, strong specular: the highlights carry more light than their opacity
    # (emission, as in VTK's Phong shading); the engine's image is premultiplied all the same,
    # so the filter must not warn "rgba_premultiplied: colour channels exceed their opacity".
    _, spec, image = phantom
    light = Lighting(ambient=0.5, diffuse=0.8, specular=1.0, specular_power=2.0)
    white = [replace(s, lighting=light, colour=(1.0, 1.0, 1.0)) for s in spec.structures]
    shiny = replace(spec, structures=tuple(white), rendering=replace(spec.rendering, shade=True))
    f = PerceptionMeasures()
    f.spec_json = json.dumps(spec_to_dict(shiny))
    f.width = f.height = 24
    f.SetInputDataObject(image)
    ok, errors = _update_capturing(f)
    assert ok, errors
    assert f.warning_messages == []
    out = f.GetOutputDataObject(0)
    rgba = _point(out, "rgba").astype(np.float64)
    assert (rgba[:, :3].max(axis=1) > rgba[:, 3] + 1e-3).sum() > 10  # there are highlights
    bg = float(np.dot(spec.background, LUMA_WEIGHTS))
    want = rgba[:, :3] @ np.asarray(LUMA_WEIGHTS) + (1 - rgba[:, 3]) * bg
    np.testing.assert_allclose(_point(out, "luminance"), want, atol=1e-6)
