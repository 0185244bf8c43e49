r"""Transparency deviation of a rendering: perceived versus expected layer opacity (Sec. 4.3).

Pipeline (all luminances are linear CIE Y of ``rgba`` composited over ``spec.background``):

1. **Layers.** A structure's footprint is where it *is* (decision D3), not only where it is
   seen: where its absolute visible opacity exceeds ``threshold``
   (:func:`~.regions.layer_footprints`) or its occlusion-free opacity ``assigned`` (the sum
   of its samples' importance-based opacities, occlusion ignored) exceeds ``threshold``
   times its importance.  Relative to the importance, that is where the ray crosses a
   meaningful length of the structure whatever its importance, so the layers, regions and
   relations do not change with the rendering opacities (a faint skin of importance 0.1
   rendered at 0.3 would otherwise gain and lose a rim as the optimiser moves its opacity).
   A structure hidden behind another is hence still a layer of the pixels it lies on, and
   the hiding layer is read over it (rule 3) instead of standing alone in Case 1.  Analyses
   without ``assigned`` (hand-made ones) or made with ``occlusion_free=False`` keep the
   visible footprints.  Pixels with the same layer set form sub-regions
   (:func:`~.regions.subregions`), and layer pairs are related as *separate*, *touch*,
   *enclose* or *overlap* (:func:`~.regions.layer_relations`).
2. **Reference regions** are looked up by layer set: the luminance ``I_X`` of a set ``X`` is the
   mean over the *union of all sub-regions whose layer set is exactly X* (not only those
   adjacent to the evaluated region), and TAP uses all pixels of that union as samples.  A set
   absent from the image makes the layer **undetermined** (reported, excluded, never guessed).
3. **Enclosers.** In a region with layer set ``S``, a layer ``e`` of ``S`` that encloses some
   layer and, within ``S``, encloses or is enclosed by every other layer is part of the
   region's *enclosing context* ``E``; the others are its *active* layers.  An encloser's
   transmittance is the same in all its regions (Case 2 for its plain view, kept in Case 3).
   Its transparent region ``P`` is every pixel where ``e`` and a layer it encloses are
   present, and:

   * **hidden is opaque** (D3, D7): on the pixels of ``P`` where the enclosed layers are
     hidden (their summed visible opacity is at most ``HIDDEN_FRACTION`` = 0.1 of the opacity
     they carry there: their occlusion-free opacity capped at 0.7, where presence saturates,
     times their rendering opacity over their importance), ``e`` lets nothing of them
     through, transmittance 0;
   * the rest, ``P'``, is read by TAP, ``alpha = C(P') / C(A)`` (Eq. 6-7).  By default
     (``enclosure="auto"``, decision D7) ``A`` is what ``e`` covers seen *without* it: the
     same pixels re-composited from the analysis's cache with ``e``'s opacity 0 (and the
     analysis's own opacities, colours and light), as :func:`~.covered.covered_transmittance`
     (the Fig. 9 reading) does, and only the contrast ``e`` transmits counts (``P'``
     regressed on ``A``: ``e``'s own shading texture is not transmitted contrast;
     :func:`~._layer_sets.transmitted_tap`).  A brighter or more opaque enclosing layer lowers the
     Michelson contrast of what it covers and reads as less transparent (tested against the
     closed form ``T mu / (T mu + c)``).  ``enclosure="plain"`` is the paper's Case 2: the
     plain view of ``e`` (layer set ``{e}`` plus the layers enclosing ``e``), which saturates
     at 1 where what ``e`` covers has more contrast than ``e``'s ring (a faint shell around
     contrasted blobs) and is not monotone in ``e``'s opacity; it is reported beside the
     default.  Each reading is the fallback of the other where it is missing or uniform.  An
     engine analysis without a cache makes the same view by walking those pixels again
     with ``e``'s opacity 0 (:func:`~dvr_perception.rays.engine.rewalk`), so every path gives
     the same ``E_t`` (D7); only an analysis that is neither (hand-made) reads the plain
     view, with a note, and ``"unoccluded"`` demands the re-composite (an error there).

   The estimate is the mean over ``P``: ``|P'| / |P| * C(P') / C(A)``, so hiding more of what
   it covers makes a layer more opaque, and hiding all of it gives 0 (method ``"hidden"``).
4. **Active layers** (every reference set below is taken together with ``E``, i.e. enclosing
   layers are ignored as in the paper):

   * none or one active layer ``i`` without an *overlap* partner: Case 1, no transmittance;
   * one active layer ``i`` overlapping others (Case 2): Eq. 8 against the partner ``j`` with
     the largest overlap whose references exist, Metelli (Eq. 5) on ``P = {i, j}``, ``Q =
     {i}``, ``A = {j}``, ``B = {}`` and TAP ``C(P) / C(A)``.  D3 holds here too (D7): on the
     pixels of ``P`` where ``j`` is hidden (as above), ``i`` transmits nothing, so both terms
     are read on the rest and scaled by its share of ``P`` (all hidden: 0, method
     ``"hidden"``); and TAP's contrast of ``P`` keeps only the variance that ``i``'s plain
     view ``Q`` lacks, so ``i``'s own shading texture is not transmitted contrast;
   * two overlapping active layers (Case 3): the same Eq. 8 for each of them;
   * three or more active layers (Case 3): the generalised Metelli Eq. 9 for each.

   In Eq. 8, ``h = 1 - C`` with ``C`` the contrast (Eq. 7) of the evaluated region's robust
   luminance range: the Michelson contrast ``(I_max - I_min) / (I_max + I_min)`` (decision
   D2; with ``contrast="range"`` the range ``I_max - I_min``, the Eq. 6 reading); when one of
   Metelli and TAP is undetermined (denominator below ``1e-3``) the other is used alone.
5. Transmittances are clipped to [0, 1] (reported), mapped through the ``calibration`` curve
   and compared with each structure's expected opacity (``Structure.target_opacity``):
   ``delta_t = sum_i (1 - alpha_t(i) - o_i)^2`` (Eq. 10) over the determined layers, and
   ``E_t = sum_r w_r delta_t(r)`` (Eq. 11) over the non-empty regions ``R``, with ``w_r`` the
   region's share of their area.  A region whose layers that need a transmittance are all
   undetermined is left out of ``R`` (its record says ``counted: False``): an undetermined
   layer must never lower ``E_t``.  The paper writes both ``1/|R|`` and area weights; taken
   literally that double normalisation makes ``E_t`` shrink as the image splits into more regions,
   so the project reads Eq. 11 as the area-weighted mean (issue: "E_t weights regions by area").
"""

