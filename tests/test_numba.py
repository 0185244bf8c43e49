"""dvr_perception._numba: the kernels come from numba unless it is missing or switched off."""

import pytest

from dvr_perception import _numba


def test_kernels_are_imported_when_numba_is_there(monkeypatch):
    monkeypatch.delenv("DVR_PERCEPTION_NO_NUMBA", raising=False)
    module = _numba.kernels("dvr_perception.measures._kernels")
    assert module is not None
    assert callable(module.group_stats)


@pytest.mark.parametrize(("value", "off"), [("1", True), ("yes", True), ("0", False), ("", False)])
def test_environment_variable_switches_numba_off(monkeypatch, value, off):
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", value)
    assert (_numba.kernels("dvr_perception.rays._numba_kernels") is None) == off


def test_a_module_that_cannot_be_imported_gives_none(monkeypatch):
    monkeypatch.delenv("DVR_PERCEPTION_NO_NUMBA", raising=False)
    assert _numba.kernels("dvr_perception.no_such_kernels") is None


def test_serial_below_runs_small_work_on_this_thread_alone_and_restores():
    import numba

    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    before = numba.get_num_threads()
    with _numba.serial_below(10, limit=100):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == before
    with _numba.serial_below(100, limit=100):  # enough work: left alone
        assert numba.get_num_threads() == before
    with pytest.raises(KeyError), _numba.serial_below(0):  # restored on an error too
        raise KeyError("x")
    assert numba.get_num_threads() == before


def test_reevaluate_keeps_its_lighting_only_while_it_is_the_same():
    """The kept light arrays follow the materials and the light (a change, then back)."""
    import numpy as np

    from dvr_perception.rays.camera import Camera
    from dvr_perception.rays.engine import analyze, reevaluate
    from dvr_perception.structures import make_phantom
    from dvr_perception.structures.spec import Lighting

    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, width=20, height=20)
    cache = analyze(vol, spec, cam, build_cache=True).cache
    first = reevaluate(cache)
    mats = [Lighting(0.3, 0.6, 0.5, 40.0)] * len(spec.structures)
    moved = reevaluate(cache, lighting=mats, light_direction=(0.5, 0.2, 0.8))
    lit = reevaluate(cache, lighting=mats)
    assert not np.array_equal(first.image, moved.image)
    assert not np.array_equal(moved.image, lit.image)
    fresh = analyze(vol, spec, cam).image
    again = reevaluate(cache)
    assert np.array_equal(again.image, first.image)
    assert np.array_equal(again.image, fresh)
    rays = np.flatnonzero(first.accumulated.ravel() > 0)[::3]
    part = reevaluate(cache, rays=rays)  # few rays: one thread, the same numbers
    assert np.array_equal(part.image.reshape(-1, 3)[rays], first.image.reshape(-1, 3)[rays])
