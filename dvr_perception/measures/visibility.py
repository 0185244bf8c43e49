r"""Visibility deviation of a rendering: visible against target opacity, on one scale (Sec. 4.1).

For every ray ``r`` and structure ``s`` the analysis provides the **visible** opacity
``visible(s, r) = sum_{i in s} a_i T_i`` (what the structure contributes to the pixel, after
occlusion) and the **assigned** opacity ``sum_{i in s} a^w_i`` (the importance-based opacities
of its samples, ignoring occlusion).  Following the project's decision D1 (the paper: "the
visibility of voxels is always lower than its initially assigned opacity", so both live on one
scale):

* ``alpha_v(s, r) = visible(s, r)`` (not normalised);
* ``alpha_o(s, r) = c(s, r) * A_imp(r)``, where ``A_imp(r)`` is the accumulated opacity of the
  ray rendered with every structure's opacity equal to its importance (fixed for a view:
  ``analysis.importance_accumulated``) and ``c(s, r)`` the **target composition** of the ray:

  - ``composition="importance"`` (default): ``c = imp_s p(s, r) / sum_s' imp_s' p(s', r)``
    with the presence weight ``p(s, r) = 1 - exp(-assigned(s, r) / presence_scale)``, which
    saturates with the structure's occlusion-free opacity on the ray (a ray that grazes a
    structure does not count as full presence; ``presence_scale`` 0.05 by default);
  - ``composition="thickness"`` (the paper read literally): ``c = assigned(s, r) / sum_s'
    assigned(s', r)``, the thickness-weighted share.

The ray deviation (Eq. 2) ``delta_v(r) = sum_s |alpha_o(s, r) - alpha_v(s, r)|`` lies in
[0, 2]; ``E_v`` is its mean over the rays that carry assigned opacity.  Fading every opacity
towards 0 leaves ``alpha_o`` where it is and raises ``E_v``: the measure has no trivial
minimiser.  At the importance opacities, with the importance composition, a ray through one
structure has ``delta_v = 0``.
"""

from __future__ import annotations

import numpy as np

from dvr_perception._numba import kernels
from dvr_perception.errors import DVRInputError
from dvr_perception.measures.results import (
    VisibilityResult,
    _accumulated,
    _assigned,
    _names,
    _visible,
)

__all__ = ["COMPOSITIONS", "PRESENCE_SCALE", "target_opacity", "visibility"]

#: The target compositions ``c(s, r)`` of :func:`target_opacity`.
COMPOSITIONS = ("importance", "thickness")
#: Occlusion-free opacity at which a structure's presence weight reaches 1 - 1/e.
PRESENCE_SCALE = 0.05


def _check_composition(composition, presence_scale) -> None:
    if composition not in COMPOSITIONS:
        raise DVRInputError(f"composition must be one of {COMPOSITIONS}, got {composition!r}")
    ok = isinstance(presence_scale, (int, float, np.floating, np.integer)) and not isinstance(
        presence_scale, bool
    )
    if not ok or not np.isfinite(presence_scale) or presence_scale <= 0:
        raise DVRInputError(f"presence_scale must be a positive number, got {presence_scale!r}")


def target_composition(
    assigned, importance, *, composition: str = "importance", presence_scale=PRESENCE_SCALE,
    fixed=None,
) -> np.ndarray:  # fmt: skip
    """Target composition ``c(s, r)`` of every ray (module docstring); 0 on empty rays.

    Parameters
    ----------
    assigned : ndarray, shape (K, ...)
        Occlusion-free (importance-based) opacity of each structure on each ray.
    importance : array_like, shape (K,)
        The structures' importances.
    composition : {"importance", "thickness"}
    presence_scale : float
    fixed : array_like, shape (K,), optional
        Lens targets: ``c`` of structure ``s`` is ``fixed[s]`` wherever the structure is on the
        ray (NaN: no target); the others are rescaled to fill ``1 - sum(fixed)``, and the
        composition is normalised again.

    Returns
    -------
    ndarray, shape (K, ...)
        Non-negative, summing to 1 over the structures on rays with assigned opacity.

    Examples
    --------
    >>> c = target_composition(np.array([[0.9], [0.05]]), [0.2, 0.8])
    >>> np.round(c[:, 0], 3).tolist()   # thin but important: more than its thickness share
    [0.283, 0.717]
    >>> np.round(target_composition(np.array([[0.9], [0.05]]), [0.2, 0.8],
    ...                             composition="thickness")[:, 0], 3).tolist()
    [0.947, 0.053]
    """
    _check_composition(composition, presence_scale)
    a = np.maximum(np.asarray(assigned, np.float64), 0.0)
    shape = (-1,) + (1,) * (a.ndim - 1)
    if composition == "importance":
        imp = np.asarray(importance, np.float64).reshape(shape)
        w = imp * -np.expm1(-a / float(presence_scale))
    else:
        w = a
    c = _normalise(w, w.sum(axis=0))
    if fixed is None:
        return c
    t = np.asarray(fixed, np.float64).reshape(shape)
    targeted = ~np.isnan(t)
    if not targeted.any():
        return c
    on = c > 0
    pinned = np.where(on & targeted, np.nan_to_num(t), 0.0)
    free = np.where(targeted, 0.0, c)
    scale = np.zeros(c.shape[1:])
    free_sum = free.sum(axis=0)
    np.divide(np.clip(1.0 - pinned.sum(axis=0), 0.0, None), free_sum, out=scale,
              where=free_sum > 0)  # fmt: skip
    out = pinned + free * scale
    return np.where(out.sum(axis=0) > 0, _normalise(out, out.sum(axis=0)), c)