from __future__ import annotations

from functools import partial

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.measures._estimates import region_estimates, region_table
from dvr_perception.measures._layer_sets import DENOMINATOR_EPS as DENOMINATOR_EPS  # re-export
from dvr_perception.measures._layer_sets import Carried, _LayerSets
from dvr_perception.measures.covered import _without as _luminance_without
from dvr_perception.measures.covered import _without_many, can_recomposite
from dvr_perception.measures.psychophysics import calibrate
from dvr_perception.measures.regions import _layer_set_bits, _relations, _subregions
from dvr_perception.measures.results import (
    TransparencyResult,
    _accumulated,
    _assigned,
    _image_luminance,
    _names,
    _recalled,
    _remembered,
    _visible,
)
from dvr_perception.rays._results import engine_made

__all__ = ["transparency"]

#: TAP backgrounds of an enclosing layer (see the module docstring, rule 3).
ENCLOSURES = ("auto", "plain", "unoccluded")


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


def _core(analysis, spec, threshold, calibration, tolerance, contrast, enclosure):
    """Check the inputs; find layers, regions, relations and every region's estimates."""
    _check_options(spec, contrast, calibration)
    if enclosure not in ENCLOSURES:
        raise DVRInputError(
            f"enclosure must be one of {', '.join(map(repr, ENCLOSURES))}, got {enclosure!r}"
        )
    accumulated = _accumulated(analysis)
    visible = _visible(analysis, accumulated, native=True)  # read in float64
    names = _names(analysis, spec, visible.shape[0])
    expected = [float(s.target_opacity) for s in spec.structures]
    y, notes = _image_luminance(analysis, spec, accumulated.shape)
    assigned = _occlusion_free(analysis, accumulated.shape)
    # D3: a layer where a structure is (its occlusion-free opacity), not only where it is seen
    importance = np.array([float(s.importance) for s in spec.structures])
    bits = _layer_set_bits(visible, threshold, assigned, threshold * importance)
    rmap = _subregions(bits, len(names), geometry=False)  # no bounding boxes: not reported
    relations = _relations(rmap.layer_set, len(names), tolerance)  # = layer_relations
    layer_sets = _LayerSets(y, rmap, relations, names, contrast)
    if assigned is not None:
        layer_sets.visible, layer_sets.carry = visible, _carried(analysis, spec, assigned)
    if enclosure == "unoccluded":
        enclosers = sorted({r.encloser for r in relations.values() if r.kind == "enclose"})
        layer_sets.without = {e: _luminance_without(analysis, spec, e) for e in enclosers}
    elif can_recomposite(analysis):
        layer_sets.recomposite = partial(_luminance_without, analysis, spec)
        layer_sets.recomposite_many = partial(_without_many, analysis, spec)
        layer_sets.prefer_recomposite = enclosure == "auto"
        layer_sets.prefetch({r.layers for r in rmap.regions})  # every encloser in one walk
    elif enclosure == "auto" and any(r.kind == "enclose" for r in relations.values()):
        notes.append(
            "the analysis can be neither re-composited nor walked again (no re-evaluation "
            "cache, not made by analyze): enclosing layers are read against their plain view"
        )
    est = region_estimates(layer_sets, rmap, y, expected, calibration, notes)
    return names, expected, rmap, relations, est, notes


