"""The three measures of one rendering together (what ``dvr-perception measure`` computes).

:func:`all_measures` gives the same results as calling
:func:`~dvr_perception.measures.visibility.visibility`,
:func:`~dvr_perception.measures.shape.shape` and
:func:`~dvr_perception.measures.transparency.transparency` in turn; it computes transparency in
a worker thread meanwhile (numpy, scikit-image and the numba kernels release the interpreter
lock for most of their work), which takes a sixth to a quarter off the time on two cores.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

from dvr_perception.measures.results import (
    ShapeResult,
    TransparencyResult,
    VisibilityResult,
    _accumulated,
    _image_luminance,
)
from dvr_perception.measures.shape import shape
from dvr_perception.measures.transparency import transparency
from dvr_perception.measures.visibility import visibility
from dvr_perception.rays._results import engine_made

__all__ = ["MeasureSet", "all_measures"]

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


class MeasureSet(NamedTuple):
    """The three measures of one rendering."""

    visibility: VisibilityResult
    shape: ShapeResult
    transparency: TransparencyResult


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="dvr-measures")
        return _POOL


def all_measures(
    analysis, spec, *, bins: int = 20, calibration=None, parallel: bool = True
) -> MeasureSet:
    """Visibility, shape and transparency of one ray analysis, with their defaults.

    Parameters
    ----------
    analysis : RayAnalysis
        What the three measures read (see each of them).
    spec : StructureSpec
        Structures (names must match the analysis), background and expected opacities.
    bins : int, optional
        Visibility histogram bins (default 20).
    calibration : pair of array_like (x, y), optional
        Transparency's calibration curve (default: none, the identity).
    parallel : bool, optional
        Compute transparency in a worker thread while shape and visibility run (default);
        ``False`` computes the three in turn.  The results are the same either way.

    Returns
    -------
    MeasureSet
        ``(visibility, shape, transparency)`` results.

    Raises
    ------
    DVRInputError
        As the measures do (the first one that fails, in the order visibility, shape,
        transparency).

    Examples
    --------
    >>> import numpy as np
    >>> from dvr_perception.rays import Camera
    >>> from dvr_perception.rays.engine import analyze
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> from dvr_perception.volume import Volume
    >>> vol = Volume(np.full((8, 8, 8), 100, np.uint8))
    >>> spec = StructureSpec((Structure("slab", 0.5, (1, 1, 1), range=(50, 150)),))
    >>> res = all_measures(analyze(vol, spec, Camera.from_view(vol.bounds, width=8, height=8)),
    ...                    spec)
    >>> round(res.visibility.E_v, 6), res.transparency.E_t
    (0.0, 0.0)
    """
    if not parallel:
        return MeasureSet(
            visibility(analysis, spec, bins=bins),
            shape(analysis, spec),
            transparency(analysis, spec, calibration=calibration),
        )
    if engine_made(analysis):
        # what the measures share is remembered for an engine analysis: make it once, here
        accumulated = _accumulated(analysis)
        _image_luminance(analysis, spec, accumulated.shape)
    pending = _pool().submit(transparency, analysis, spec, calibration=calibration)
    try:
        vis = visibility(analysis, spec, bins=bins)
        shp = shape(analysis, spec)
    finally:
        trn_error = pending.exception()  # waits; a failure of ours is raised first
    if trn_error is not None:
        raise trn_error
    return MeasureSet(vis, shp, pending.result())