def target_opacity(analysis, spec, **options) -> np.ndarray:
    """``alpha_o = c * A_imp`` (K, H, W) of an analysis: what each structure should show.

    ``options`` go to :func:`target_composition`.  ``A_imp`` is the analysis's
    ``importance_accumulated``; an analysis without it is taken to be rendered at the
    importances (``A_imp = accumulated``).
    """
    accumulated = _accumulated(analysis)
    assigned = _assigned(analysis, accumulated.shape)
    importance = _importance(spec, assigned.shape[0])
    c = target_composition(assigned, importance, **options)
    return c * _importance_accumulated(analysis, accumulated)[None]


def _importance(spec, k: int) -> np.ndarray:
    if spec is None:
        return np.ones(k)
    return np.array([float(s.importance) for s in spec.structures])


def _importance_accumulated(analysis, accumulated: np.ndarray) -> np.ndarray:
    value = getattr(analysis, "importance_accumulated", None)
    if value is None:
        return accumulated
    arr = np.asarray(value, np.float64)
    if arr.shape != accumulated.shape or not np.all(np.isfinite(arr)):
        raise DVRInputError(
            f"analysis.importance_accumulated must be a finite array of shape "
            f"{accumulated.shape} (an analysis made with occlusion_free=True)"
        )
    return np.clip(arr, 0.0, 1.0)


def _normalise(x: np.ndarray, total: np.ndarray) -> np.ndarray:
    out = np.zeros_like(x)
    np.divide(x, total, out=out, where=np.broadcast_to(total > 0, x.shape))
    return np.clip(out, 0.0, 1.0)


def _presence(analysis, assigned: np.ndarray, visible: np.ndarray):
    """Per structure ``k``, a function giving its (H, W) bool mask of rays that meet it.

    Uses the ``present`` bitmask when the analysis has one (bit ``k`` of each pixel, read one
    structure at a time), else "any assigned or visible opacity".
    """
    bits = _presence_bits(analysis, assigned)
    if bits.size == 0:
        return lambda k: (assigned[k] > 0) | (visible[k] > 0)
    bits = bits.reshape(assigned.shape[1:])
    return lambda k: ((bits >> np.uint64(k)) & np.uint64(1)).astype(bool)


def _check_bins(bins) -> int:
    if isinstance(bins, (bool, np.bool_)) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise DVRInputError(f"bins must be a positive integer, got {bins!r}")
    return int(bins)


