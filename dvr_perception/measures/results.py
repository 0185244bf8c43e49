"""Result containers of the perceptual measures and the checks of their common input.

The three measures (:func:`~dvr_perception.measures.visibility.visibility`,
:func:`~dvr_perception.measures.shape.shape`,
:func:`~dvr_perception.measures.transparency.transparency`) read a *ray analysis*: any object
with the fields ``rgba`` (H, W, 4, premultiplied), ``image`` (H, W, 3, composited over the spec
background), ``accumulated`` (H, W), ``visible`` and ``assigned`` (K, H, W), ``present`` (H, W,
uint32 bitmask), ``curvature`` (H, W) and ``names`` (K strings).  Each measure reads only the
fields it needs; the helpers here check them and raise
:class:`~dvr_perception.errors.DVRInputError` naming the field at fault.
"""

from __future__ import annotations

import threading
import warnings
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from dvr_perception._numba import kernels
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.measures.luminance import _composite, composite_luminance, luminance
from dvr_perception.rays._results import RayAnalysis, engine_made

__all__ = ["ShapeResult", "TransparencyResult", "VisibilityResult"]

#: Slack allowed on opacities slightly outside [0, 1] and on ``sum(visible) == accumulated``.
_OPACITY_SLACK = 1e-5
_SUM_SLACK = 1e-3
#: Share of covered pixels with colour above opacity beyond which rgba looks straight-alpha.
_STRAIGHT_FRACTION = 0.05


@dataclass(frozen=True)
class VisibilityResult:
    """Visibility deviation of a rendering (paper, Sec. 4.1, Eq. 1-2).

    Attributes
    ----------
    E_v : float
        Mean of ``deviation`` over the non-empty rays, in [0, 2]; 0 when no ray is non-empty.
    deviation : ndarray of float32, shape (H, W)
        ``delta_v(r) = sum_s |alpha_o(s, r) - alpha_v(s, r)|`` (target against visible
        opacity, decision D1); 0 on empty rays.
    nonempty : ndarray of bool, shape (H, W)
        Rays with any assigned opacity.
    per_structure : dict
        ``name -> {"visible_share", "target_share", "assigned_share", "visible_opacity",
        "target_opacity", "histogram_visible", "histogram_assigned", "rays"}``: image-wide
        shares of the visible opacity, of the target opacity and of the (thickness) assigned
        opacity; mean visible and target opacity per non-empty ray; histograms (int64 counts
        over ``bin_edges``) of the per-ray visible and target opacities over the rays where the
        structure is present, and the number of those rays.
    bin_edges : ndarray of float64
        Histogram bin edges on [0, 1].
    notes : tuple of str
        Remarks on degenerate input.
    target : ndarray of float32, shape (K, H, W) or None
        The target opacities ``alpha_o`` of every structure and ray.
    composition : str
        The target composition used (``"importance"`` or ``"thickness"``).
    """

    E_v: float
    deviation: np.ndarray
    nonempty: np.ndarray
    per_structure: dict
    bin_edges: np.ndarray
    notes: tuple[str, ...]
    target: np.ndarray | None = None
    composition: str = "importance"


@dataclass(frozen=True)
class ShapeResult:
    """Shape deviation of a rendering (paper, Sec. 4.2, Eq. 3-4).

    Attributes
    ----------
    E_s : float
        Mean of ``deviation`` over the non-empty pixels, in [0, 1); 0 when there are none.
    deviation : ndarray of float32, shape (H, W)
        ``delta_s = 1 - exp(-(v_s - v_i)^2 / steepness)``; 0 on empty pixels.
    v_s : ndarray of float32, shape (H, W)
        Normalised structural shape (curvature), in [0, 1].
    v_i : ndarray of float32, shape (H, W)
        Normalised image variation (Sobel gradient magnitude of the luminance), in [0, 1].
    nonempty : ndarray of bool, shape (H, W)
        Pixels with accumulated opacity above 1e-3.
    notes : tuple of str
    """

    E_s: float
    deviation: np.ndarray
    v_s: np.ndarray
    v_i: np.ndarray
    nonempty: np.ndarray
    notes: tuple[str, ...]


