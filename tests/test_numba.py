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
