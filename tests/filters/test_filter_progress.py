"""ParaView's progress bar moves inside the long steps (issue 19).

The filters hand the library a ``progress`` callback per step
(:meth:`~dvr_perception.filters._base.DVRFilterBase.progress_range`); here the VTK
``ProgressEvent`` values are recorded: several inside the curvature step (0.05 to 0.3) and the
ray step (0.3 to 0.7) of *Perception Measures*, whole and in bricks, the output unchanged; an
abort requested during the ray step stops the filter with one "cancelled" error.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from dvr_perception._vtk import vtk_to_numpy, vtkLogger, vtkOutputWindow, vtkStringOutputWindow
from dvr_perception.filters import PerceptionMeasures, StructuralLayers
from dvr_perception.rays import memory
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom
from dvr_perception.structures.io import spec_to_dict
from dvr_perception.volume import from_vtk_image, to_vtk_image

pytest.importorskip("numba")

SIZE = 48


@pytest.fixture
def small_memory(monkeypatch):
    """A plan that puts the 48^3 phantom in 8 bricks of 32 cells (as a large CT would go)."""
    real = memory.plan

    def bricked(*args, **kwargs):
        return real(*args, **{**kwargs, "brick": kwargs.get("brick") or (32, 32, 32)})

    monkeypatch.setattr(memory, "plan", bricked)
    memory.set_limit("8M")
    yield
    memory.set_limit(None)


@pytest.fixture(scope="module")
def phantom():
    vol, spec = make_phantom(size=SIZE)
    return spec, to_vtk_image(vol), json.dumps(spec_to_dict(spec))


def _run(f, abort_above=None):
    """Update ``f`` quietly; return (ok, errors, progress values)."""
    progress: list[float] = []
    errors: list[str] = []

    def on_progress(obj, _event):
        progress.append(obj.GetProgress())
        if abort_above is not None and progress[-1] > abort_above:
            obj.SetAbortExecute(1)

    def on_error(_obj, _event, data=None):
        errors.append(str(data))

    on_error.CallDataType = "string0"
    f.AddObserver("ProgressEvent", on_progress)
    f.AddObserver("ErrorEvent", on_error)
    previous = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(vtkStringOutputWindow())
    verbosity = vtkLogger.GetCurrentVerbosityCutoff()
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    try:
        ok = bool(f.Update())
    finally:
        vtkLogger.SetStderrVerbosity(verbosity)
        vtkOutputWindow.SetInstance(previous)
    return ok, errors, progress


def _inside(progress, lo, hi) -> int:
    return len({round(p, 4) for p in progress if lo < p < hi})


@pytest.mark.parametrize("bricked", [False, True])
def test_perception_measures_progress_moves_inside_curvature_and_rays(phantom, request, bricked):
    spec, image, spec_json = phantom
    if bricked:
        request.getfixturevalue("small_memory")
    f = PerceptionMeasures()
    f.spec_json = spec_json
    f.width = f.height = SIZE
    f.SetInputDataObject(image)
    ok, errors, progress = _run(f)
    assert ok, errors
    assert progress[-1] == 1.0
    assert all(b >= a for a, b in itertools.pairwise(progress)), progress
    assert _inside(progress, 0.05, 0.3) >= 3  # the curvature volume's z slices
    assert _inside(progress, 0.3, 0.7) >= (6 if bricked else 2)  # bricks / groups of tiles
    # the output is the library's analysis without a callback
    vol = from_vtk_image(image)
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE,
                           height=SIZE)  # fmt: skip
    res = analyze(vol, spec, cam, curvature=curvature_volume(vol, spec)[0], build_cache=False)
    assert res.stats.get("bricks", 0) == (8 if bricked else 0)
    rgba = vtk_to_numpy(f.GetOutputDataObject(0).GetPointData().GetArray("rgba"))
    np.testing.assert_array_equal(rgba.reshape(SIZE, SIZE, 4)[::-1], res.rgba)


def test_abort_during_the_ray_step_is_one_cancelled_error(phantom, small_memory):
    _, image, spec_json = phantom
    f = PerceptionMeasures()
    f.spec_json = spec_json
    f.width = f.height = SIZE
    f.SetInputDataObject(image)
    ok, errors, progress = _run(f, abort_above=0.35)
    assert not ok
    assert len(errors) == 1, errors
    assert errors[0] == "PerceptionMeasures: progress: cancelled (abort requested)"
    assert "Traceback" not in errors[0]
    assert all(p < 0.7 or p == 1.0 for p in progress)  # stopped inside the ray step
    assert any(0.35 < p < 0.7 for p in progress)
    assert f.GetOutputDataObject(0).GetNumberOfPoints() == 0  # no partial output


def test_structural_layers_progress_moves_inside_curvature(phantom):
    _, image, spec_json = phantom
    f = StructuralLayers()
    f.spec_json = spec_json
    f.SetInputDataObject(image)
    ok, errors, progress = _run(f)
    assert ok, errors
    assert progress[-1] == 1.0
    assert _inside(progress, 0.2, 0.9) >= 10
