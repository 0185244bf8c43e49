r"""Transparency deviation of a rendering: perceived versus expected layer opacity (Sec. 4.3).

Pipeline (all luminances are linear CIE Y of ``rgba`` composited over ``spec.background``):

1. **Layers.** A structure's footprint is where its absolute visible opacity exceeds
   ``threshold`` (:func:`~.regions.layer_footprints`); pixels with the same layer set form
   sub-regions (:func:`~.regions.subregions`), and layer pairs are related as *separate*,
   *touch*, *enclose* or *overlap* (:func:`~.regions.layer_relations`).
2. **Reference regions** are looked up by layer set: the luminance ``I_X`` of a set ``X`` is the
   mean over the *union of all sub-regions whose layer set is exactly X* (not only those
   adjacent to the evaluated region), and TAP uses all pixels of that union as samples.  A set
   absent from the image makes the layer **undetermined** (reported, excluded, never guessed).
3. **Enclosers.** In a region with layer set ``S``, a layer ``e`` of ``S`` that encloses some
   layer and, within ``S``, encloses or is enclosed by every other layer is part of the
   region's *enclosing context* ``E``; the others are its *active* layers.  An encloser's
   transmittance is the same in all its regions (Case 2 for its plain view, kept in Case 3):
   following the paper, its plain view (layer set ``{e}`` plus the layers enclosing ``e``) is
   the background ``A`` and all pixels where ``e`` and a layer it encloses are present are
   treated as the transparent region ``P``: ``alpha = C(P) / C(A)`` (TAP, Eq. 6-7).
4. **Active layers** (every reference set below is taken together with ``E``, i.e. enclosing
   layers are ignored as in the paper):

   * none or one active layer ``i`` without an *overlap* partner: Case 1, no transmittance;
   * one active layer ``i`` overlapping others (Case 2): Eq. 8 against the partner ``j`` with
     the largest overlap whose references exist, Metelli (Eq. 5) on ``P = {i, j}``, ``Q =
     {i}``, ``A = {j}``, ``B = {}`` and TAP ``C(P) / C(A)``;
   * two overlapping active layers (Case 3): the same Eq. 8 for each of them;
   * three or more active layers (Case 3): the generalised Metelli Eq. 9 for each.

   In Eq. 8, ``h`` comes from the robust luminance range of the evaluated region; when one of
   Metelli and TAP is undetermined (denominator below ``1e-3``) the other is used alone.
5. Transmittances are clipped to [0, 1] (reported), mapped through the ``calibration`` curve
   and compared with each structure's expected opacity (``Structure.target_opacity``):
   ``delta_t = sum_i (1 - alpha_t(i) - o_i)^2`` (Eq. 10), and
   ``E_t = sum_r w_r delta_t(r)`` (Eq. 11) over the non-empty regions ``R``, with ``w_r`` the
   region's share of the non-empty area.  The paper writes both ``1/|R|`` and area weights; taken
   literally that double normalisation makes ``E_t`` shrink as the image splits into more regions,
   so the project reads Eq. 11 as the area-weighted mean (issue: "E_t weights regions by area").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.measures.psychophysics import (
    blended_transmittance,
    calibrate,
    generalized_metelli,
    luminance_range,
    metelli_transmittance,
    tap_transmittance,
)
from dvr_perception.measures.regions import layer_footprints, layer_relations, subregions
from dvr_perception.measures.results import (
    TransparencyResult,
    _accumulated,
    _image_luminance,
    _names,
    _visible,
)

__all__ = ["transparency"]

#: A Metelli denominator or a TAP background range below this (in luminance) is "~0".
DENOMINATOR_EPS = 1e-3


@dataclass(frozen=True)
class _Estimate:
    """A transmittance with its method, or the reason it is undetermined."""

    alpha: float = float("nan")
    method: str | None = None
    reason: str | None = None


def _bits(layers) -> int:
    out = 0
    for k in layers:
        out |= 1 << int(k)
    return out


class _Scene:
    """Luminance, layer sets and relations of one image, with cached reference lookups."""

    def __init__(self, y, rmap, relations, names, contrast):
        self.y, self.layer_set, self.names, self.contrast = y, rmap.layer_set, names, contrast
        k = len(names)
        self.encloses = np.zeros((k, k), dtype=bool)  # [e, k]: e encloses k
        self.kind: dict[tuple[int, int], str] = {}
        partners: dict[int, list[tuple[int, int]]] = {i: [] for i in range(k)}
        for (i, j), rel in relations.items():
            self.kind[(i, j)] = self.kind[(j, i)] = rel.kind
            if rel.kind == "enclose":
                self.encloses[rel.encloser, rel.enclosed] = True
            elif rel.kind == "overlap":
                partners[i].append((-rel.intersection, j))
                partners[j].append((-rel.intersection, i))
        self.partners = {i: [j for _, j in sorted(p)] for i, p in partners.items()}
        self._masks: dict[int, np.ndarray] = {}
        self._enclosers: dict[int, _Estimate] = {}

    def label(self, bits: int) -> str:
        names = [n for k, n in enumerate(self.names) if bits >> k & 1]
        return "{" + ", ".join(names) + "}"

    def mask(self, bits: int) -> np.ndarray:
        if bits not in self._masks:
            self._masks[bits] = self.layer_set == np.uint32(bits)
        return self._masks[bits]

    def missing(self, sets) -> str | None:
        absent = [self.label(b) for b in sets if not self.mask(b).any()]
        if not absent:
            return None
        return "no region shows exactly the layer set(s) " + ", ".join(dict.fromkeys(absent))

    def mean(self, bits: int) -> float:
        return float(self.y[self.mask(bits)].mean())

    def tap(self, lum_p: np.ndarray, lum_a: np.ndarray) -> float:
        lo, hi = luminance_range(lum_a)
        if hi - lo < DENOMINATOR_EPS:
            return float("nan")
        return tap_transmittance(lum_p, lum_a, contrast=self.contrast)

    def encloser(self, e: int) -> _Estimate:
        """TAP transmittance of an enclosing layer: enclosed part ``P`` over plain view ``A``."""
        if e not in self._enclosers:
            self._enclosers[e] = self._encloser(e)
        return self._enclosers[e]

    def _encloser(self, e: int) -> _Estimate:
        plain = _bits([e, *np.flatnonzero(self.encloses[:, e])])
        inner = np.uint32(_bits(np.flatnonzero(self.encloses[e])))
        in_e = ((self.layer_set >> np.uint32(e)) & 1).astype(bool)
        lum_p = self.y[in_e & ((self.layer_set & inner) != 0)]
        head = f"enclosing layer {self.names[e]}: "
        why = self.missing([plain])
        if why is not None:
            return _Estimate(reason=head + why)
        if lum_p.size == 0:
            return _Estimate(reason=head + "no pixel shows it with a layer it encloses")
        alpha = self.tap(lum_p, self.y[self.mask(plain)])
        if np.isnan(alpha):
            return _Estimate(
                reason=head + f"its plain view {self.label(plain)} has no luminance contrast "
                "(TAP denominator ~0)"
            )
        return _Estimate(alpha=alpha, method="tap")

    def pair(self, i: int, j: int, base: int, region_lum: np.ndarray) -> _Estimate:
        """Eq. 8 for layer ``i`` over the bipartite background given by layer ``j``."""
        p, q, a, b = base | 1 << i | 1 << j, base | 1 << i, base | 1 << j, base
        why = self.missing([p, q, a, b])
        if why is not None:
            return _Estimate(reason=f"Eq. 8 with {self.names[j]}: {why}")
        met = float(
            metelli_transmittance(
                self.mean(p), self.mean(q), self.mean(a), self.mean(b), eps=DENOMINATOR_EPS
            )
        )
        tap = self.tap(self.y[self.mask(p)], self.y[self.mask(a)])
        if np.isnan(met) and np.isnan(tap):
            return _Estimate(
                reason=f"Eq. 8 with {self.names[j]}: Metelli denominator I{self.label(a)} - "
                f"I{self.label(b)} and TAP contrast of {self.label(a)} are ~0"
            )
        lo, hi = luminance_range(region_lum)
        alpha = float(blended_transmittance(met, tap, hi - lo))
        if np.isnan(tap) or hi - lo == 0.0:
            method = "metelli"
        elif np.isnan(met) or hi - lo >= 1.0:
            method = "tap"
        else:
            method = "blend"
        return _Estimate(alpha=alpha, method=method)

    def generalized(self, i: int, active: list[int], base: int) -> _Estimate:
        """Eq. 9 for layer ``i`` of three or more overlapping active layers."""
        every = _bits(active)
        sets = [base | every, base | 1 << i, base | (every & ~(1 << i)), base]
        why = self.missing(sets)
        if why is not None:
            return _Estimate(reason=f"Eq. 9: {why}")
        alpha = float(generalized_metelli(*(self.mean(s) for s in sets), eps=DENOMINATOR_EPS))
        if np.isnan(alpha):
            return _Estimate(
                reason=f"Eq. 9: denominator I{self.label(sets[2])} - I{self.label(sets[3])} ~0"
            )
        return _Estimate(alpha=alpha, method="generalized")

    def evaluate(self, layers: frozenset, region_lum: np.ndarray, notes: list[str]):
        """Estimates ``{layer: _Estimate}`` for the layers of one region (Case 1-3)."""
        enc = {
            e
            for e in layers
            if self.encloses[e].any()
            and all(self.encloses[e, k] or self.encloses[k, e] for k in layers - {e})
        }
        active, base = sorted(layers - enc), _bits(enc)
        out = {e: self.encloser(e) for e in sorted(enc)}
        if len(active) == 1:
            i = active[0]
            reasons = []
            for j in self.partners[i]:
                est = self.pair(i, j, base, region_lum)
                if est.reason is None:
                    out[i] = est
                    break
                reasons.append(est.reason)
            else:
                if reasons:
                    out[i] = _Estimate(reason="; ".join(reasons))
        elif len(active) == 2:
            i, j = active
            if self.kind.get((i, j)) == "overlap":
                out[i] = self.pair(i, j, base, region_lum)
                out[j] = self.pair(j, i, base, region_lum)
            else:
                notes.append(
                    f"layers {self.names[i]} and {self.names[j]} share a region but are "
                    f"{self.kind.get((i, j), 'unrelated')}; treated as Case 1 there"
                )
        elif len(active) >= 3:
            for i in active:
                out[i] = self.generalized(i, active, base)
        return out


def _check_options(spec, contrast, calibration):
    if spec is None or not hasattr(spec, "structures"):
        raise DVRInputError("spec is required: a StructureSpec giving the expected opacities")
    if contrast not in ("michelson", "range"):
        raise DVRInputError(f"contrast must be 'michelson' or 'range', got {contrast!r}")
    if calibration is not None:
        try:
            calibrate(0.5, calibration)
        except DVRInputError as err:
            raise DVRInputError(f"calibration: {err}") from None


def transparency(
    analysis,
    spec,
    *,
    threshold: float = 0.05,
    calibration=None,
    tolerance: float = 0.02,
    contrast: str = "michelson",
) -> TransparencyResult:
    """Transparency deviation ``E_t`` of a rendering (Eq. 5-11, rules of Sec. 4.3.2).

    Parameters
    ----------
    analysis : RayAnalysis
        Ray analysis with ``visible`` (K, H, W), ``accumulated`` (H, W), ``rgba`` (H, W, 4,
        premultiplied; or ``image``) and ``names``.
    spec : StructureSpec
        Structures (names must match ``analysis.names``; ``target_opacity`` is the expected
        opacity) and the background colour entering the luminance.
    threshold : float, optional
        A structure is a layer of a pixel where its visible opacity exceeds this (default
        0.05, see :func:`~.regions.layer_footprints`).
    calibration : pair of array_like (x, y), optional
        Knots of a monotone curve mapping measured to perceived transmittance (see
        :func:`~.psychophysics.calibrate`); ``None`` is the identity.
    tolerance : float, optional
        Footprint fraction forgiven by the layer relations (default 0.02).
    contrast : {"michelson", "range"}, optional
        TAP contrast: Michelson (Eq. 7, default) or luminance range (Eq. 6).

    Returns
    -------
    TransparencyResult
        ``E_t``, the per-pixel ``deviation``, the regions with their transmittances, methods
        and ``delta_t``, relations, per-structure perceived transparency and the undetermined
        (region, layer) pairs with reasons; see the module docstring for the rules.

    Raises
    ------
    DVRInputError
        If a field is missing or malformed, ``spec`` is missing or its names differ, or an
        option is out of range.

    Warns
    -----
    DVRWarning
        If ``visible`` does not sum to ``accumulated`` or ``rgba`` is not premultiplied.
    """
    _check_options(spec, contrast, calibration)
    accumulated = _accumulated(analysis)
    visible = _visible(analysis, accumulated)
    names = _names(analysis, spec, visible.shape[0])
    expected = [float(s.target_opacity) for s in spec.structures]
    y, notes = _image_luminance(analysis, spec, accumulated.shape)
    footprints = layer_footprints(visible, threshold=threshold)
    rmap = subregions(footprints)
    relations = layer_relations(footprints, tolerance=tolerance)
    scene = _Scene(y, rmap, relations, names, contrast)

    flat = rmap.region_id.ravel()
    counts = np.bincount(flat, minlength=len(rmap.regions))
    region_lum = np.split(y.ravel()[np.argsort(flat, kind="stable")], np.cumsum(counts)[:-1])
    regions, undetermined, deltas = [], [], np.zeros(len(rmap.regions))
    sums = {n: [0.0, 0.0] for n in names}  # area-weighted alpha sum, area
    reasons: dict[str, list[str]] = {n: [] for n in names}
    for region in rmap.regions:
        entry = {
            "id": region.id,
            "layers": [names[k] for k in sorted(region.layers)],
            "kind": region.kind,
            "area_fraction": region.area_fraction,
            "transmittance": {},
            "measured": {},
            "method": {},
            "clipped": {},
            "undetermined": {},
            "delta_t": 0.0,
        }
        estimates = scene.evaluate(region.layers, region_lum[region.id], notes)
        for k, est in estimates.items():
            name = names[k]
            if est.reason is not None:
                entry["undetermined"][name] = est.reason
                undetermined.append({"region": region.id, "structure": name, "reason": est.reason})
                if est.reason not in reasons[name]:
                    reasons[name].append(est.reason)
                continue
            measured = min(max(est.alpha, 0.0), 1.0)
            if measured != est.alpha:
                entry["clipped"][name] = est.alpha
            alpha_t = float(calibrate(measured, calibration))
            entry["measured"][name] = measured
            entry["transmittance"][name] = alpha_t
            entry["method"][name] = est.method
            deltas[region.id] += (1.0 - alpha_t - expected[k]) ** 2
            sums[name][0] += region.area_fraction * alpha_t
            sums[name][1] += region.area_fraction
        entry["delta_t"] = float(deltas[region.id])
        regions.append(entry)

    n_clipped = sum(len(r["clipped"]) for r in regions)
    if n_clipped:
        notes.append(f"{n_clipped} transmittance(s) outside [0, 1] were clipped (see 'clipped')")
    nonempty = [r for r in rmap.regions if r.kind != "empty"]
    if not nonempty:
        e_t = 0.0
        notes.append("no non-empty region (no layer above the threshold); E_t = 0")
    else:
        total_area = sum(r.area_fraction for r in nonempty)
        e_t = float(sum(r.area_fraction * deltas[r.id] for r in nonempty) / total_area)
    if not any(r["transmittance"] for r in regions):
        notes.append("no region has a determinable layer transmittance; E_t = 0")

    per_structure = {}
    for k, name in enumerate(names):
        total, area = sums[name]
        alpha = total / area if area > 0 else None
        per_structure[name] = {
            "perceived_transparency": alpha,
            "perceived_opacity": None if alpha is None else 1.0 - alpha,
            "expected_opacity": expected[k],
            "undetermined_reasons": reasons[name],
        }
    relation_out = {
        (names[i], names[j]): {
            "kind": rel.kind,
            "encloser": None if rel.encloser is None else names[rel.encloser],
        }
        for (i, j), rel in relations.items()
    }
    return TransparencyResult(
        E_t=e_t,
        deviation=deltas[rmap.region_id].astype(np.float32),
        region_id=rmap.region_id,
        layer_set=rmap.layer_set,
        regions=regions,
        relations=relation_out,
        per_structure=per_structure,
        undetermined=undetermined,
        notes=tuple(dict.fromkeys(notes)),
    )