def _core_key(analysis, spec, threshold, calibration, tolerance, contrast, enclosure):
    """Return what :func:`_core` reads besides the analysis, as a key (or ``None``).

    The structures' names, expected opacities and importances, the background, and (only for
    an analysis that does not record the parameters it was rendered with) the rendering
    opacities and colours; with the options.  ``None`` (nothing kept) for a calibration
    curve, an analysis the engine did not make or an option that cannot be a key.
    """
    if calibration is not None or not engine_made(analysis):
        return None
    try:
        s = spec.structures
        stats = getattr(analysis, "stats", None)
        own = isinstance(stats, dict) and stats.get("params") is not None
        key = (
            "transparency",
            tuple(spec.names),
            tuple(float(x.target_opacity) for x in s),
            tuple(float(x.importance) for x in s),
            tuple(float(v) for v in spec.background),
            None if own else tuple((float(x.render_opacity), tuple(x.colour)) for x in s),
            threshold, tolerance, contrast, enclosure,
        )  # fmt: skip
        hash(key)
    except (AttributeError, TypeError, ValueError):  # _core says what is wrong
        return None
    return key


def _core_kept(analysis, spec, threshold, calibration, tolerance, contrast, enclosure, *,
               keep=False):  # fmt: skip
    """:func:`_core`, shared by the optimiser's ``E_t`` and the measure of one rendering.

    The optimiser computes ``E_t`` of a rendering at the user's resolution
    (:func:`transparency_table` with ``keep``) and then measures the same rendering
    (:func:`transparency`): the layers, regions and estimates, with an enclosing layer's
    re-composites, are made once.  Only what ``keep`` made is reused (:func:`transparency`
    stores nothing), keyed by everything :func:`_core` reads (:func:`_core_key`); they are
    only read afterwards, and the notes are a new list each time.
    """
    args = (analysis, spec, threshold, calibration, tolerance, contrast, enclosure)
    key = _core_key(*args)
    if key is None:
        return _core(*args)
    if keep:

        def compute():
            names, expected, rmap, relations, est, notes = _core(*args)
            return names, expected, rmap, relations, est, tuple(notes)

        hit = _remembered(analysis, key, compute)
    else:
        hit = _recalled(analysis, key)
        if hit is None:
            return _core(*args)
    names, expected, rmap, relations, est, notes = hit
    return names, expected, rmap, relations, est, list(notes)


