"""Transmittance estimates of every sub-region, worked out once per layer set (``transparency``).

Which rule of Sec. 4.3.2 applies to a layer, and every Metelli and TAP term, depend only on the
layer set of the region (:meth:`._layer_sets._LayerSets.template`); only the Eq. 8 weight
``h = 1 - C`` depends on the region (``C`` the contrast of its robust luminance range, Eq. 7).
:func:`region_estimates` therefore evaluates each layer set once and the regions of a set
together, as arrays; :func:`region_table` gives the result as one (regions x layers) table for
callers that need numbers, not per-region records (the optimiser evaluates E_t this way many
times per stage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dvr_perception.measures._layer_sets import _group_stats
from dvr_perception.measures.psychophysics import calibrate


@dataclass(frozen=True)
class LayerEstimate:
    """One layer of one layer set, over the regions of that set (lists in the set's order).

    ``reason`` is set when the layer is undetermined (then the lists are ``None``); otherwise
    ``raw`` is the transmittance before clipping, ``measured`` clipped to [0, 1], ``alpha_t``
    after the calibration curve, and ``method`` the rule used in each region.
    """

    k: int
    reason: str | None = None
    raw: list | None = None
    measured: list | None = None
    alpha_t: list | None = None
    method: list | None = None


@dataclass(frozen=True)
class RegionEstimates:
    """Estimates of every region.

    ``sets``: per layer set, ``(region ids, [LayerEstimate, ...])``; ``layers[r]`` is region
    ``r``'s list (shared by the regions of its set) and ``position[r]`` its index in the
    lists; ``deltas``: Eq. 10 per region; ``undetermined``: the regions whose layers with a
    rule are all undetermined (they are left out of ``E_t``: an undetermined layer must not
    lower it).
    """

    sets: list
    layers: list
    position: np.ndarray
    deltas: np.ndarray
    undetermined: np.ndarray


def _contrasts(lo: np.ndarray, hi: np.ndarray, kind: str) -> np.ndarray:
    """Contrast ``C`` of many regions from their robust ranges, as ``_layer_sets._contrast``."""
    if kind == "range":
        return hi - lo
    total = hi + lo
    return np.divide(hi - lo, total, out=np.zeros(lo.shape), where=total > 0)


def _blend_many(met: float, tap: float, c: np.ndarray):
    """Eq. 8 for many regions: ``h = 1 - C`` (as ``_layer_sets._blended``, elementwise)."""
    if math.isnan(met):
        alpha = np.full(c.shape, tap)
    elif math.isnan(tap):
        alpha = np.full(c.shape, met)
    else:
        h = 1.0 - c
        alpha = h * met + (1.0 - h) * tap
    metelli = math.isnan(tap) | (c == 0.0)
    only_tap = math.isnan(met) | (c >= 1.0)
    method = np.where(metelli, "metelli", np.where(only_tap, "tap", "blend"))
    return alpha, method.tolist()


def region_estimates(layer_sets, rmap, y, expected, calibration, notes: list) -> RegionEstimates:
    """Evaluate every region of ``rmap`` (see the module docstring); notes go to ``notes``."""
    n = len(rmap.regions)
    _, mean, std = _group_stats(y.ravel(), rmap.region_id.ravel(), n)
    # mu -/+ 2 sigma clipped to [0, 1]: the robust range of Eq. 6-7 of every region
    lo = np.maximum(mean - 2.0 * std, 0.0)
    hi = np.minimum(mean + 2.0 * std, 1.0)
    contrast = _contrasts(lo, hi, layer_sets.contrast)  # C of Eq. 7: Eq. 8's h = 1 - C
    groups: dict[frozenset, list[int]] = {}  # layer set -> its regions, by first region
    for region in rmap.regions:
        groups.setdefault(region.layers, []).append(region.id)
    deltas = np.zeros(n)
    undetermined = np.zeros(n, bool)
    position = np.empty(n, np.int64)
    layers: list = [None] * n
    sets = []
    for layer_set, members in groups.items():
        ids = np.asarray(members, np.int64)
        position[ids] = np.arange(ids.size)
        items, set_notes = layer_sets.template(layer_set)
        notes.extend(set_notes)
        out = []
        for k, fixed, met, tap in items:
            if fixed is not None and fixed.reason is not None:
                out.append(LayerEstimate(k, reason=fixed.reason))
                continue
            if fixed is not None:
                raw, method = np.full(ids.size, fixed.alpha), [fixed.method] * ids.size
            else:
                raw, method = _blend_many(met, tap, contrast[ids])
            measured = np.clip(raw, 0.0, 1.0)
            alpha_t = measured
            if calibration is not None:
                alpha_t = np.asarray(calibrate(measured, calibration), np.float64)
            deltas[ids] += (1.0 - alpha_t - expected[k]) ** 2
            lists = {"raw": raw, "measured": measured, "alpha_t": alpha_t}
            out.append(LayerEstimate(k, method=method, **{f: v.tolist() for f, v in lists.items()}))
        for r in members:
            layers[r] = out
        if out and all(lay.reason is not None for lay in out):
            undetermined[ids] = True
        sets.append((ids, out))
    return RegionEstimates(sets, layers, position, deltas, undetermined)


def region_table(est: RegionEstimates, rmap, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(alpha_t, skip)`` of every region as arrays.

    ``alpha_t``: (regions, k) calibrated transmittances, NaN where a layer is absent or
    undetermined; ``skip``: (regions,) mask of the regions left out of ``E_t``, those without
    layers and those whose layers are all undetermined.
    """
    alpha = np.full((len(rmap.regions), k), np.nan)
    for ids, lays in est.sets:
        for lay in lays:
            if lay.reason is None:
                alpha[ids, lay.k] = lay.alpha_t
    empty = np.array([r.kind == "empty" for r in rmap.regions], bool)
    return alpha, empty | est.undetermined
