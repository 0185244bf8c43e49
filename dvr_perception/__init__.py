"""dvr_perception: perception-based transparency optimisation for direct volume rendering.

The pipeline reads as the sub-packages: :mod:`~dvr_perception.volume` (I/O) →
:mod:`~dvr_perception.structures` (spec, transfer functions, the phantom and presets) →
:mod:`~dvr_perception.rays` (camera, ray-analysis engine) → :mod:`~dvr_perception.measures` →
optimisation → front ends (:mod:`~dvr_perception.cli`, plotting, web app, ParaView plugin);
``tests/test_layering.py`` checks that no package imports one above it.

The main entry points are importable from the package root (loaded on first use, so
``import dvr_perception`` stays light: no VTK, no numba):

========================  =================================================================
:func:`load_volume`       read a volume file (NRRD, MetaImage, VTK, DICOM, NIfTI, ...)
:func:`make_phantom`      the built-in test volume and its structure spec
:func:`load_spec`         read a structure spec (JSON)
:class:`Camera`           a pinhole camera (``Camera.from_view(bounds, azimuth=...)``)
:func:`analyze`           cast the rays: the :class:`RayAnalysis` the measures read
:func:`all_measures`      visibility, shape and transparency: a :class:`MeasureSet`
:func:`optimize`          optimise opacity, lighting and colour: an
                          :class:`OptimizationResult`
========================  =================================================================

Examples
--------
>>> import dvr_perception as dp
>>> dp.Camera.__name__, callable(dp.optimize), callable(dp.analyze)
('Camera', True, True)
"""

import importlib
import types

__version__ = "0.1.0"

#: Top-level name -> the sub-package that defines it (imported on first access).
_API = {
    "Volume": "dvr_perception.volume",
    "load_volume": "dvr_perception.volume",
    "save_volume": "dvr_perception.volume",
    "make_phantom": "dvr_perception.structures",
    "StructureSpec": "dvr_perception.structures",
    "Structure": "dvr_perception.structures",
    "Lighting": "dvr_perception.structures",
    "load_spec": "dvr_perception.structures",
    "save_spec": "dvr_perception.structures",
    "Camera": "dvr_perception.rays",
    "RayAnalysis": "dvr_perception.rays",
    "analyze": "dvr_perception.rays",
    "all_measures": "dvr_perception.measures",
    "MeasureSet": "dvr_perception.measures",
    "VisibilityResult": "dvr_perception.measures",
    "ShapeResult": "dvr_perception.measures",
    "TransparencyResult": "dvr_perception.measures",
    "OptimizationResult": "dvr_perception.optimize",
    "DVRInputError": "dvr_perception.errors",
}

__all__ = ["__version__", "optimize", *sorted(_API)]


class _CallableModule(types.ModuleType):
    """A sub-package that can be called as its namesake function (``dvr_perception.optimize``).

    ``dvr_perception.optimize`` is both the sub-package (the import system puts a sub-package
    on its parent as an attribute) and, called, :func:`dvr_perception.optimize.optimize`; the
    sub-package sets this class on itself when it is imported.
    """

    def __call__(self, *args, **kwargs):
        return getattr(self, self.__name__.rpartition(".")[2])(*args, **kwargs)


def _make_callable(module_name: str) -> types.ModuleType:
    """Import ``module_name`` and make it callable as its namesake function."""
    module = importlib.import_module(module_name)
    if not isinstance(module, _CallableModule):
        module.__class__ = _CallableModule
    return module


def __getattr__(name: str):
    if name == "optimize":
        return _make_callable("dvr_perception.optimize")
    if name in _API:
        value = getattr(importlib.import_module(_API[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), *__all__})
