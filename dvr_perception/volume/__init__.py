"""Volumes: the container, readers and writers for common formats, and the phantom's voxels.

The readers, writers and ``vtkImageData`` conversions are imported on first use (they need
VTK; the container and the phantom do not, so the core runs without ``vtkmodules``).
"""

import importlib

from dvr_perception.volume.phantom import phantom_volume
from dvr_perception.volume.volume import Volume

__all__ = [
    "Volume",
    "from_vtk_image",
    "load_volume",
    "phantom_volume",
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
    if name == "make_phantom":  # deprecated alias (one release): the phantom's spec is above
        import warnings

        warnings.warn(
            "dvr_perception.volume.make_phantom is deprecated; use dvr_perception.make_phantom "
            "(dvr_perception.structures.make_phantom)",
            DeprecationWarning,
            stacklevel=2,
        )
        from dvr_perception.structures.phantom import make_phantom  # layering: deprecated alias

        return make_phantom
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    """List the module's names with the lazily imported ones (for ``dir()`` and autodoc)."""
    return sorted({*globals(), *__all__})