def visibility(
    analysis, spec=None, *, bins: int = 20, composition: str = "importance",
    presence_scale: float = PRESENCE_SCALE,
) -> VisibilityResult:  # fmt: skip
    """Visibility deviation ``E_v`` and per-structure visibility histograms (Eq. 1-2, D1).

    Parameters
    ----------
    analysis : RayAnalysis
        Ray analysis with ``visible``, ``assigned`` (K, H, W), ``accumulated`` (H, W),
        ``names`` and, from the engine, ``importance_accumulated`` (``A_imp``; without it the
        analysis is taken to be rendered at the importances, ``A_imp = accumulated``, and a
        note says so); ``present`` is used when there (else presence is "any assigned or
        visible opacity").
    spec : StructureSpec, optional
        Gives the importances (without it all importances are equal); its structure names
        must equal ``analysis.names``.
    bins : int, optional
        Number of histogram bins on [0, 1] (default 20).
    composition : {"importance", "thickness"}, optional
        Target composition ``c(s, r)`` (module docstring); default ``"importance"``.
    presence_scale : float, optional
        Scale of the presence weight of the importance composition (default 0.05).

    Returns
    -------
    VisibilityResult
        ``E_v``; the per-ray ``deviation`` (0 on empty rays); the ``nonempty`` mask; the
        per-ray ``target`` opacities ``alpha_o`` (K, H, W); per structure the image-wide
        ``visible_share`` (``sum_r visible[s] / sum_r sum_s visible``), ``target_share``
        (``sum_r alpha_o[s] / sum_r sum_s alpha_o``), the thickness ``assigned_share``
        (``sum_r assigned[s] / sum_r sum_s assigned``; ``analyze``'s default skipping walk
        counts ``assigned`` up to saturation per ray, ``stats["assigned_cap"]``, DECISIONS
        D8: ``exact=True`` or the cache for the share beyond it), ``visible_opacity`` and
        ``target_opacity`` (mean ``alpha_v`` and ``alpha_o`` over the non-empty rays),
        histograms of the per-ray ``alpha_v`` and ``alpha_o`` over the rays where the
        structure is present and their count; the ``bin_edges``, ``composition`` and
        ``notes``.

    Raises
    ------
    DVRInputError
        If a field is missing, non-finite, negative or of the wrong shape, the names disagree
        with the spec, or an option is out of range.

    Warns
    -----
    DVRWarning
        If ``visible`` does not sum over the structures to ``accumulated``.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> ray = SimpleNamespace(  # one ray: an opaque front structure hides the back one
    ...     visible=np.array([[[0.9]], [[0.0]]]), assigned=np.array([[[2.0]], [[1.0]]]),
    ...     accumulated=np.array([[0.9]]), importance_accumulated=np.array([[0.9]]),
    ...     names=("front", "back"))
    >>> res = visibility(ray)  # equal importances, both fully present: 0.45 each
    >>> round(res.E_v, 6)  # |0.45 - 0.9| + |0.45 - 0|
    0.9
    >>> round(visibility(ray, composition="thickness").E_v, 6)  # 0.6 and 0.3 wanted
    0.6
    """
    nbins = _check_bins(bins)
    _check_composition(composition, presence_scale)
    accumulated = _accumulated(analysis)
    core = _core_numba if kernels("dvr_perception.measures._kernels") else _core_numpy
    native = core is _core_numba  # the kernel reads an engine's float32 fields in float64
    visible = _visible(analysis, accumulated, native=native)
    assigned = _assigned(analysis, accumulated.shape, native=native)
    if assigned.shape[0] != visible.shape[0]:
        raise DVRInputError(
            f"analysis.assigned has {assigned.shape[0]} structures, "
            f"analysis.visible {visible.shape[0]}"
        )
    names = _names(analysis, spec, visible.shape[0])
    notes: list[str] = []
    stats = getattr(analysis, "stats", None)
    cap = stats.get("assigned_cap") if isinstance(stats, dict) else None
    if cap is not None and composition == "thickness":  # the skipping walk (DECISIONS D8)
        raise DVRInputError(
            f"composition='thickness' reads the occlusion-free opacity beyond saturation, "
            f"but this analysis holds it capped at {cap} (analyze(..., exact=False) without "
            f"the cache); analyse with exact=True or build_cache=True"
        )
    if getattr(analysis, "importance_accumulated", None) is None:
        notes.append("no importance_accumulated: the analysis is taken to be rendered at the "
                     "importances (A_imp = accumulated)")  # fmt: skip
    if spec is None and composition == "importance":
        notes.append("no spec: every structure has the same importance")
    a_imp = _importance_accumulated(analysis, accumulated)
    imp = _importance(spec, len(names))
    edges = np.linspace(0.0, 1.0, nbins + 1)
    target, deviation, nonempty, e_v, sums, hist, rays = core(
        analysis, visible, assigned, a_imp, imp, composition, presence_scale, edges
    )
    if e_v is None:
        e_v = 0.0
        notes.append("no ray carries assigned opacity; E_v = 0")
    vis_k, tgt_k, asg_k, vis_nz, tgt_nz = sums
    n_rays = max(int(np.count_nonzero(nonempty)), 1)
    per_structure = {}
    for k, name in enumerate(names):
        per_structure[name] = {
            "visible_share": _fraction(vis_k, k),
            "target_share": _fraction(tgt_k, k),
            "assigned_share": _fraction(asg_k, k),
            "visible_opacity": float(vis_nz[k]) / n_rays,
            "target_opacity": float(tgt_nz[k]) / n_rays,
            "histogram_visible": hist[0][k],
            "histogram_assigned": hist[1][k],
            "rays": int(rays[k]),
        }
    return VisibilityResult(
        E_v=e_v,
        deviation=deviation,
        nonempty=nonempty,
        per_structure=per_structure,
        bin_edges=edges,
        notes=tuple(notes),
        target=target,
        composition=composition,
    )


