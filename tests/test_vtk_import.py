"""VTK's modules are imported on first use; a Ctrl-C in the middle of that import waits for it.

An extension module interrupted half-way through its import left VTK half-initialised, and the
process crashed with SIGSEGV while it cleaned up (``optimize`` interrupted twice, about one run
in five, in tests/security/test_outputs.py).
"""

from __future__ import annotations

import importlib
import os
import signal
import time

import pytest

from dvr_perception import _vtk

TARGET = "vtkmodules.vtkCommonMath"


def test_a_ctrl_c_during_a_vtk_import_is_delivered_after_the_import(monkeypatch):
    real = importlib.import_module
    finished = []

    def interrupted_import(name, *args):
        if name != TARGET:  # VTK imports its own helpers the same way
            return real(name, *args)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the KeyboardInterrupt is raised here unless it is held back
        module = real(name, *args)
        finished.append(name)
        return module

    monkeypatch.setattr(importlib, "import_module", interrupted_import)
    with pytest.raises(KeyboardInterrupt):
        _vtk._import(TARGET)
    assert finished == [TARGET]


def test_the_lazy_names_are_vtk_classes():
    assert _vtk.vtkMatrix4x4().GetClassName() == "vtkMatrix4x4"
