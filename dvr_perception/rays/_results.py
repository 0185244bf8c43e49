"""Result containers of the ray-analysis engine (:class:`RayAnalysis`, :class:`RayCache`)."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from dvr_perception.rays.camera import Camera
from dvr_perception.structures.spec import StructureSpec

__all__ = ["RayAnalysis", "RayCache"]

#: The analyses the engine made (:func:`engine_made`): their arrays are read-only, finite and
#: in range by construction, so the measures read them without checking them again.
_ENGINE_MADE: weakref.WeakSet = weakref.WeakSet()


@dataclass(frozen=True, eq=False)
class RayCache:
    """Per-ray compact sample lists of one :func:`analyze` call, for :func:`reevaluate`.

    Ray ``r`` (row-major pixel) owns entries ``start[r] : start[r] + count[r]`` of ``lut``
    (uint16 table index: structure id and membership), ``shading`` (uint16 (E, 2): VTK's
    interpolated lit diffuse cosine and specular power term as ``round(x * 65534)``, 65535 in
    column 0 while not yet computed; empty when unshaded) and ``curvature`` (float32, -1 while
    not yet computed; empty without a curvature volume).
    """

    spec: StructureSpec
    camera: Camera
    ids: np.ndarray
    membership: np.ndarray
    ratio: float
    start: np.ndarray
    count: np.ndarray
    lut: np.ndarray
    shading: np.ndarray
    curvature: np.ndarray
    assigned: np.ndarray
    present: np.ndarray
    backend: str
    stats: dict
    #: Per-entry sample index (``steps``), the rays (``a``, ``b``, ``t``, ``step``), the voxel
    #: records (``volume``: table index | normal code << 16) and curvature volume, and the
    #: ``shading_key`` of the light the ``shading`` column was computed for, so that shading
    #: and curvature of an entry are computed when compositing first reaches it (numba) or
    #: again after a change of light.  The volumes are referenced, not copied (a non-negative
    #: float32 curvature array passed to ``analyze`` is used as is: do not modify it while the
    #: cache is in use).
    lazy: dict | None = None
    #: (H, W) accumulated opacity of each ray at the importance opacities (see
    #: :attr:`RayAnalysis.importance_accumulated`).
    importance_accumulated: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        """Bytes held by the per-ray sample lists and the per-pixel arrays."""
        arrays = (self.start, self.count, self.lut, self.shading, self.curvature)
        if self.lazy is not None:
            arrays += (self.lazy["steps"], self.lazy["a"], self.lazy["b"], self.lazy["t"])
        return int(sum(a.nbytes for a in arrays) + self.assigned.nbytes + self.present.nbytes)


@dataclass(frozen=True, eq=False)
class RayAnalysis:
    """What each pixel's ray sees; arrays are ``(H, W)`` images, row 0 at the top.

    See the module docstring of :mod:`dvr_perception.rays.engine` for the definitions of
    ``visible`` (sum of ``a_i T_i``), ``assigned`` (sum of the importance-based step-corrected
    opacity, no occlusion), ``present`` (bit ``s`` set if any sample of ``s``) and
    ``curvature`` (visibility-weighted mean ``|H|`` over boundary samples).

    ``importance_accumulated`` (``A_imp``, DECISIONS D1) is the accumulated opacity of each ray
    rendered with every structure's opacity equal to its importance (early ray termination
    included): fixed for a view, whatever the current opacities.  The engine always sets it
    (NaN with ``occlusion_free=False``); hand-made analyses may leave it ``None``.
    """

    rgba: np.ndarray
    image: np.ndarray
    accumulated: np.ndarray
    visible: np.ndarray
    assigned: np.ndarray
    present: np.ndarray
    curvature: np.ndarray
    names: tuple[str, ...]
    camera: Camera
    stats: dict
    cache: RayCache | None = None
    importance_accumulated: np.ndarray | None = None

    @property
    def visible_share(self) -> np.ndarray:
        """``visible / accumulated`` per structure (0 where nothing accumulated)."""
        return _share(self.visible, self.accumulated[None])

    @property
    def assigned_share(self) -> np.ndarray:
        """``assigned / assigned.sum(0)`` per structure (0 where the sum is 0)."""
        return _share(self.assigned, self.assigned.sum(axis=0, keepdims=True))


def _share(x: np.ndarray, total: np.ndarray) -> np.ndarray:
    """float32 ``x / total``, 0 where ``total`` is not positive (no division there)."""
    out = np.zeros(x.shape, np.result_type(x, total, np.float32))
    np.divide(x, total, out=out, where=np.broadcast_to(total > 0, x.shape))
    return out.astype(np.float32, copy=False)


def engine_made(analysis, *, mark: bool = False) -> bool:
    """Whether ``analysis`` is a :class:`RayAnalysis` the engine made (``mark``: record it so).

    The engine marks each analysis it returns after making its arrays read-only; anything
    else (a hand-made :class:`RayAnalysis`, any other object) is not trusted.
    """
    if not isinstance(analysis, RayAnalysis):
        return False
    if mark:
        for name in ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature",
                     "importance_accumulated"):  # fmt: skip
            getattr(analysis, name).flags.writeable = False
        _ENGINE_MADE.add(analysis)
        return True
    return analysis in _ENGINE_MADE
