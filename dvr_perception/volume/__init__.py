"""Volumes: the container, readers and writers for common formats, and the built-in phantom."""

from dvr_perception.volume.convert import from_vtk_image, to_vtk_image
from dvr_perception.volume.io import load_volume, save_volume
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
