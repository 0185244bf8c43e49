"""The one module of the core that imports ``vtkmodules``.

Everything else in :mod:`dvr_perception` gets VTK classes from here, so the set of VTK modules
the core needs is visible in one place and works with both the VTK wheel (9.7) and ParaView
5.11's bundled VTK (9.2).  Rendering modules (OpenGL) are imported lazily by
:func:`rendering`, because importing them is harmless but *using* them without EGL/OSMesa
crashes the process; callers must check :func:`dvr_perception._vtk.can_render` first.
"""

from __future__ import annotations

import os

#: Where each name of this module comes from (``vtkmodules`` sub-module).  They are imported on
#: first use (:func:`__getattr__`): importing a VTK module costs time (all of them about 0.3 s)
#: that a command which never touches VTK (``optimize`` on a NRRD volume) need not pay.
_SOURCES = {
    "vtkmodules.util.numpy_support": ("get_vtk_array_type", "numpy_to_vtk", "vtk_to_numpy"),
    "vtkmodules.util.vtkAlgorithm": ("VTKPythonAlgorithmBase",),
    "vtkmodules.vtkCommonCore": (
        "VTK_DOUBLE",
        "VTK_FLOAT",
        "vtkCommand",
        "vtkDoubleArray",
        "vtkFloatArray",
        "vtkIntArray",
        "vtkLogger",
        "vtkOutputWindow",
        "vtkStringArray",
        "vtkStringOutputWindow",
    ),
    "vtkmodules.vtkCommonDataModel": (
        "vtkDataObject",
        "vtkImageData",
        "vtkPiecewiseFunction",
        "vtkTable",
    ),
    "vtkmodules.vtkCommonExecutionModel": (
        "vtkAlgorithm",
        "vtkExtentTranslator",
        "vtkStreamingDemandDrivenPipeline",
    ),
    "vtkmodules.vtkCommonMath": ("vtkMatrix4x4",),
    "vtkmodules.vtkIOImage": (
        "vtkDICOMImageReader",
        "vtkMetaImageReader",
        "vtkMetaImageWriter",
        "vtkNIFTIImageReader",
        "vtkNIFTIImageWriter",
        "vtkNrrdReader",
        "vtkPNGReader",
        "vtkPNGWriter",
    ),
    "vtkmodules.vtkIOLegacy": ("vtkDataSetReader", "vtkStructuredPointsWriter"),
    "vtkmodules.vtkIOXML": ("vtkXMLImageDataReader", "vtkXMLImageDataWriter"),
    "vtkmodules.vtkRenderingCore": (
        "vtkCamera",
        "vtkColorTransferFunction",
        "vtkVolumeProperty",
    ),
}
_MODULE_OF = {name: module for module, names in _SOURCES.items() for name in names}

__all__ = ["can_render", "rendering", *sorted(_MODULE_OF)]


def __getattr__(name: str):
    """Import the VTK class (or function, constant) ``name`` on first use and keep it.

    Examples
    --------
    >>> from dvr_perception import _vtk
    >>> _vtk.vtkImageData().GetClassName()
    'vtkImageData'
    """
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_import(module), name)
    globals()[name] = value
    return value


def _import(module: str):
    """Import the VTK module ``module`` with Ctrl-C and SIGTERM held back until it is done.

    A VTK extension module interrupted half-way through its import (a ``KeyboardInterrupt``
    raised inside it) leaves VTK half-initialised, and the process then crashes (SIGSEGV)
    while it cleans up; the signal is delivered once the import is complete.
    """
    import importlib

    from dvr_perception._files import _deferred_sigint

    with _deferred_sigint():
        return importlib.import_module(module)


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULE_OF})


def rendering():
    """Import and return a namespace with VTK's rendering classes (OpenGL, volume mappers).

    Sets ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` when no display and no override is
    configured, so the wheel renders headless through EGL.
    """
    if "DISPLAY" not in os.environ:
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import types

    _import("vtkmodules.vtkRenderingOpenGL2")  # registers the OpenGL overrides
    core = _import("vtkmodules.vtkRenderingCore")
    return types.SimpleNamespace(
        vtkFixedPointVolumeRayCastMapper=_import(
            "vtkmodules.vtkRenderingVolume"
        ).vtkFixedPointVolumeRayCastMapper,
        vtkOpenGLGPUVolumeRayCastMapper=_import(
            "vtkmodules.vtkRenderingVolumeOpenGL2"
        ).vtkOpenGLGPUVolumeRayCastMapper,
        vtkLight=core.vtkLight,
        vtkRenderWindow=core.vtkRenderWindow,
        vtkRenderer=core.vtkRenderer,
        vtkVolume=core.vtkVolume,
        vtkWindowToImageFilter=core.vtkWindowToImageFilter,
    )


def can_render() -> tuple[bool, str]:
    """Return ``(True, "")`` if an off-screen OpenGL context can be made, else ``(False, why)``.

    The check runs in a subprocess, because VTK segfaults (rather than raising) when neither
    EGL nor OSMesa is available.
    """
    import subprocess
    import sys

    code = (
        "from dvr_perception._vtk import rendering; r = rendering(); "
        "w = r.vtkRenderWindow(); w.SetOffScreenRendering(1); w.SetSize(8, 8); "
        "w.AddRenderer(r.vtkRenderer()); w.Render(); print('ok')"
    )
    try:
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"could not start a render check: {exc}"
    if proc.returncode == 0 and "ok" in proc.stdout:
        return True, ""
    return False, (
        "VTK cannot open an off-screen OpenGL context (exit code "
        f"{proc.returncode}). Install EGL/Mesa: apt-get install libegl1 libegl-mesa0 "
        "libgl1-mesa-dri (or libosmesa6 with VTK_DEFAULT_OPENGL_WINDOW=vtkOSOpenGLRenderWindow)."
    )