def _core_numpy(analysis, visible, assigned, a_imp, imp, composition, presence_scale, edges):
    """Targets, deviations, ``E_v`` (None without a non-empty ray), sums and histograms."""
    c = target_composition(assigned, imp, composition=composition,
                           presence_scale=presence_scale)  # fmt: skip
    target = c * a_imp[None]
    nonempty = assigned.sum(axis=0) > 0
    deviation = np.where(nonempty, np.abs(target - visible).sum(axis=0), 0.0)
    e_v = float(deviation[nonempty].mean()) if nonempty.any() else None
    present = _presence(analysis, assigned, visible)
    sums = (visible.sum(axis=(1, 2)), target.sum(axis=(1, 2)), assigned.sum((1, 2)),
            [float(v[nonempty].sum()) for v in visible],
            [float(t[nonempty].sum()) for t in target])  # fmt: skip
    nbins = len(edges) - 1
    hist: tuple[list, list] = ([], [])
    rays = []
    for k in range(len(imp)):
        on = present(k)
        # bins=nbins with a range takes numpy's uniform-bin path (no sort); the counts
        # equal those for bins=edges, which np.histogram builds the same way
        hist[0].append(np.histogram(np.clip(visible[k][on], 0, 1), bins=nbins, range=(0, 1))[0])
        hist[1].append(np.histogram(np.clip(target[k][on], 0, 1), bins=nbins, range=(0, 1))[0])
        rays.append(int(np.count_nonzero(on)))
    return (target.astype(np.float32), deviation.astype(np.float32), nonempty, e_v, sums,
            hist, rays)  # fmt: skip


def _core_numba(analysis, visible, assigned, a_imp, imp, composition, presence_scale, edges):
    """:func:`_core_numpy` in one numba pass over the rays (the per-ray numbers to the bit)."""
    from dvr_perception.measures._kernels import visibility_core

    k = visible.shape[0]
    bits = _presence_bits(analysis, assigned)
    flat = tuple(np.ascontiguousarray(x.reshape(k, -1), _kernel_dtype(x))
                 for x in (visible, assigned))  # fmt: skip
    target, deviation, nonempty, e_sum, n_on, sums, hist, rays = visibility_core(
        *flat, np.ascontiguousarray(a_imp.reshape(-1), np.float64),
        np.ascontiguousarray(imp, np.float64), float(presence_scale), composition == "thickness",
        bits, np.ascontiguousarray(edges),
    )  # fmt: skip
    shape = visible.shape[1:]
    e_v = float(e_sum) / int(n_on) if n_on else None
    return (target.reshape(k, *shape), deviation.reshape(shape), nonempty.reshape(shape), e_v,
            sums, hist, rays)  # fmt: skip


def _kernel_dtype(x: np.ndarray):
    """float32 stays float32 (the engine's fields, read in float64 inside), else float64."""
    return np.float32 if x.dtype == np.float32 else np.float64


def _presence_bits(analysis, assigned: np.ndarray) -> np.ndarray:
    """Return the ``present`` bitmask as flat uint64, checked as :func:`_presence` does."""
    present = getattr(analysis, "present", None)
    if present is None:
        return np.zeros(0, np.uint64)
    bits = np.asarray(present)
    if bits.shape != assigned.shape[1:] or not np.issubdtype(bits.dtype, np.integer):
        raise DVRInputError(
            f"analysis.present must be an integer bitmask of shape {assigned.shape[1:]}"
        )
    return np.ascontiguousarray(bits.reshape(-1).astype(np.uint64))


def _fraction(totals: np.ndarray, k: int) -> float:
    """``totals[k] / totals.sum()``, 0 when the sum is not positive."""
    total = float(totals.sum())
    return float(totals[k]) / total if total > 0 else 0.0
