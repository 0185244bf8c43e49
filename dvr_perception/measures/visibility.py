r"""Visibility deviation of a rendering: assigned versus visible opacity shares (Sec. 4.1).

For every ray ``r`` and structure ``s`` the analysis provides the **visible** opacity
``sum_{i in s} a_i T_i`` (what the structure contributes to the pixel, after occlusion) and the
**assigned** opacity ``sum_{i in s} a^w_i`` (the importance-based opacities of its samples,
ignoring occlusion).  Their normalised forms are

* ``alpha_v(s, r) = visible(s, r) / accumulated(r)`` (the visible share, 0 where nothing is
  accumulated), and
* ``alpha_o(s, r) = assigned(s, r) / sum_s assigned(s, r)`` (the assigned share).

Both sum to 1 over the structures on a non-empty ray, so the ray deviation (Eq. 2)

.. math:: \delta_v(r) = \sum_s |\alpha_o(s, r) - \alpha_v(s, r)|

lies in [0, 2]: 0 when every structure is seen in proportion to its intended opacity, 2 when
the visible and the intended structures are disjoint.  ``E_v`` is its mean over the non-empty
rays (those with any assigned opacity).
"""

from __future__ import annotations

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.measures.results import (
    VisibilityResult,
    _accumulated,
    _assigned,
    _names,
    _visible,
)
from dvr_perception.rays._results import engine_made

__all__ = ["visibility"]


def _share(analysis, prop: str, shape: tuple[int, ...], fallback) -> np.ndarray:
    """Use the analysis' share property if it exists and fits, else compute it.

    An engine analysis' shares are finite and of the right shape by construction: not checked.
    """
    value = getattr(analysis, prop, None)
    if value is None:
        return fallback()
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.floating) or arr.dtype.itemsize > 8:
        arr = np.asarray(arr, dtype=np.float64)
    if not engine_made(analysis) and (arr.shape != shape or not np.all(np.isfinite(arr))):
        raise DVRInputError(f"analysis.{prop} must be a finite array of shape {shape}")
    # clipping before widening to float64 gives the same numbers (0 and 1 are exact)
    return np.clip(arr, 0.0, 1.0).astype(np.float64, copy=False)


def _normalise(x: np.ndarray, total: np.ndarray) -> np.ndarray:
    out = np.zeros_like(x)
    np.divide(x, total, out=out, where=np.broadcast_to(total > 0, x.shape))
    return np.clip(out, 0.0, 1.0)


def _presence(analysis, assigned: np.ndarray, visible: np.ndarray):
    """Per structure ``k``, a function giving its (H, W) bool mask of rays that meet it.

    Uses the ``present`` bitmask when the analysis has one (bit ``k`` of each pixel, read one
    structure at a time), else "any assigned or visible opacity".
    """
    present = getattr(analysis, "present", None)
    if present is None:
        return lambda k: (assigned[k] > 0) | (visible[k] > 0)
    bits = np.asarray(present)
    if bits.shape != assigned.shape[1:] or not np.issubdtype(bits.dtype, np.integer):
        raise DVRInputError(
            f"analysis.present must be an integer bitmask of shape {assigned.shape[1:]}"
        )
    bits = bits.astype(np.uint64)
    return lambda k: ((bits >> np.uint64(k)) & np.uint64(1)).astype(bool)


def _check_bins(bins) -> int:
    if isinstance(bins, (bool, np.bool_)) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise DVRInputError(f"bins must be a positive integer, got {bins!r}")
    return int(bins)


def visibility(analysis, spec=None, *, bins: int = 20) -> VisibilityResult:
    """Visibility deviation ``E_v`` and per-structure visibility histograms (Eq. 1-2).

    Parameters
    ----------
    analysis : RayAnalysis
        Ray analysis with ``visible``, ``assigned`` (K, H, W), ``accumulated`` (H, W) and
        ``names``; ``visible_share``, ``assigned_share`` and ``present`` are used when present
        (the shares are otherwise computed as in the module docstring, and presence falls back
        to "any assigned or visible opacity").
    spec : StructureSpec, optional
        If given, its structure names must equal ``analysis.names``.
    bins : int, optional
        Number of histogram bins on [0, 1] (default 20).

    Returns
    -------
    VisibilityResult
        ``E_v``, the per-ray ``deviation`` (0 on empty rays), the ``nonempty`` mask, per-structure
        image-wide shares (``sum_r visible[s] / sum_r accumulated`` and ``sum_r assigned[s] /
        sum_r sum_s assigned``) with histograms of the per-ray visible and assigned shares over
        the rays where the structure is present, the ``bin_edges`` and ``notes``.

    Raises
    ------
    DVRInputError
        If a field is missing, non-finite, negative or of the wrong shape, the names disagree
        with the spec, or ``bins`` is not a positive integer.

    Warns
    -----
    DVRWarning
        If ``visible`` does not sum over the structures to ``accumulated``.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> ray = SimpleNamespace(  # one ray: an opaque front structure hides the back one
    ...     visible=np.array([[[1.0]], [[0.0]]]), assigned=np.array([[[0.6]], [[0.2]]]),
    ...     accumulated=np.array([[1.0]]), names=("front", "back"))
    >>> round(visibility(ray).E_v, 6)  # 2 * 0.2 / (0.6 + 0.2)
    0.5
    """
    nbins = _check_bins(bins)
    accumulated = _accumulated(analysis)
    visible = _visible(analysis, accumulated)
    assigned = _assigned(analysis, accumulated.shape)
    if assigned.shape[0] != visible.shape[0]:
        raise DVRInputError(
            f"analysis.assigned has {assigned.shape[0]} structures, "
            f"analysis.visible {visible.shape[0]}"
        )
    names = _names(analysis, spec, visible.shape[0])
    total_assigned = assigned.sum(axis=0)
    v_share = _share(
        analysis, "visible_share", visible.shape, lambda: _normalise(visible, accumulated)
    )
    a_share = _share(
        analysis, "assigned_share", assigned.shape, lambda: _normalise(assigned, total_assigned)
    )

    notes: list[str] = []
    nonempty = total_assigned > 0
    deviation = np.where(nonempty, np.abs(a_share - v_share).sum(axis=0), 0.0)
    if nonempty.any():
        e_v = float(deviation[nonempty].mean())
    else:
        e_v = 0.0
        notes.append("no ray carries assigned opacity; E_v = 0")

    edges = np.linspace(0.0, 1.0, nbins + 1)
    present = _presence(analysis, assigned, visible)
    acc_sum, assigned_sum = float(accumulated.sum()), float(total_assigned.sum())
    per_structure = {}
    for k, name in enumerate(names):
        rays = present(k)
        per_structure[name] = {
            "visible_share": float(visible[k].sum()) / acc_sum if acc_sum > 0 else 0.0,
            "assigned_share": (
                float(assigned[k].sum()) / assigned_sum if assigned_sum > 0 else 0.0
            ),
            # bins=nbins with a range takes numpy's uniform-bin path (no sort); the counts
            # equal those for bins=edges, which np.histogram builds the same way
            "histogram_visible": np.histogram(v_share[k][rays], bins=nbins, range=(0, 1))[0],
            "histogram_assigned": np.histogram(a_share[k][rays], bins=nbins, range=(0, 1))[0],
            "rays": int(np.count_nonzero(rays)),
        }
    return VisibilityResult(
        E_v=e_v,
        deviation=deviation.astype(np.float32),
        nonempty=nonempty,
        per_structure=per_structure,
        bin_edges=edges,
        notes=tuple(notes),
    )