def _carried(analysis, spec, assigned: np.ndarray) -> Carried:
    """Opacity each structure carries on each pixel, occlusion ignored (D7).

    The occlusion-free opacity ``assigned`` (at the importance opacities) capped at
    :data:`~._layer_sets.PRESENCE_CAP`, where presence saturates (D8: the skipping walk is exact
    below it), and scaled by the structure's rendering opacity over its importance, so a
    structure the rendering fades is not taken for a hidden one.  A covered structure whose
    visible opacity is at most :data:`~._layer_sets.HIDDEN_FRACTION` of this is hidden there.
    Returns a :class:`~._layer_sets.Carried`: the opacities are made only on the covered
    pixels that are read.
    """
    importance = np.array([float(s.importance) for s in spec.structures])
    params = getattr(analysis, "stats", None)
    params = params.get("params") if isinstance(params, dict) else None
    if params is not None:
        render = np.asarray(params["opacities"], np.float64)
    else:
        render = np.array([float(s.render_opacity) for s in spec.structures])
    scale = np.divide(render, importance, out=np.ones_like(render), where=importance > 0)
    return Carried(assigned, scale)


def _occlusion_free(analysis, shape) -> np.ndarray | None:
    """Return the (K, H, W) occlusion-free opacity ``assigned``, or ``None`` without one.

    Hand-made analyses without the field, and engine analyses made with
    ``occlusion_free=False`` (``assigned`` is NaN there), keep visible footprints.
    """
    if getattr(analysis, "assigned", None) is None:
        return None
    if engine_made(analysis) and not analysis.stats.get("occlusion_free", True):
        return None
    return _assigned(analysis, shape, native=True)  # read in float64


def transparency_table(analysis, spec, *, calibration=None, keep=False):
    """E_t's ingredients as arrays, without the per-region records (for the optimiser).

    Returns ``(region_id, deltas, alpha_t, skip)``: the (H, W) region map, Eq. 10 per region,
    the (regions, K) calibrated transmittances (NaN: layer absent or undetermined) and the
    mask of the regions left out of ``E_t`` (empty, or all their layers undetermined); the
    other options are :func:`transparency`'s defaults.  ``keep``: remember the layers,
    regions and estimates of an engine analysis (without a calibration curve), so that
    :func:`transparency` of the same rendering (same names, expected opacities,
    importances and background) reuses them.
    """
    names, _, rmap, _, est, _ = _core_kept(
        analysis, spec, 0.05, calibration, 0.02, "michelson", "auto", keep=keep
    )  # fmt: skip
    alpha, empty = region_table(est, rmap, len(names))
    return rmap.region_id, est.deltas, alpha, empty


