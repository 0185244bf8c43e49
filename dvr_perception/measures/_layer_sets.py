"""Layer sets of one image and the transmittance rules of Sec. 4.3.2 (used by ``transparency``).

:class:`_LayerSets` caches, per exact layer set, the pixel count, mean and standard deviation of the
luminance, so every Metelli (Eq. 5, 9) and TAP (Eq. 6-7) term is computed once per layer set
(or layer pair), not once per sub-region; only the Eq. 8 weight ``h = 1 - C`` depends on the
region (``C`` its contrast, Eq. 7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dvr_perception._numba import kernels
from dvr_perception.measures.psychophysics import (
    generalized_metelli,
    luminance_range,
    metelli_transmittance,
    tap_transmittance,
)

#: A Metelli denominator or a TAP background range below this (in luminance) is "~0".
DENOMINATOR_EPS = 1e-3
#: A covered structure is hidden on a pixel where its visible opacity is at most this fraction
#: of the opacity it carries there (D7: relative, not an absolute threshold).
HIDDEN_FRACTION = 0.1
#: The carried opacity is capped here, where presence saturates (D8).
PRESENCE_CAP = 0.7
#: A layer set covering less than this share of the image is no reference (D9): its mean and
#: contrast would rest on a handful of pixels, a number that changes with the image size.
MIN_REFERENCE_FRACTION = 1e-3


@dataclass(frozen=True)
class _Estimate:
    """A transmittance with its method, or the reason it is undetermined."""

    alpha: float = float("nan")
    method: str | None = None
    reason: str | None = None


def _group_stats(values: np.ndarray, group: np.ndarray, n: int):
    """Per-group pixel count, mean and two-pass population std (exactly 0 on uniform groups).

    ``values`` and ``group`` are flat; the numba twin (:func:`._kernels.group_stats`) is used
    when numba is there, the numpy code below otherwise (the same numbers to the last bit).
    """
    kernel = _numba_group_stats()
    if kernel is not None:
        return kernel(np.ascontiguousarray(values, np.float64), np.ascontiguousarray(group), n)
    return _group_stats_numpy(values, group, n)


def _numba_group_stats():
    module = kernels("dvr_perception.measures._kernels")
    return None if module is None else module.group_stats


def _group_stats_numpy(values: np.ndarray, group: np.ndarray, n: int):
    count = np.bincount(group, minlength=n)
    safe = np.maximum(count, 1)
    mean = np.bincount(group, weights=values, minlength=n) / safe
    dev = values - mean[group]
    std = np.sqrt(np.bincount(group, weights=dev * dev, minlength=n) / safe)
    return count, mean, std


def _robust(mu: float, sigma: float, i_max: float = 1.0) -> tuple[float, float]:
    """Robust luminance range from mean and std, as :func:`~.psychophysics.luminance_range`."""
    return max(0.0, float(mu) - 2.0 * float(sigma)), min(i_max, float(mu) + 2.0 * float(sigma))


def _contrast(lo: float, hi: float, kind: str) -> float:
    if kind == "range":
        return hi - lo
    return (hi - lo) / (hi + lo) if hi + lo > 0 else 0.0


def _blend(met: float, tap: float, contrast: float) -> float:
    """Scalar :func:`~.psychophysics.blended_transmittance` (Eq. 8, ``h = 1 - C``), unchecked."""
    if math.isnan(met):
        return tap
    if math.isnan(tap):
        return met
    h = 1.0 - contrast
    return h * met + (1.0 - h) * tap


def transmitted_tap(lum_p: np.ndarray, lum_a: np.ndarray, contrast: str) -> float:
    """TAP ``C(P) / C(A)`` of the same pixels seen with (``lum_p``) and without a layer.

    Only the contrast the layer *transmits* counts (D7: its own shading texture is not
    transmitted contrast): ``P``'s luminance is regressed on ``A``'s, ``P ~ c + b A``, and
    ``P``'s robust range is that of its mean with the standard deviation ``max(b, 0)
    sigma(A)`` of the transmitted part.  For a uniform layer (``P = T A + c`` exactly) that
    is ``P``'s own standard deviation, so the reading is the plain TAP.  NaN when ``A`` has
    no luminance range (below ``DENOMINATOR_EPS``) or no contrast.
    """
    lum_p = np.asarray(lum_p, np.float64).ravel()
    lum_a = np.asarray(lum_a, np.float64).ravel()
    mean_a, std_a = float(lum_a.mean()), float(lum_a.std())
    lo_a, hi_a = _robust(mean_a, std_a)
    if hi_a - lo_a < DENOMINATOR_EPS:
        return float("nan")
    c_a = _contrast(lo_a, hi_a, contrast)
    if c_a < 1e-6:
        return float("nan")
    mean_p = float(lum_p.mean())
    slope = float(np.mean((lum_p - mean_p) * (lum_a - mean_a))) / (std_a * std_a)
    return _contrast(*_robust(mean_p, max(slope, 0.0) * std_a), contrast) / c_a


@dataclass(frozen=True)
class Carried:
    """Opacity the structures carry, occlusion ignored (D7): ``min(assigned, cap) * scale``.

    ``assigned`` (K, H, W) is the occlusion-free opacity (float32 or float64, read in
    float64), capped at :data:`PRESENCE_CAP` and scaled per structure by ``scale`` (K,) (see
    :func:`~.transparency._carried`).  Read only where needed, on the covered pixels
    (:meth:`on`), not made for the whole (K, H, W) stack.
    """

    assigned: np.ndarray
    scale: np.ndarray

    def on(self, layers, pix: np.ndarray) -> np.ndarray:
        """Return the carried opacity of ``layers`` on the flat pixels ``pix`` (layers, pixels)."""
        k = self.assigned.shape[0]
        layers = np.asarray(layers, np.intp).reshape(-1)
        on = self.assigned.reshape(k, -1)[np.ix_(layers, pix)].astype(np.float64)
        return np.minimum(on, PRESENCE_CAP) * self.scale[layers][:, None]


def _bits(layers) -> int:
    out = 0
    for k in layers:
        out |= 1 << int(k)
    return out


class _LayerSets:
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
        self._pairs: dict[tuple[int, int, int], tuple] = {}
        self._general: dict[tuple[int, int, int], _Estimate] = {}
        self._plans: dict[frozenset, tuple] = {}
        self._templates: dict[frozenset, tuple] = {}
        #: ``enclosure="unoccluded"``: per enclosing layer, the luminance without it.
        self.without: dict[int, np.ndarray] | None = None
        #: (K, H, W) visible opacities, and the carried (occlusion-free, capped) opacities
        #: (:class:`Carried`): a
        #: covered layer whose visible opacity is at most ``HIDDEN_FRACTION`` of what it
        #: carries on a pixel is hidden there (D3, D7); ``None``: footprints are visible
        #: ones, nothing covered is hidden.
        self.visible: np.ndarray | None = None
        self.carry = None
        #: Luminance of the view without layer ``e`` on the pixels of a mask
        #: (``recomposite(e, mask)``, computed once per layer: exact on ``mask``), or ``None``
        #: when the analysis has no re-evaluation cache; ``prefer``: an
        #: encloser's TAP background is that view first (D3), else only when its plain view
        #: is missing or uniform.
        self.recomposite = None
        #: ``recomposite`` of several layers at once (``{layer: mask}`` to ``{layer:
        #: luminance}``, :meth:`prefetch`), or ``None``.
        self.recomposite_many = None
        self.prefer_recomposite = False
        self._recomposited: dict[int, np.ndarray] = {}
        self._covers: dict[int, tuple | None] = {}
        # per layer set: pixel count, mean and (two-pass) population std of the luminance
        flat = self.layer_set.ravel()
        if k <= 16:  # layer sets index a table directly: no sort
            count, mean, std = _group_stats(self.y.ravel(), flat, 1 << k)
            sets = np.flatnonzero(count)
            count, mean, std = count[sets], mean[sets], std[sets]
        else:
            sets, inverse = np.unique(flat, return_inverse=True)
            count, mean, std = _group_stats(self.y.ravel(), inverse, sets.size)
        #: Pixels a layer set needs to be a reference (``MIN_REFERENCE_FRACTION``, at least 1).
        self.min_count = max(1, math.ceil(MIN_REFERENCE_FRACTION * self.layer_set.size))
        rows = zip(sets.tolist(), count.tolist(), mean.tolist(), std.tolist(), strict=True)
        self._stats = {b: (n, m, d) for b, n, m, d in rows}

    def label(self, bits: int) -> str:
        names = [n for k, n in enumerate(self.names) if bits >> k & 1]
        return "{" + ", ".join(names) + "}"

    def mask(self, bits: int) -> np.ndarray:
        if bits not in self._masks:
            self._masks[bits] = self.layer_set == np.uint32(bits)
        return self._masks[bits]

    def missing(self, sets) -> str | None:
        """Why some of ``sets`` are no reference (absent or below the minimum area), or None."""
        absent = [self.label(b) for b in sets if b not in self._stats]
        small = [
            self.label(b) for b in sets if b in self._stats and self._stats[b][0] < self.min_count
        ]
        why = []
        if absent:
            why.append(
                "no region shows exactly the layer set(s) " + ", ".join(dict.fromkeys(absent))
            )
        if small:
            why.append(
                f"the layer set(s) {', '.join(dict.fromkeys(small))} cover less than "
                f"{MIN_REFERENCE_FRACTION:.1%} of the image"
            )
        return "; ".join(why) if why else None

    def mean(self, bits: int) -> float:
        return self._stats[bits][1]

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
        """Return an encloser's transmittance: TAP over what it covers, hidden pixels as 0.

        ``P`` are the pixels where ``e`` and a layer it encloses are present.  Where the
        enclosed layers are hidden (their visible opacity at most the threshold although they
        are present: D3), the layer lets nothing of them through: transmittance 0 there.  The
        rest, ``P'``, is read by TAP against the plain view of ``e`` and its enclosers (the
        paper's Case 2, ``enclosure="plain"``) or against the same pixels re-composited
        without ``e`` (``"unoccluded"``; ``"auto"`` when the analysis can be re-composited);
        each is the fallback of the other where that is missing or uniform (the re-composite
        only with a cache).  The estimate is
        the mean over ``P``: ``|P'| / |P| * TAP``, and 0 (method ``"hidden"``) when everything
        covered is hidden or only the hidden part can be read.
        """
        head = f"enclosing layer {self.names[e]}: "
        covered = self._covered(e)
        if covered is None:
            return _Estimate(reason=head + "no pixel shows it with a layer it encloses")
        covered, n_covered, shown, n_shown = covered
        if n_shown == 0:
            return _Estimate(alpha=0.0, method="hidden")
        alpha, why = self._encloser_tap(e, shown)
        if why is not None:
            if n_shown < n_covered:  # only the hidden part can be read: opaque there
                return _Estimate(alpha=0.0, method="hidden")
            return _Estimate(reason=head + why)
        return _Estimate(alpha=alpha * (n_shown / n_covered), method="tap")

    def _covered(self, e: int):
        """``(P, |P|, P', |P'|)`` of encloser ``e`` (see :meth:`_encloser`), or None without P.

        ``P`` (covered) and ``P'`` (shown: what ``e`` covers is seen there) as (H, W) masks;
        worked out once per layer.
        """
        if e not in self._covers:
            self._covers[e] = self._covered_pixels(e)
        return self._covers[e]

    def _covered_pixels(self, e: int):
        """:meth:`_covered`, worked out."""
        inner_layers = np.flatnonzero(self.encloses[e])
        inner = _bits(inner_layers)
        # the layer sets with e and an enclosed layer, looked up among the sets in the image
        sets = [b for b in self._stats if b >> e & 1 and b & inner]
        if not sets:
            return None
        if len(self.names) <= 16:  # layer sets index a table directly
            table = np.zeros(1 << len(self.names), bool)
            table[sets] = True
            covered = table[self.layer_set]
        else:
            covered = np.isin(self.layer_set, np.array(sets, self.layer_set.dtype))
        n_covered = int(np.count_nonzero(covered))
        shown = covered
        if self.visible is not None:  # D3: pixels where what e covers is not seen
            pix = np.flatnonzero(covered)
            seen = self.seen(inner_layers, pix)
            shown = np.zeros(covered.shape, bool)
            shown.ravel()[pix[seen]] = True
        return covered, n_covered, shown, int(np.count_nonzero(shown))

    def prefetch(self, layer_sets) -> None:
        """Make at once the re-composites that the estimates of ``layer_sets`` will read first.

        With ``prefer_recomposite`` every enclosing layer of these sets (:meth:`_plan`) reads
        its TAP against its shown pixels re-composited without it (:meth:`_tap_without`);
        ``recomposite_many`` makes them all in one call (one walk of the union of their
        pixels for an analysis without a cache): the same luminance as one
        ``recomposite`` per layer.
        """
        if self.recomposite_many is None or not self.prefer_recomposite or self.without:
            return
        enclosers = sorted(set().union(*(self._plan(frozenset(ls))[0] for ls in layer_sets)))
        wanted = {}
        for e in enclosers:
            if e in self._recomposited:
                continue
            covered = self._covered(e)
            if covered is not None and covered[3] > 0:
                wanted[e] = covered[2]
        if wanted:
            self._recomposited.update(self.recomposite_many(wanted))

    def seen(self, layers, pix: np.ndarray) -> np.ndarray:
        """Whether ``layers`` (together) are seen on the flat pixels ``pix`` (D3, D7).

        Hidden where their summed visible opacity is at most ``HIDDEN_FRACTION`` of the
        opacity they carry there (:func:`~.transparency._carried`).
        """
        k = self.visible.shape[0]
        nk = kernels("dvr_perception.measures._kernels")
        if nk is not None:  # the sums below, per pixel, in one pass
            return nk.seen_on(
                np.ascontiguousarray(self.visible).reshape(k, -1),
                np.ascontiguousarray(self.carry.assigned).reshape(k, -1),
                np.asarray(self.carry.scale, np.float64),
                np.asarray(layers, np.int64).reshape(-1),
                np.asarray(pix, np.int64),
                PRESENCE_CAP,
                HIDDEN_FRACTION,
            )
        vis = self.visible.reshape(k, -1)[np.ix_(layers, pix)].astype(np.float64).sum(axis=0)
        carry = self.carry.on(layers, pix).sum(axis=0)
        return (vis > HIDDEN_FRACTION * carry) | (carry <= 0.0)

    def _encloser_tap(self, e: int, shown: np.ndarray) -> tuple[float, str | None]:
        """TAP of ``e`` on the pixels ``shown``: ``(alpha, None)`` or ``(nan, reason)``."""
        lum_p = self.y[shown]
        if self.without is not None:  # enclosure="unoccluded": the same pixels without e
            alpha = transmitted_tap(lum_p, self.without[e][shown], self.contrast)
            if math.isnan(alpha):
                return alpha, "what it covers has no contrast without it (TAP denominator ~0)"
            return alpha, None
        readings = [self._tap_plain, self._tap_without]
        if self.prefer_recomposite:
            readings.reverse()
        reasons = []
        for reading in readings:
            alpha, why = reading(e, shown, lum_p)
            if why is None:
                return alpha, None
            if why:
                reasons.append(why)
        return float("nan"), "; ".join(reasons)

    def _tap_plain(self, e: int, shown: np.ndarray, lum_p: np.ndarray):
        """Read the paper's Case 2: TAP against the plain view of ``e`` (and its enclosers)."""
        plain = _bits([e, *np.flatnonzero(self.encloses[:, e])])
        why = self.missing([plain])
        if why is not None:
            return float("nan"), why
        alpha = self.tap(lum_p, self.y[self.mask(plain)])
        if math.isnan(alpha):
            return alpha, (
                f"its plain view {self.label(plain)} has no luminance contrast (TAP denominator ~0)"
            )
        return alpha, None

    def _tap_without(self, e: int, shown: np.ndarray, lum_p: np.ndarray):
        """Read D3's TAP against the same pixels without ``e`` (reason "" without a cache)."""
        if self.recomposite is None:
            return float("nan"), ""
        if e not in self._recomposited:  # read on ``shown`` only: those rays re-composited
            self._recomposited[e] = self.recomposite(e, shown)
        alpha = transmitted_tap(lum_p, self._recomposited[e][shown], self.contrast)
        if math.isnan(alpha):
            return alpha, "what it covers has no luminance contrast without it"
        return alpha, None

    def _pair_terms(self, i: int, j: int, base: int) -> tuple:
        """``(metelli, tap, reason, shown)`` of Eq. 8 for ``i`` over ``j``; cached.

        Region-independent.  D3 for every layer (D7): on the pixels of ``P`` where ``j`` is
        hidden, ``i`` lets nothing of it through (transmittance 0), so both terms are read on
        the rest ``P'`` and scaled by its share ``shown = |P'| / |P|`` (0: ``j`` is hidden
        on all of ``P``).  ``i``'s own texture is not transmitted contrast: TAP's contrast of
        ``P'`` keeps only the luminance variance that ``i``'s plain view ``Q`` lacks
        (``sigma^2(P') - sigma^2(Q)``, at least 0).
        """
        key = (i, j, base)
        if key not in self._pairs:
            p, q, a, b = base | 1 << i | 1 << j, base | 1 << i, base | 1 << j, base
            why = self.missing([p, q, a, b])
            if why is not None:
                self._pairs[key] = (None, None, f"Eq. 8 with {self.names[j]}: {why}", 1.0)
                return self._pairs[key]
            n_p, mean_p, std_p = self._stats[p]
            shown = 1.0
            if self.visible is not None:
                pix = np.flatnonzero(self.mask(p))
                seen = self.seen([j], pix)
                n_seen = int(np.count_nonzero(seen))
                shown = n_seen / n_p
                if n_seen == 0:
                    self._pairs[key] = (0.0, 0.0, None, 0.0)
                    return self._pairs[key]
                if n_seen < n_p:
                    lum = self.y.ravel()[pix[seen]]
                    mean_p, std_p = float(lum.mean()), float(lum.std())
            met = float(
                metelli_transmittance(
                    mean_p, self.mean(q), self.mean(a), self.mean(b), eps=DENOMINATOR_EPS
                )
            )
            own = self._stats[q][2]
            transmitted = math.sqrt(max(std_p * std_p - own * own, 0.0))
            tap = self._tap_stats(mean_p, transmitted, a)
            why = None
            if math.isnan(met) and math.isnan(tap):
                why = (
                    f"Eq. 8 with {self.names[j]}: Metelli denominator I{self.label(a)} - "
                    f"I{self.label(b)} and TAP contrast of {self.label(a)} are ~0"
                )
            self._pairs[key] = (met * shown, tap * shown, why, shown)
        return self._pairs[key]

    def _tap_stats(self, mean_p: float, std_p: float, a: int) -> float:
        """TAP ``C(P) / C(A)`` from ``P``'s mean and std and the cached stats of set ``a``."""
        lo_a, hi_a = _robust(*self._stats[a][1:])
        if hi_a - lo_a < DENOMINATOR_EPS:
            return float("nan")
        c_a = _contrast(lo_a, hi_a, self.contrast)
        if c_a < 1e-6:
            return float("nan")
        return _contrast(*_robust(mean_p, std_p), self.contrast) / c_a

    def generalized(self, i: int, active: list[int], base: int) -> _Estimate:
        """Eq. 9 for layer ``i`` of three or more overlapping active layers (cached)."""
        key = (i, _bits(active), base)
        if key not in self._general:
            self._general[key] = self._generalized(i, active, base)
        return self._general[key]

    def _generalized(self, i: int, active: list[int], base: int) -> _Estimate:
        every = _bits(active)
        sets = [base | every, base | 1 << i, base | (every & ~(1 << i)), base]
        why = self.missing(sets)
        if why is not None:
            return _Estimate(reason=f"Eq. 9: {why}")
        alpha = float(generalized_metelli(*(self.mean(s) for s in sets), eps=DENOMINATOR_EPS))
        if math.isnan(alpha):
            return _Estimate(
                reason=f"Eq. 9: denominator I{self.label(sets[2])} - I{self.label(sets[3])} ~0"
            )
        return _Estimate(alpha=alpha, method="generalized")

    def _plan(self, layers: frozenset) -> tuple:
        """``(enclosing layers, active layers, enclosing bits)`` of a layer set (cached)."""
        if layers not in self._plans:
            enc = {
                e
                for e in layers
                if self.encloses[e].any()
                and all(self.encloses[e, k] or self.encloses[k, e] for k in layers - {e})
            }
            self._plans[layers] = (sorted(enc), sorted(layers - enc), _bits(enc))
        return self._plans[layers]

    def evaluate(self, layers: frozenset, region_range: tuple, notes: list[str]):
        """Estimates ``{layer: _Estimate}`` for the layers of one region (Case 1-3).

        Which rule applies, and every term except the Eq. 8 weight, depends on the layer set
        only: that is worked out once per set (:meth:`_template`); a region adds its robust
        luminance range ``region_range``, whose contrast (Eq. 7, or the range with
        ``contrast="range"``) gives the Eq. 8 weight ``h = 1 - C``.
        The measure evaluates all regions of a set at once
        (:func:`~dvr_perception.measures._estimates.region_estimates`); this per-region form
        is its reference (``tests/measures/test_estimates.py``).
        """
        items, tpl_notes = self.template(layers)
        notes.extend(tpl_notes)
        out = {}
        for k, fixed, met, tap in items:
            if fixed is None:
                fixed = self._blended(met, tap, _contrast(*region_range, self.contrast))
            out[k] = fixed
        return out

    def template(self, layers: frozenset) -> tuple[list, list[str]]:
        """:meth:`_template` of a layer set, worked out once."""
        tpl = self._templates.get(layers)
        if tpl is None:
            tpl = self._templates[layers] = self._template(layers)
        return tpl

    @staticmethod
    def _blended(met: float, tap: float, contrast: float) -> _Estimate:
        """Eq. 8 for one pair's Metelli and TAP terms with the region's contrast ``C``."""
        alpha = _blend(met, tap, contrast)
        if math.isnan(tap) or contrast == 0.0:
            method = "metelli"
        elif math.isnan(met) or contrast >= 1.0:
            method = "tap"
        else:
            method = "blend"
        return _Estimate(alpha=alpha, method=method)

    def _template(self, layers: frozenset) -> tuple[list, list[str]]:
        """Per layer ``(k, estimate or None, metelli, tap)`` of a layer set, and its notes.

        ``None``: an Eq. 8 pair whose blend depends on the region's range.
        """
        enc, active, base = self._plan(layers)
        items: list = [(e, self.encloser(e), None, None) for e in enc]
        notes: list[str] = []

        def pair_item(i, j):
            met, tap, why, shown = self._pair_terms(i, j, base)
            if why is not None:
                return (i, _Estimate(reason=why), None, None)
            if shown == 0.0:  # what i overlaps is hidden wherever they overlap (D3, D7)
                return (i, _Estimate(alpha=0.0, method="hidden"), None, None)
            return (i, None, met, tap)

        if len(active) == 1:
            i = active[0]
            reasons = []
            for j in self.partners[i]:
                item = pair_item(i, j)
                if item[1] is None or item[1].reason is None:
                    items.append(item)
                    break
                reasons.append(item[1].reason)
            else:
                if reasons:
                    items.append((i, _Estimate(reason="; ".join(reasons)), None, None))
        elif len(active) == 2:
            i, j = active
            if self.kind.get((i, j)) == "overlap":
                items.append(pair_item(i, j))
                items.append(pair_item(j, i))
            else:
                notes.append(
                    f"layers {self.names[i]} and {self.names[j]} share a region but are "
                    f"{self.kind.get((i, j), 'unrelated')}; treated as Case 1 there"
                )
        elif len(active) >= 3:
            items.extend((i, self.generalized(i, active, base), None, None) for i in active)
        return items, notes