@dataclass(frozen=True)
class TransparencyResult:
    """Transparency deviation of a rendering (paper, Sec. 4.3, Eq. 5-11).

    Attributes
    ----------
    E_t : float
        Area-weighted mean of ``delta_t(r)`` over the non-empty regions ``R`` (Eq. 11) that
        have a determined layer or no layer needing one (regions whose layers are all
        undetermined are left out); 0 when there is none.
    deviation : ndarray of float32, shape (H, W)
        ``delta_t`` of the region of every pixel (0 in empty and Case-1 regions).
    region_id : ndarray of int32, shape (H, W)
        Index into ``regions`` of every pixel.
    layer_set : ndarray of uint32, shape (H, W)
        Bitmask of the layers present at every pixel (bit ``k`` = structure ``k``).
    regions : list of dict
        One dict per sub-region: ``id``, ``layers`` (names), ``kind`` ("empty", "plain",
        "overlay"), ``area_fraction``, ``transmittance`` ``{name: perceived alpha_t}`` (after
        clipping and calibration), ``measured`` ``{name: clipped, uncalibrated alpha}``,
        ``method`` ``{name: "metelli" | "tap" | "blend" | "generalized" | "hidden"}``, ``clipped``
        ``{name: raw value}`` for values clipped to [0, 1], ``undetermined`` ``{name:
        reason}``, ``delta_t`` and ``counted`` (whether the region enters ``E_t``: not when
        it is empty or all its layers are undetermined).
    relations : dict
        ``(name_i, name_j) -> {"kind": ..., "encloser": name or None}`` for every pair of
        visible layers (``i < j`` in structure order).
    per_structure : dict
        ``name -> {"perceived_transparency", "perceived_opacity", "expected_opacity",
        "undetermined_reasons"}``; the perceived values are area-weighted means over the
        regions where the structure's transmittance was determined, else ``None``.
    undetermined : list of dict
        ``{"region", "structure", "reason"}`` for every excluded (region, layer).
    notes : tuple of str
    records : callable
        Makes ``regions`` (called once, when ``regions`` is first read).
    """

    E_t: float
    deviation: np.ndarray
    region_id: np.ndarray
    layer_set: np.ndarray
    relations: dict
    per_structure: dict
    undetermined: list
    notes: tuple[str, ...]
    #: Makes the per-region records; they are made when :attr:`regions` is first read (a
    #: fragmented view has thousands, and the scalar, images and per-structure figures do not
    #: need them).
    records: Callable[[], list] = field(repr=False, compare=False)

    @cached_property
    def regions(self) -> list:
        """One dict per sub-region (see the class docstring), made when first read."""
        return self.records()


