"""TAP transmittance of one layer over what it covers, seen with and without it (paper, Fig. 9).

The paper's colour experiment (Sec. 7, Fig. 9) derives the outer layer's perceived
transparency "based on the TAP": the contrast of what lies behind the layer, seen through it,
relative to the contrast of the same things seen plainly (Eq. 6-7).  In a volume rendering the
plain view of an *enclosed* or *overlapped* structure rarely exists as a region of the image, so
:func:`covered_transmittance` renders it: the layer's covered pixels ``P`` (where the layer and
at least one other layer are present) are compared with the same pixels re-composited from the
analysis's cache with the layer's opacity set to 0 (``A``).  :func:`~.transparency.transparency`
reads an enclosing layer this way where its plain view is missing or uniform (decision D3), or
always with ``enclosure="auto"`` / ``"unoccluded"``; it is offered here for any layer.

A brighter layer adds the same luminance to every covered pixel, so the Michelson contrast of
``P`` falls and the layer reads as *less* transparent, while the luminance range (Eq. 6) and
Metelli's ratio (Eq. 5) keep the physical transmittance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.measures._layer_sets import DENOMINATOR_EPS, transmitted_tap
from dvr_perception.measures.luminance import _composite
from dvr_perception.measures.psychophysics import luminance_range
from dvr_perception.measures.regions import layer_footprints
from dvr_perception.measures.results import _accumulated, _image_luminance, _names, _visible

__all__ = ["CoveredTransmittance", "covered_transmittance"]


@dataclass(frozen=True)
class CoveredTransmittance:
    """Result of :func:`covered_transmittance`.

    Attributes
    ----------
    structure : str
        The layer.
    alpha : float
        TAP transmittance ``C(P) / C(A)`` (not clipped); NaN when undetermined.
    pixels : int
        Number of covered pixels ``P``.
    contrast : str
        ``"michelson"`` (Eq. 7) or ``"range"`` (Eq. 6).
    reason : str or None
        Why ``alpha`` is undetermined, else ``None``.
    """

    structure: str
    alpha: float
    pixels: int
    contrast: str
    reason: str | None = None


def has_cache(analysis) -> bool:
    """Whether ``analysis`` can be re-composited without a layer.

    True for a :class:`~dvr_perception.rays.engine.RayCache`, or a stand-in with a
    ``reevaluate`` method of its own (the MPI ranks' ``RankCache``, through which the
    optimiser renders).
    """
    from dvr_perception.rays.engine import RayCache

    cache = getattr(analysis, "cache", None)
    if isinstance(cache, RayCache):
        return True
    if getattr(getattr(cache, "session", None), "stopped", False):
        return False  # the ranks no longer serve: nothing to re-composite through
    return callable(getattr(cache, "reevaluate", None))


def can_recomposite(analysis) -> bool:
    """Whether the view of ``analysis`` without a layer can be made (DECISIONS D7).

    From a re-evaluation cache (:func:`has_cache`), or, for an engine analysis without one,
    by walking the affected rays again (:func:`~dvr_perception.rays.engine.rewalk`): both
    give the same luminance.
    """
    from dvr_perception.rays.engine import can_rewalk

    return has_cache(analysis) or can_rewalk(analysis)


def _without(analysis, spec, layer: int, pixels=None) -> np.ndarray:
    """Luminance of the same view with ``layer``'s opacity 0 (re-composited, D7).

    The other parameters are those the analysis was rendered with (``stats["params"]`` of an
    engine analysis, so a re-evaluated analysis is re-composited with its own opacities,
    colours, materials and light), else ``spec``'s opacities and colours.  From the
    re-evaluation cache where the analysis has one; an engine analysis without one walks
    those rays again with ``layer``'s opacity 0 (:func:`~dvr_perception.rays.engine.rewalk`,
    the same luminance).  ``pixels`` (an (H, W) bool mask) re-composites only those rays of
    an engine analysis: the luminance is exact there and not meant to be read elsewhere.
    """
    from dvr_perception.rays.engine import RayCache, can_rewalk, reevaluate, rewalk

    cache = getattr(analysis, "cache", None)
    params = getattr(analysis, "stats", {}).get("params")
    rays = None if pixels is None else np.flatnonzero(pixels)
    if not has_cache(analysis):
        if not can_rewalk(analysis):
            raise DVRInputError(
                "analysis: the view without a layer needs the analysis's re-evaluation cache "
                "(analyze(..., build_cache=True)) or an engine analysis to walk again"
            )
        ops = list(params["opacities"])
        ops[layer] = 0.0
        other = rewalk(analysis, opacities=ops, rays=rays, background=spec.background)
    elif params is not None:
        ops = list(params["opacities"])
        ops[layer] = 0.0
        kwargs = {"opacities": ops, "colours": params["colours"], "lighting": params["lighting"],
                  "light_direction": params["light_direction"]}  # fmt: skip
        if isinstance(cache, RayCache):
            other = reevaluate(cache, background=spec.background, rays=rays, **kwargs)
        else:  # a stand-in that re-composites itself (the MPI ranks' RankCache)
            other = cache.reevaluate(**kwargs)
    else:
        ops = [float(s.render_opacity) for s in spec.structures]
        ops[layer] = 0.0
        colours = [tuple(s.colour) for s in spec.structures]
        if isinstance(cache, RayCache):
            other = reevaluate(cache, opacities=ops, colours=colours, background=spec.background)
        else:
            other = cache.reevaluate(opacities=ops, colours=colours)
    y, _ = _image_luminance(other, spec, analysis.accumulated.shape)
    return y


def _without_many(analysis, spec, pixels: dict) -> dict:
    """:func:`_without` of several layers at once: ``{layer: luminance}`` for ``{layer: mask}``.

    Each luminance is exact on its mask (an (H, W) bool array) and 0 elsewhere.  An engine
    analysis without a cache walks the masks' rays once for all the layers
    (:func:`~dvr_perception.rays.engine.rewalk_rgba`: the same colour as :func:`_without`'s
    walk, to the bit, and the same luminance); one with a numba cache re-composites them after
    one set-up of its materials and light (:func:`~dvr_perception.rays.engine.reevaluate_rgba`,
    the same colour as :func:`_without`'s); otherwise each layer is :func:`_without`.
    """
    from dvr_perception.rays.engine import RayCache, reevaluate_rgba, rewalk_rgba

    params = getattr(analysis, "stats", {}).get("params")
    cache = getattr(analysis, "cache", None)
    numba_cache = isinstance(cache, RayCache) and cache.backend in ("numba", "cuda")
    if params is None or not (
        numba_cache or (not has_cache(analysis) and can_recomposite(analysis))
    ):
        return {e: _without(analysis, spec, e, mask) for e, mask in pixels.items()}
    variants, shape = [], analysis.accumulated.shape
    for e, mask in pixels.items():
        ops = list(params["opacities"])
        ops[e] = 0.0
        variants.append((ops, np.flatnonzero(mask)))
    if numba_cache:  # one set-up of the materials and light for all the layers
        rgbas = reevaluate_rgba(cache, variants, colours=params["colours"],
                                lighting=params["lighting"],
                                light_direction=params["light_direction"])  # fmt: skip
    else:
        rgbas = rewalk_rgba(analysis, variants)
    bg = np.asarray(tuple(spec.background), np.float64)
    out = {}
    for (e, _), (_, rays), rgba in zip(pixels.items(), variants, rgbas, strict=True):
        y = np.zeros(shape[0] * shape[1])
        y[rays] = np.clip(_composite(np.asarray(rgba, np.float64), bg), 0.0, 1.0)
        out[e] = y.reshape(shape)
    return out


def covered_transmittance(
    analysis, spec, structure: str, *, threshold: float = 0.05, contrast: str = "michelson"
) -> CoveredTransmittance:
    """TAP transmittance of ``structure`` over the layers it covers (see the module docstring).

    Parameters
    ----------
    analysis : RayAnalysis
        An engine analysis (with a re-evaluation cache, or without one: the affected rays
        are then walked again, the same luminance).
    spec : StructureSpec
        The spec of the analysis (names must match; its background enters the luminance).
    structure : str
        Name of the layer.
    threshold : float, optional
        Footprint threshold of :func:`~.regions.layer_footprints` (default 0.05, as
        :func:`~.transparency.transparency`).
    contrast : {"michelson", "range"}, optional
        TAP contrast (default Michelson, Eq. 7).

    Returns
    -------
    CoveredTransmittance

    Raises
    ------
    DVRInputError
        If ``structure`` is not a structure of ``spec``, ``contrast`` is unknown or the analysis
        can be neither re-composited nor walked again (not made by the engine).

    Examples
    --------
    >>> import numpy as np
    >>> from dvr_perception.rays import Camera
    >>> from dvr_perception.rays.engine import analyze
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> from dvr_perception.structures.spec import RenderSettings
    >>> from dvr_perception.volume import Volume
    >>> lab = np.zeros((12, 16, 16), np.uint8)
    >>> lab[2:6, 2:14, 2:8], lab[2:6, 2:14, 8:14], lab[8:10, 1:15, 1:15] = 2, 3, 1
    >>> spec = StructureSpec((Structure("veil", 0.3, (0.8, 0.8, 0.8), label=1),
    ...                       Structure("light", 1.0, (0.4, 0.4, 0.4), label=2),
    ...                       Structure("dark", 1.0, (0.1, 0.1, 0.1), label=3)),
    ...                      rendering=RenderSettings(shade=False))
    >>> vol = Volume(np.zeros(lab.shape, np.uint8), labels=lab)
    >>> a = analyze(vol, spec, Camera.from_view(vol.bounds, width=32, height=32))
    >>> res = covered_transmittance(a, spec, "veil")
    >>> res.pixels > 0, 0.0 < res.alpha < 1.0
    (True, True)
    """
    if contrast not in ("michelson", "range"):
        raise DVRInputError(f"contrast must be 'michelson' or 'range', got {contrast!r}")
    accumulated = _accumulated(analysis)
    visible = _visible(analysis, accumulated)
    names = _names(analysis, spec, visible.shape[0])
    if structure not in names:
        raise DVRInputError(f"structure: expected one of {list(names)}, got {structure!r}")
    k = names.index(structure)
    fp = layer_footprints(visible, threshold=threshold)
    covered = fp[k] & np.delete(fp, k, axis=0).any(axis=0)
    n = int(np.count_nonzero(covered))
    if n == 0:
        why = f"no pixel shows {structure!r} over another layer"
        return CoveredTransmittance(structure, float("nan"), 0, contrast, why)
    lum_a = _without(analysis, spec, k)[covered]
    y, _ = _image_luminance(analysis, spec, accumulated.shape)
    lo, hi = luminance_range(lum_a)
    if hi - lo < DENOMINATOR_EPS:
        why = f"what {structure!r} covers has no luminance contrast without it"
        return CoveredTransmittance(structure, float("nan"), n, contrast, why)
    alpha = transmitted_tap(y[covered], lum_a, contrast)
    return CoveredTransmittance(structure, float(alpha), n, contrast)
