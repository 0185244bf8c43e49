"""What ``optimize`` does to cut its one-time costs changes no number (issue 31)."""

import sys

import numpy as np
import pytest

from dvr_perception.optimize import _problem, _solver
from dvr_perception.optimize._problem import Params, Problem
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom


@pytest.fixture(scope="module")
def problem():
    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=40, height=32)
    analysis = analyze(vol, spec, cam, build_cache=True)
    return analysis, spec


def _terms(analysis, spec, overlap_pixels, monkeypatch):
    monkeypatch.setattr(_problem, "OVERLAP_PIXELS", overlap_pixels)
    prob = Problem([analysis.cache], [None], spec, np.ones(3), {}, None)
    params = Params.from_spec(spec)
    params = params.replace(opacities=params.opacities * 0.8)  # a fresh rendering each time
    return prob.terms(params)


def test_terms_with_transparency_in_a_worker_equal_terms_in_turn(problem, monkeypatch):
    analysis, spec = problem
    alone = _terms(analysis, spec, 10**12, monkeypatch)
    threaded = _terms(analysis, spec, 0, monkeypatch)  # every image: E_t in the worker
    assert np.isfinite(alone["E_t"])
    assert alone["E_t"] > 0.0  # the phantom's layers give transparency something to measure
    for key in ("E_v", "E_s", "E_t", "E", "S", "coverage"):
        assert threaded[key] == alone[key], key
    for term in ("E_v", "E_s", "E_t"):
        assert np.array_equal(threaded["badness"][term], alone["badness"][term])
    assert np.array_equal(threaded["_stack"][0], alone["_stack"][0])


def test_a_failing_transparency_in_the_worker_is_raised(problem, monkeypatch):
    analysis, spec = problem

    def broken(*_args, **_kwargs):
        raise RuntimeError("transparency failed")

    monkeypatch.setattr(_problem, "transparency_table", broken)
    with pytest.raises(RuntimeError, match="transparency failed"):
        _terms(analysis, spec, 0, monkeypatch)


def test_prefetch_imports_the_solver_module_in_a_thread(monkeypatch):
    monkeypatch.setattr(_solver, "SOLVER_MODULE", "dvr_perception_no_such_module")
    thread = _solver.prefetch()  # a module that cannot be imported: nothing raised here
    assert thread is not None
    thread.join(10)
    assert not thread.is_alive()
    monkeypatch.setattr(_solver, "SOLVER_MODULE", "json")
    assert "json" in sys.modules
    assert _solver.prefetch() is None  # imported already: no thread