# -- input checks shared by the measures --------------------------------------------------------
def _field(analysis, name: str, ndim: int, *, required: bool = True) -> np.ndarray | None:
    """``analysis.<name>`` as a finite float64 array of ``ndim`` dimensions."""
    value = getattr(analysis, name, None)
    if value is None:
        if required:
            raise DVRInputError(f"analysis.{name} is missing; expected a {ndim}-D array")
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(f"analysis.{name} must be a numeric array") from None
    if arr.ndim != ndim:
        raise DVRInputError(f"analysis.{name} must be {ndim}-D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DVRInputError(f"analysis.{name} must be finite (found NaN or inf)")
    return arr


def _opacity_range(arr: np.ndarray, name: str) -> np.ndarray:
    if arr.size and (arr.min() < -_OPACITY_SLACK or arr.max() > 1 + _OPACITY_SLACK):
        raise DVRInputError(
            f"analysis.{name} must lie in [0, 1], got range [{arr.min():.6g}, {arr.max():.6g}]"
        )
    return np.clip(arr, 0.0, 1.0)


#: What the measures derived from the last few engine analyses (checked fields, luminance):
#: ``(id, name) -> (weakref, value)``.
_FIELD_MEMO: dict[tuple, tuple] = {}
_MEMO_LOCK = threading.Lock()


def _remembered(analysis, name, compute):
    """``compute()``, remembered for an engine :class:`RayAnalysis` (its arrays read-only).

    The three measures of one analysis check and convert the same fields and need the same
    luminance; an engine analysis is not changed after it is made, so that is done once.
    ``name`` is any hashable naming what is computed.  Other analysis objects get
    ``compute()`` every time.  The value is an array or a tuple whose arrays are frozen.
    """
    if not isinstance(analysis, RayAnalysis):
        return compute()
    key = (id(analysis), name)
    with _MEMO_LOCK:
        hit = _FIELD_MEMO.get(key)
    if hit is not None and hit[0]() is analysis:
        return hit[1]
    value = compute()
    for arr in value if isinstance(value, tuple) else (value,):
        if isinstance(arr, np.ndarray):
            arr.flags.writeable = False
    with _MEMO_LOCK:
        while len(_FIELD_MEMO) >= 12:
            del _FIELD_MEMO[next(iter(_FIELD_MEMO))]
        _FIELD_MEMO[key] = (weakref.ref(analysis), value)
    return value


def _recalled(analysis, name):
    """Return what :func:`_remembered` holds for ``analysis`` under ``name``, else ``None``.

    Looks only: nothing is computed or stored.
    """
    if not isinstance(analysis, RayAnalysis):
        return None
    with _MEMO_LOCK:
        hit = _FIELD_MEMO.get((id(analysis), name))
    return hit[1] if hit is not None and hit[0]() is analysis else None


def _accumulated(analysis) -> np.ndarray:
    """Return the (H, W) accumulated opacity, checked to lie in [0, 1]."""
    return _remembered(analysis, "accumulated", lambda: _accumulated_checked(analysis))


def _accumulated_checked(analysis) -> np.ndarray:
    if engine_made(analysis):  # in [0, 1] and at least 1 x 1 by construction
        return np.asarray(analysis.accumulated, np.float64)
    acc = _field(analysis, "accumulated", 2)
    if acc.shape[0] == 0 or acc.shape[1] == 0:
        raise DVRInputError(f"analysis.accumulated must have H, W >= 1, got shape {acc.shape}")
    return _opacity_range(acc, "accumulated")


def _stack(analysis, name: str, shape: tuple[int, int]) -> np.ndarray:
    """Return a (K, H, W) per-structure field matching the image ``shape``."""
    arr = _field(analysis, name, 3)
    if arr.shape[1:] != shape:
        raise DVRInputError(
            f"analysis.{name} must have shape (K, {shape[0]}, {shape[1]}) to match "
            f"analysis.accumulated, got {arr.shape}"
        )
    if np.any(arr < -_OPACITY_SLACK):
        raise DVRInputError(f"analysis.{name} must be non-negative, got minimum {arr.min():.6g}")
    return np.maximum(arr, 0.0)


def _visible(analysis, accumulated: np.ndarray, *, native: bool = False) -> np.ndarray:
    """``analysis.visible``, checked against ``accumulated`` (warns when sums disagree).

    float64; with ``native``, an engine analysis's own array as it is (float32 from the
    numba and CUDA back ends, read-only: the same values, without the copy), which the
    caller reads in float64 (a numba kernel, or ``np.float64`` arithmetic).
    """
    if native and engine_made(analysis):
        return analysis.visible
    return _remembered(analysis, "visible", lambda: _visible_checked(analysis, accumulated))


def _visible_checked(analysis, accumulated: np.ndarray) -> np.ndarray:
    if engine_made(analysis):  # non-negative and summing to ``accumulated`` by construction
        return np.asarray(analysis.visible, np.float64)
    vis = _opacity_range(_stack(analysis, "visible", accumulated.shape), "visible")
    if vis.shape[0] and np.max(np.abs(vis.sum(axis=0) - accumulated)) > _SUM_SLACK:
        warnings.warn(
            "analysis.visible does not sum over the structures to analysis.accumulated "
            f"(largest difference {np.max(np.abs(vis.sum(axis=0) - accumulated)):.3g})",
            DVRWarning,
            stacklevel=5,
        )
    return vis


def _assigned(analysis, shape: tuple[int, int], *, native: bool = False) -> np.ndarray:
    """``analysis.assigned`` (K, H, W), checked like :func:`_stack`; remembered.

    ``native``: as :func:`_visible`.
    """
    if native and engine_made(analysis):
        _check_occlusion_free(analysis)
        return analysis.assigned
    return _remembered(analysis, "assigned", lambda: _assigned_checked(analysis, shape))


def _assigned_checked(analysis, shape):
    if not engine_made(analysis):
        return _stack(analysis, "assigned", shape)
    _check_occlusion_free(analysis)
    return np.asarray(analysis.assigned, np.float64)  # non-negative by construction


def _check_occlusion_free(analysis) -> None:
    """Refuse the NaN ``assigned`` of an engine analysis made with ``occlusion_free=False``."""
    if not analysis.stats.get("occlusion_free", True):
        raise DVRInputError(
            "analysis.assigned must be finite, but this analysis was made with "
            "occlusion_free=False (render only): analyze with occlusion_free=True for it"
        )


def _curvature(analysis, shape: tuple[int, int]) -> np.ndarray:
    """``analysis.curvature`` (H, W) as float64, checked to be non-negative and to fit."""
    if engine_made(analysis):  # a weighted mean of |H| >= 0 by construction
        return np.asarray(analysis.curvature, np.float64)
    curvature = _field(analysis, "curvature", 2)
    if curvature.shape != shape:
        raise DVRInputError(
            f"analysis.curvature must have shape {shape} to match "
            f"analysis.accumulated, got {curvature.shape}"
        )
    if np.any(curvature < 0):
        raise DVRInputError("analysis.curvature must be non-negative (it is |mean curvature|)")
    return curvature


def _names(analysis, spec, k: int) -> tuple[str, ...]:
    """Structure names of the analysis, checked against the spec when one is given."""
    names = getattr(analysis, "names", None)
    spec_names = None if spec is None else tuple(spec.names)
    if names is None:
        names = spec_names if spec_names is not None else tuple(f"s{i}" for i in range(k))
    names = tuple(str(n) for n in names)
    if len(names) != k:
        raise DVRInputError(f"analysis.names has {len(names)} names for {k} structures")
    if spec_names is not None and spec_names != names:
        raise DVRInputError(
            f"spec: structure names {list(spec_names)} do not match analysis.names {list(names)}"
        )
    return names


def _check_premultiplied(rgba: np.ndarray, notes: list[str], *, trusted: bool = False) -> None:
    """Warn if ``rgba`` looks straight (not premultiplied); note a few emissive pixels.

    Shaded renderings add a white specular term, so a highlight may carry more light than its
    opacity: that is emission, not a straight-alpha image.  Only when more than
    ``_STRAIGHT_FRACTION`` of the covered pixels have colour above opacity is the image
    taken to be non-premultiplied (a :class:`DVRWarning`); otherwise a note counts them.
    ``trusted``: the image comes from the ray-analysis engine, which composites premultiplied
    colour by construction (dim, specular-lit silhouettes may exceed their opacity on many
    pixels), so only the note is made.
    """
    nk = kernels("dvr_perception.measures._kernels")
    if nk is not None:  # the counts below in one pass
        n_over, covered = nk.premultiplied_excess(
            np.ascontiguousarray(rgba).reshape(-1, 4), _OPACITY_SLACK
        )
    else:
        alpha = rgba[..., 3]
        brightest = np.maximum(np.maximum(rgba[..., 0], rgba[..., 1]), rgba[..., 2])
        n_over = int(np.count_nonzero(brightest > alpha + _OPACITY_SLACK))
        covered = int(np.count_nonzero(alpha > _OPACITY_SLACK))
    if n_over == 0:
        return
    covered = max(covered, 1)
    if not trusted and n_over > _STRAIGHT_FRACTION * covered:
        warnings.warn(
            f"analysis.rgba: colour exceeds opacity on {n_over} of {covered} covered pixels; "
            "is the image really premultiplied?",
            DVRWarning,
            stacklevel=4,
        )
    else:
        notes.append(
            f"{n_over} pixel(s) carry more light than their opacity (specular highlights); "
            "composited as emission"
        )


def _image_luminance(analysis, spec, shape: tuple[int, int]) -> tuple[np.ndarray, list[str]]:
    """Linear CIE Y of the rendering composited over the background, clipped to [0, 1].

    With a spec, ``analysis.rgba`` is composited over ``spec.background``; without one,
    ``analysis.image`` (already composited) is used, falling back to ``rgba`` over black.
    Luminance above the displayable 1 is clipped, with a note.  For an engine
    :class:`RayAnalysis` (whose arrays are not changed after it is made) the result is
    remembered, so shape and transparency of one analysis compute it once; it is read-only.
    """
    background = None if spec is None else tuple(spec.background)

    def compute():
        y, notes = _compute_luminance(analysis, spec, shape)
        return y, tuple(notes)

    y, notes = _remembered(analysis, ("luminance", background, shape), compute)
    return y, list(notes)


def _compute_luminance(analysis, spec, shape):
    notes: list[str] = []
    rgba = getattr(analysis, "rgba", None)
    image = getattr(analysis, "image", None)
    if rgba is not None and (spec is not None or image is None):
        background = (0.0, 0.0, 0.0) if spec is None else tuple(spec.background)
        if engine_made(analysis):  # finite, premultiplied, opacity in [0, 1] by construction
            arr = np.asarray(analysis.rgba, np.float64)
            y = _composite(arr, np.asarray(background, np.float64))
        else:
            arr = _field(analysis, "rgba", 3)
            with warnings.catch_warnings():  # judged below: a few emissive pixels are expected
                warnings.simplefilter("ignore", DVRWarning)
                y = composite_luminance(arr, background=background)
        _check_premultiplied(arr, notes, trusted=isinstance(analysis, RayAnalysis))
        source = "rgba"
    elif image is not None:
        y = luminance(_field(analysis, "image", 3))
        source = "image"
    else:
        raise DVRInputError("analysis.rgba (or analysis.image) is missing; need the rendering")
    if y.shape != shape:
        raise DVRInputError(
            f"analysis.{source} must be {shape[0]} x {shape[1]} pixels to match "
            f"analysis.accumulated, got {y.shape}"
        )
    if np.any(y > 1.0):
        notes.append(
            f"luminance above 1 clipped to the displayable range on {np.count_nonzero(y > 1)} "
            "pixel(s)"
        )
    return np.clip(y, 0.0, 1.0), notes