def transparency(
    analysis,
    spec,
    *,
    threshold: float = 0.05,
    calibration=None,
    tolerance: float = 0.02,
    contrast: str = "michelson",
    enclosure: str = "auto",
) -> TransparencyResult:
    """Transparency deviation ``E_t`` of a rendering (Eq. 5-11, rules of Sec. 4.3.2).

    Parameters
    ----------
    analysis : RayAnalysis
        Ray analysis with ``visible`` (K, H, W), ``accumulated`` (H, W), ``rgba`` (H, W, 4,
        premultiplied; or ``image``) and ``names``; with ``assigned`` (K, H, W) footprints
        are where the structures are (D3), and with ``cache`` an encloser without a usable
        plain view is read against the view without it.
    spec : StructureSpec
        Structures (names must match ``analysis.names``; ``target_opacity`` is the expected
        opacity) and the background colour entering the luminance.
    threshold : float, optional
        A structure is a layer of a pixel where its visible or its occlusion-free opacity
        exceeds this (default 0.05, see :func:`~.regions.layer_footprints`).
    calibration : pair of array_like (x, y), optional
        Knots of a monotone curve mapping measured to perceived transmittance (see
        :func:`~.psychophysics.calibrate`); ``None`` is the identity.
    tolerance : float, optional
        Footprint fraction forgiven by the layer relations (default 0.02).
    contrast : {"michelson", "range"}, optional
        TAP contrast: Michelson (Eq. 7, default) or luminance range (Eq. 6).
    enclosure : {"auto", "plain", "unoccluded"}, optional
        TAP background ``A`` of an enclosing layer: the covered pixels re-composited without
        the layer (default, decision D7: from the re-evaluation cache, or walked again for an
        engine analysis without one), its plain view where the re-composite is uniform; the
        plain view first (``"plain"``, the paper's Case 2); or always the re-composite
        (``"unoccluded"``, an error for an analysis the engine did not make).  See the
        module docstring, rule 3.

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
    names, expected, rmap, relations, est, notes = _core_kept(
        analysis, spec, threshold, calibration, tolerance, contrast, enclosure
    )
    deltas = est.deltas
    delta_list = deltas.tolist()
    area = np.array([r.area_fraction for r in rmap.regions], np.float64)
    # per layer set: the undetermined (region, layer) pairs and the determined transmittances
    pairs = []  # (region, position in its set's layers, name, reason)
    determined: dict[str, list] = {n: [] for n in names}  # (region ids, alpha_t) per set
    n_clipped = 0
    for ids, lays in est.sets:
        for pos, lay in enumerate(lays):
            name = names[lay.k]
            if lay.reason is not None:
                pairs.extend((r, pos, name, lay.reason) for r in ids.tolist())
                continue
            n_clipped += int(np.count_nonzero(np.asarray(lay.measured) != np.asarray(lay.raw)))
            determined[name].append((ids, np.asarray(lay.alpha_t, np.float64)))
    pairs.sort(key=lambda t: (t[0], t[1]))  # region by region, as the records list them
    undetermined = [{"region": r, "structure": n, "reason": why} for r, _, n, why in pairs]
    reasons: dict[str, list[str]] = {n: [] for n in names}
    for _, _, name, why in pairs:
        if why not in reasons[name]:
            reasons[name].append(why)

    if n_clipped:
        notes.append(f"{n_clipped} transmittance(s) outside [0, 1] were clipped (see 'clipped')")
    nonempty = [r for r in rmap.regions if r.kind != "empty"]
    counted = [r for r in nonempty if not est.undetermined[r.id]]
    if not nonempty:
        e_t = 0.0
        notes.append("no non-empty region (no layer above the threshold); E_t = 0")
    elif not counted:
        e_t = 0.0
    else:
        total_area = sum(r.area_fraction for r in counted)
        e_t = float(sum(r.area_fraction * delta_list[r.id] for r in counted) / total_area)
    if not any(determined.values()):
        notes.append("no region has a determinable layer transmittance; E_t = 0")

    per_structure = {}
    for k, name in enumerate(names):
        alpha = None
        if determined[name]:
            ids = np.concatenate([i for i, _ in determined[name]])
            order = np.argsort(ids, kind="stable")  # region order, as a loop over the regions
            ids = ids[order]
            weighted = area[ids] * np.concatenate([a for _, a in determined[name]])[order]
            total, covered = _in_order_sum(weighted), _in_order_sum(area[ids])
            alpha = total / covered if covered > 0 else None
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
        records=partial(_records, rmap, est, names, delta_list),
        relations=relation_out,
        per_structure=per_structure,
        undetermined=undetermined,
        notes=tuple(dict.fromkeys(notes)),
    )


def _in_order_sum(values: np.ndarray) -> float:
    """``0.0 + v[0] + v[1] + ...`` left to right, as a Python loop adds (no pairwise sum)."""
    return float(np.add.accumulate(values)[-1]) if values.size else 0.0


def _records(rmap, est, names, delta_list) -> list:
    """One dict per region (``TransparencyResult.regions``), made when first read."""
    regions = []
    positions = est.position.tolist()
    set_names: dict[frozenset, list[str]] = {}  # per layer set: its layers' names, in order
    for region in rmap.regions:
        layer_names = set_names.get(region.layers)
        if layer_names is None:
            layer_names = set_names[region.layers] = [names[k] for k in sorted(region.layers)]
        rid = region.id
        entry = {
            "id": rid,
            "layers": list(layer_names),
            "kind": region.kind,
            "area_fraction": region.area_fraction,
            "transmittance": {},
            "measured": {},
            "method": {},
            "clipped": {},
            "undetermined": {},
            "delta_t": delta_list[rid],
            "counted": region.kind != "empty" and not bool(est.undetermined[rid]),
        }
        p = positions[rid]
        for lay in est.layers[rid]:
            name = names[lay.k]
            if lay.reason is not None:
                entry["undetermined"][name] = lay.reason
                continue
            measured = lay.measured[p]
            if measured != lay.raw[p]:
                entry["clipped"][name] = lay.raw[p]
            entry["measured"][name] = measured
            entry["transmittance"][name] = lay.alpha_t[p]
            entry["method"][name] = lay.method[p]
        regions.append(entry)
    return regions
