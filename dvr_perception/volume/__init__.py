"""Volumes: the container, readers and writers for common formats, and the built-in phantom.

The readers, writers and ``vtkImageData`` conversions are imported on first use (they need
VTK; the container and the phantom do not, so the core runs without ``vtkmodules``).
"""

import importlib

from dvr_perception.volume.phantom import make_phantom
from dvr_perception.volume.volume import Volume

__all__ = [
    "Volume",
    "from_vtk_image",
    "load_volume",
    "make_phantom",
    "save_volume",
    "to_vtk_image",
]

_LAZY = {
    "from_vtk_image": "convert",
    "to_vtk_image": "convert",
    "load_volume": "io",
    "save_volume": "io",
}


def __getattr__(name: str):
    """Import the VTK-backed readers, writers and conversions when first asked for."""
    if name in _LAZY:
        return getattr(importlib.import_module(f"dvr_perception.volume.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    """List the module's names with the lazily imported ones (for ``dir()`` and autodoc)."""
    return sorted({*globals(), *__all__})
