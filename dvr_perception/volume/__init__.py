"""Volumes: the container, readers for common formats, and the built-in phantom."""

from dvr_perception.volume.volume import Volume

__all__ = ["Volume"]
