"""Curvature for the engine without a whole-volume array when the volume is large.

:func:`curvature_source` returns what :func:`~dvr_perception.rays.engine.analyze` takes as
``curvature``: the usual float32 ``|H|`` volume when it is small enough to hold, else a
:class:`CurvatureField` that computes each brick's piece when a bricked analysis walks it
(:func:`~dvr_perception.rays.curvature.curvature_volume` with ``extent``; the whole-volume
quantities are computed once, so every piece equals the slice of the whole result).
"""

from __future__ import annotations

import numpy as np

from dvr_perception._progress import reporter
from dvr_perception.rays.curvature import curvature_globals, curvature_volume

__all__ = ["CurvatureField", "curvature_source"]


class CurvatureField:
    """``|H|`` of ``volume``'s structure boundaries, computed piece by piece on demand.

    Parameters
    ----------
    volume, spec, sigma
        As :func:`~dvr_perception.rays.curvature.curvature_volume`.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> field = CurvatureField(vol, spec)
    >>> whole = curvature_volume(vol, spec)[0]
    >>> piece = field.piece(((3, 9), (0, 24), (5, 20)))
    >>> bool(np.array_equal(piece, whole[3:9, :, 5:20]))
    True
    """

    def __init__(self, volume, spec, *, sigma: float = 1.0) -> None:
        self.volume = volume
        self.spec = spec
        self.sigma = float(sigma)
        self.shape = volume.data.shape
        self._globals = None

    @property
    def globals(self):
        """The whole-volume quantities (computed once)."""
        if self._globals is None:
            self._globals = curvature_globals(self.volume, self.spec, sigma=self.sigma)
        return self._globals

    def piece(self, extent) -> np.ndarray:
        """float32 ``|H|`` on the voxels ``extent = ((z0, z1), (y0, y1), (x0, x1))``."""
        extent = tuple((int(a), int(b)) for a, b in extent)
        out, _ = curvature_volume(
            self.volume, self.spec, sigma=self.sigma, extent=extent, gradient_max=self.globals
        )
        return np.ascontiguousarray(out, np.float32)

    def __array__(self, dtype=None, copy=None):
        """Return the whole volume's ``|H|`` (what a whole-volume analysis reads)."""
        out, _ = curvature_volume(
            self.volume, self.spec, sigma=self.sigma, gradient_max=self.globals
        )
        return out if dtype is None else out.astype(dtype)


def curvature_source(volume, spec, *, sigma: float = 1.0, memory_limit=None, progress=None):
    """Return the ``curvature`` to give :func:`~dvr_perception.rays.engine.analyze`.

    The float32 volume when the volume, its derived volumes and this array fit the memory
    limit (:func:`~dvr_perception.rays.memory.whole_fits`: the whole-volume analysis's share
    of :func:`~dvr_perception.rays.memory.plan`, however many voxels), else a
    :class:`CurvatureField`.  ``progress``: as
    :func:`~dvr_perception.rays.curvature.curvature_volume`'s (a field reports 0.0 and 1.0
    at once: its pieces are computed, and reported, by the bricked analysis that walks them).
    """
    from dvr_perception.rays import memory

    report = reporter(progress)
    if memory.whole_fits(volume, memory_limit):
        return curvature_volume(volume, spec, sigma=sigma, progress=report)[0]
    report(0.0)
    report(1.0)
    return CurvatureField(volume, spec, sigma=sigma)
