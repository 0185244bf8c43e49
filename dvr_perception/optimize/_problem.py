"""The optimisation problem: rendering parameters, and the energy of Eq. 12 from cached rays.

:class:`Params` holds everything the stages may change (per-structure rendering opacity, Phong
material and colour, and the light direction).  :class:`Problem` owns one
:class:`~dvr_perception.rays.engine.RayCache` per view and evaluates the three measures for a
parameter set through :func:`~dvr_perception.rays.engine.reevaluate` (the volume is never
sampled again).  With a region mask, only the masked rays count:

* ``E_v`` and ``E_s``: mean per-pixel deviation over the masked non-empty pixels;
* ``E_t``: the area-weighted mean ``delta_t`` over the non-empty sub-regions that intersect the
  mask, each weighted by its area *inside* the mask;
* ``coverage``: mean accumulated opacity over the masked rays that carry assigned opacity (a
  set that does not depend on the parameters), kept above a floor when the user asks for one
  (``coverage_keep``; none by default, D1);
* ``luminance``: (K,) mean image luminance over each structure's **footprint**, weighted by
  its visible opacity (``sum visible_i Y / sum visible_i``), used to forbid "winning by
  darkening" in the lighting stage.

``terms(params, need=("E_v",))`` computes only the named measures (``E_v``, ``coverage`` and
``luminance`` always, they are cheap; the others are ``nan``): the stages' cheap objectives
for the finite-difference gradients.  The transparency measure is by far the most expensive term.

``E_v`` compares the visible opacity with the target opacity ``alpha_o = c * A_imp`` of
:func:`~dvr_perception.measures.visibility.target_composition` (decision D1; ``composition``
picks the importance or thickness composition).  A visibility target ``t`` of structure ``s``
replaces its composition ``c`` by ``t`` on the rays where it is present; the other structures'
compositions are rescaled to fill ``1 - t`` (and all are renormalised to sum to 1).  A
transparency target ``a`` sets the expected opacity of ``s`` to ``1 - a``.  With several views every
term is the mean over the views.

**Eq. 13.**  Every full evaluation also returns ``S``, the least-squares residue of Eq. 13
normalised by the pixel count: ``S = mean_r (w_v d_v(r) + w_s d_s(r) + w_t d_t(r))^2`` over
the counted rays (those that carry assigned opacity, inside the mask), with ``d_v(r)`` the
ray's visibility deviation ``sum_s |alpha_o - alpha_v|``, ``d_s`` the shape measure's
per-pixel deviation and ``d_t`` the ``delta_t`` of the pixel's region (0 outside the pixels
each measure counts), and the mean over the views.  The private entry ``_stack`` keeps, per
view, the (3, rays) deviations so that a stage can weigh them with its own (boosted) weights
(:func:`residue`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from dvr_perception._deprecation import renamed_keyword
from dvr_perception._numba import serial_below
from dvr_perception.errors import DVRWarning
from dvr_perception.measures import shape
from dvr_perception.measures.luminance import LUMA_WEIGHTS
from dvr_perception.measures.transparency import transparency_table
from dvr_perception.measures.visibility import target_composition
from dvr_perception.rays.engine import reevaluate
from dvr_perception.structures.spec import Lighting, StructureSpec

__all__ = ["TERMS", "Params", "Problem", "residue"]

TERMS = ("E_v", "E_s", "E_t")


@dataclass(frozen=True, eq=False)
class Params:
    """Rendering parameters: opacities (K,), lighting (K, 4), colours (K, 3), light (3,).

    ``colors`` (attribute, constructor and :meth:`replace` keyword) is a deprecated alias of
    ``colours``.
    """

    opacities: np.ndarray
    lighting: np.ndarray
    colours: np.ndarray
    light: np.ndarray

    @property
    def colors(self) -> np.ndarray:
        """Deprecated alias of ``colours``."""
        warnings.warn(
            "Params.colors is deprecated; use Params.colours", DeprecationWarning, stacklevel=2
        )
        return self.colours

    @classmethod
    def from_spec(cls, spec: StructureSpec) -> Params:
        s = spec.structures
        light = np.asarray(spec.rendering.light_direction, float)
        return cls(
            opacities=np.array([x.render_opacity for x in s], float),
            lighting=np.array(
                [
                    (
                        x.lighting.ambient,
                        x.lighting.diffuse,
                        x.lighting.specular,
                        x.lighting.specular_power,
                    )
                    for x in s
                ],
                float,
            ),
            colours=np.array([x.colour for x in s], float),
            light=light / np.linalg.norm(light),
        )

    @renamed_keyword("colors", "colours", name="Params.replace")
    def replace(self, **changes) -> Params:
        return replace(self, **{k: np.array(v, float) for k, v in changes.items()})

    def materials(self) -> tuple[Lighting, ...]:
        return tuple(Lighting(*(float(v) for v in row)) for row in self.lighting)

    def to_spec(self, spec: StructureSpec) -> StructureSpec:
        """``spec`` with these opacities, materials, colours and light direction."""
        structures = tuple(
            replace(
                s,
                opacity=float(self.opacities[k]),
                lighting=Lighting(*(float(v) for v in self.lighting[k])),
                colour=tuple(float(c) for c in self.colours[k]),
            )
            for k, s in enumerate(spec.structures)
        )
        rendering = replace(spec.rendering, light_direction=tuple(float(v) for v in self.light))
        return replace(spec, structures=structures, rendering=rendering)

    def toward(self, other: Params, t: float) -> Params:
        """Return the point a fraction ``t`` of the way from these parameters to ``other``.

        Opacities, materials and colours are mixed linearly; the light direction is mixed and
        renormalised.
        """
        light = (1.0 - t) * self.light + t * other.light
        return Params(
            opacities=(1.0 - t) * self.opacities + t * other.opacities,
            lighting=(1.0 - t) * self.lighting + t * other.lighting,
            colours=(1.0 - t) * self.colours + t * other.colours,
            light=light / max(float(np.linalg.norm(light)), 1e-12),
        )

    def same(self, other: Params) -> bool:
        return all(
            np.array_equal(getattr(self, f), getattr(other, f))
            for f in ("opacities", "lighting", "colours", "light")
        )


# ``Params(colors=...)`` keeps working for one release (a DeprecationWarning).
Params.__init__ = renamed_keyword("colors", "colours", name="Params")(Params.__init__)


class Problem:
    """Terms of Eq. 12 for parameter sets, over one or more cached views.

    Parameters
    ----------
    caches : list of RayCache
        One per view (built with the curvature volume).
    masks : list of (ndarray of bool or None)
        Region mask per view (``None``: the whole image).
    spec : StructureSpec
        The user's spec (names, importance, expected opacities, background).
    weights : ndarray, shape (3,)
        ``(w_v, w_s, w_t)``.
    targets : dict
        Parsed targets (see :func:`~._region.parse_targets`).
    calibration : pair of array_like or None
        Passed to :func:`~dvr_perception.measures.transparency`.
    composition : {"importance", "thickness"}
        Target composition of ``E_v`` (:func:`~dvr_perception.measures.visibility`).
    """

    def __init__(self, caches, masks, spec, weights, targets, calibration,
                 composition="importance") -> None:  # fmt: skip
        self.composition = composition
        self.importance = np.array([s.importance for s in spec.structures], float)
        self.caches, self.masks = list(caches), list(masks)
        self.spec, self.weights, self.calibration = spec, np.asarray(weights, float), calibration
        self.names = spec.names
        k = len(self.names)
        self.vis_target = np.full(k, np.nan)
        expected = []
        for i, s in enumerate(spec.structures):
            t = targets.get(s.name, {})
            if "visibility" in t:
                self.vis_target[i] = t["visibility"]
            expected.append(None if "transparency" not in t else 1.0 - t["transparency"])
        self.eval_spec = replace(
            spec,
            structures=tuple(
                s if e is None else replace(s, expected_opacity=e)
                for s, e in zip(spec.structures, expected, strict=True)
            ),
        )
        self.nfev = 0
        #: Remember transparency's layers, regions and estimates of each rendering, so that
        #: measuring the same rendering afterwards reuses them (the user's resolution).
        self.keep_transparency = False
        self._fixed = {}  # (view, whole) -> what does not depend on the parameters
        self._last = {}  # view -> (params, analysis) of the latest rendering

    def present(self) -> np.ndarray:
        """(K,) bool: structures met by some masked ray of some view."""
        k = len(self.names)
        bits = np.uint64(0)
        for cache, mask in zip(self.caches, self.masks, strict=True):
            p = cache.present if mask is None else cache.present[mask]
            bits |= np.bitwise_or.reduce(p.astype(np.uint64), axis=None)
        return np.array([bool(int(bits) >> i & 1) for i in range(k)])

    def presence_fraction(self) -> np.ndarray:
        """(K,) fraction of the masked rays (all views) on which each structure is present."""
        k = len(self.names)
        hits, total = np.zeros(k), 0
        for cache, mask in zip(self.caches, self.masks, strict=True):
            p = (cache.present if mask is None else cache.present[mask]).astype(np.uint64).ravel()
            hits += [np.count_nonzero((p >> np.uint64(i)) & np.uint64(1)) for i in range(k)]
            total += p.size
        return hits / max(total, 1)

    def copresence(self) -> np.ndarray:
        """(K, K) fraction of the counted rays (all views) on which both structures are present.

        Needs the fixed parts of every view (made by the first :meth:`terms`).
        """
        k = len(self.names)
        both, total = np.zeros((k, k)), 0
        for v in range(len(self.caches)):
            fixed = self._fixed.get((v, False)) or self._fixed.get((v, True))
            if fixed is None:
                continue
            p = fixed["present"].astype(np.float64)
            both += p @ p.T
            total += p.shape[1]
        return both / max(total, 1)

    def render(self, params: Params, view: int = 0):
        """Return the ray analysis of ``params`` in ``view`` (re-composited from the cache).

        A cache with a ``reevaluate`` method of its own (the MPI ranks' :class:`~dvr_perception.
        distributed.RankCache`) re-composites itself.  The latest rendering of each view is
        kept: the same parameters again (e.g. the final rendering after the re-check at the
        user's resolution) return it without compositing.
        """
        last = self._last.get(view)
        if last is not None and last[0].same(params):
            return last[1]
        cache = self.caches[view]
        kwargs = {
            "opacities": np.clip(params.opacities, 0.0, 1.0),
            "lighting": params.materials(),
            "colours": np.clip(params.colours, 0.0, 1.0),
            "light_direction": params.light,
        }
        if hasattr(cache, "reevaluate"):
            out = cache.reevaluate(**kwargs)
        else:
            out = reevaluate(cache, **kwargs)
        fields = ("opacities", "lighting", "colours", "light")
        self._last[view] = (Params(*(np.array(getattr(params, f)) for f in fields)), out)
        return out

    def terms(self, params: Params, *, whole=False, need=TERMS, analyses=None) -> dict:
        """Terms ``{E_v, E_s, E_t, E, S, coverage, luminance, visible_share, badness}``.

        Averaged over the views.  ``badness`` maps each term to a (K,) array of per-structure
        deviations (used by the annealing moves).  ``whole=True`` ignores the region masks;
        ``need`` names the measures to compute (the others, and ``E`` unless all three are
        computed, and ``S``, are ``nan``); ``analyses`` (one per view) are renderings of ``params``
        already at hand (e.g. from :func:`~dvr_perception.rays.engine.analyze`).
        """
        self.nfev += 1
        per_view, analyses_used = [], []
        for v, mask in enumerate(self.masks):
            analysis = self.render(params, v) if analyses is None else analyses[v]
            analyses_used.append(analysis)
            with warnings.catch_warnings():  # float32 rounding notes, once per evaluation
                warnings.simplefilter("ignore", DVRWarning)
                fixed = self._fixed_parts(v, analysis, None if whole else mask, whole)
                per_view.append(self._view_terms(analysis, fixed, set(need)))
        out = {key: float(np.mean([t[key] for t in per_view])) for key in (*TERMS, "coverage")}
        out["E"] = float(np.dot(self.weights, [out[t] for t in TERMS]))
        out["_stack"] = [t["stack"] for t in per_view]
        out["S"] = residue(out["_stack"], self.weights)
        out["luminance"] = np.mean([t["luminance"] for t in per_view], axis=0)
        if set(need) != set(TERMS):  # keep the renderings: complete() adds the other terms
            out["_analyses"], out["_whole"] = analyses_used, whole
        for key in ("visible_share", "target_share"):
            out[key] = {n: float(np.mean([t[key][n] for t in per_view])) for n in self.names}
        out["badness"] = {t: np.mean([p["badness"][t] for p in per_view], axis=0) for t in TERMS}
        return out

    def complete(self, params: Params, terms: dict) -> dict:
        """Return ``terms`` with every measure (from the kept renderings of a partial one)."""
        if "_analyses" not in terms:
            return terms
        self.nfev -= 1  # not a new rendering
        return self.terms(params, whole=terms["_whole"], analyses=terms["_analyses"])

    # -- one view ---------------------------------------------------------------------------
    def fixed_parts(self, v: int, params: Params) -> dict:
        """Return the masked parts of view ``v`` that do not depend on the parameters."""
        if (v, False) not in self._fixed:
            self._fixed_parts(v, self.render(params, v), self.masks[v], False)
        return self._fixed[(v, False)]

    def _fixed_parts(self, v, analysis, mask, whole) -> dict:
        """Mask, target opacities, counted rays and presence of view ``v``, computed once.

        ``target`` (K, counted rays) is ``alpha_o = c * A_imp`` with the lens targets in ``c``;
        ``target_share`` its image-wide share per structure over the counted rays.
        """
        key = (v, bool(whole))
        if key not in self._fixed:
            k = len(self.names)
            m = np.ones(analysis.accumulated.shape, bool) if mask is None else mask
            assigned = np.asarray(analysis.assigned, float)
            rays = (assigned.sum(axis=0) > 0) & m
            bits = np.asarray(analysis.present, np.uint64)[rays]
            present = (bits[None] >> np.arange(k, dtype=np.uint64)[:, None]) & 1 > 0
            c = target_composition(
                assigned[:, rays],
                self.importance,
                composition=self.composition,
                fixed=self.vis_target,
            )
            a_imp = np.asarray(analysis.importance_accumulated, float)[rays]
            target = c * np.clip(a_imp, 0.0, 1.0)[None]
            total = target.sum()
            share = target.sum(axis=1) / total if total > 0 else np.zeros(k)
            self._fixed[key] = {"m": m, "rays": rays, "present": present, "target": target,
                                "target_share": share, "count": present.sum(axis=1)}  # fmt: skip
        return self._fixed[key]

    def _view_terms(self, analysis, fixed, need) -> dict:
        k = len(self.names)
        m, rays = fixed["m"], fixed["rays"]
        # Eq. 2 as measures.visibility computes it (D1), with the lens targets in the target
        acc = np.asarray(analysis.accumulated, float)
        visible = np.asarray(analysis.visible)  # float32: selected first, then widened (exact)
        vm = visible[:, m].astype(float)  # (K, masked pixels), each row in pixel order
        acc_r = acc[rays]
        dev = np.abs(fixed["target"] - visible[:, rays].astype(float))
        d_v = dev.sum(axis=0)
        e_v = float(d_v.mean()) if acc_r.size else 0.0
        coverage = float(acc_r.mean()) if acc_r.size else 0.0
        present = fixed["present"]
        cnt = fixed["count"]
        bad_v = np.where(cnt > 0, (dev * present).sum(axis=1) / np.maximum(cnt, 1), 0.0)
        if "E_s" in need:
            v_share = np.clip(np.asarray(analysis.visible_share, float), 0.0, 1.0)
            with serial_below(acc.size):  # the optimiser's small images: no thread wake-ups
                e_s, bad_s, d_s = self._shape(analysis, m, v_share)
        else:
            e_s, bad_s, d_s = np.nan, np.full(k, np.nan), np.full(acc.shape, np.nan)
        if "E_t" in need:
            e_t, bad_t, d_t = self._transparency(analysis, m)
        else:
            e_t, bad_t, d_t = np.nan, np.full(k, np.nan), np.full(acc.shape, np.nan)
        acc_sum = float(acc[m].sum())
        shares = {  # a row of vm holds visible[i][m]'s numbers in its order: the same sums
            n: (float(vm[i].sum()) / acc_sum if acc_sum > 0 else 0.0)
            for i, n in enumerate(self.names)
        }
        lum = np.asarray(analysis.image, float) @ np.asarray(LUMA_WEIGHTS)
        vsum = vm.sum(axis=1)
        luminance = np.where(vsum > 0, (vm * lum[m]).sum(axis=1) / np.maximum(vsum, 1e-30), 0.0)
        return {
            "E_v": e_v,
            "E_s": e_s,
            "E_t": float(e_t),
            "coverage": coverage,
            "luminance": luminance,
            "visible_share": shares,
            "target_share": dict(zip(self.names, fixed["target_share"].tolist(), strict=True)),
            "badness": {"E_v": bad_v, "E_s": bad_s, "E_t": bad_t},
            "stack": np.stack([d_v, d_s[rays], d_t[rays]]),
        }

    def _shape(self, analysis, m, v_share):
        sh = shape(analysis, self.eval_spec)
        pix = sh.nonempty & m
        e_s = float(sh.deviation[pix].mean()) if pix.any() else 0.0
        wts = v_share[:, pix]
        w_sum = wts.sum(axis=1)
        bad_s = np.where(
            w_sum > 0, (wts * sh.deviation[pix]).sum(axis=1) / np.maximum(w_sum, 1e-12), 0.0
        )
        return e_s, bad_s, np.where(pix, sh.deviation, 0.0)

    def _transparency(self, analysis, m):
        """E_t, per-structure badness and per-pixel ``delta_t`` over the pixels of ``m``.

        Region areas are counted inside ``m``; the per-pixel map is the ``delta_t`` of the
        pixel's region (0 in empty regions and outside ``m``).

        Sums run region after region in id order (``np.add.accumulate`` adds in sequence), so
        the figures equal a loop over ``transparency(...).regions`` to the last bit.
        """
        k = len(self.names)
        region_id, deltas, alpha, empty = transparency_table(
            analysis, self.eval_spec, calibration=self.calibration, keep=self.keep_transparency
        )
        counts = np.bincount(region_id[m].ravel(), minlength=len(deltas)).astype(np.float64)
        keep = (counts > 0) & ~empty
        num = _in_order_sum(counts[keep] * deltas[keep])
        den = _in_order_sum(counts[keep])
        expected = np.array([s.target_opacity for s in self.eval_spec.structures])
        s_num, s_den = np.zeros(k), np.zeros(k)
        for i in range(k):
            sel = keep & ~np.isnan(alpha[:, i])
            s_num[i] = _in_order_sum(counts[sel] * (1.0 - alpha[sel, i] - expected[i]) ** 2)
            s_den[i] = _in_order_sum(counts[sel])
        e_t = num / den if den > 0 else 0.0
        bad_t = np.where(s_den > 0, s_num / np.maximum(s_den, 1e-12), 0.0)
        per_pixel = np.where(m & ~empty[region_id], deltas[region_id], 0.0)
        return e_t, bad_t, per_pixel


def residue(stacks, weights) -> float:
    """Eq. 13 per ray, normalised: the mean over views of ``mean_r (weights . d(r))^2``.

    ``stacks`` is the ``_stack`` entry of :meth:`Problem.terms` (per view, the (3, rays)
    deviations ``d_v``, ``d_s``, ``d_t``); ``weights`` the three term weights.  A view
    without counted rays contributes 0; ``nan`` when a needed deviation is missing.

    Examples
    --------
    >>> import numpy as np
    >>> round(residue([np.array([[0.5, 0.0], [0.2, 0.4], [0.0, 0.0]])], (1.0, 1.0, 1.0)), 6)
    0.325
    """
    w = np.asarray(weights, float)
    out = []
    for st in stacks:
        used = np.asarray(st)[w > 0]
        r = w[w > 0] @ used if used.size else np.zeros(np.asarray(st).shape[1])
        out.append(float(np.mean(r**2)) if r.size else 0.0)
    return float(np.mean(out)) if out else 0.0


def _in_order_sum(x: np.ndarray) -> float:
    """Sum of ``x`` added strictly in order (as a Python loop would), 0.0 when empty."""
    return float(np.add.accumulate(x)[-1]) if x.size else 0.0


def public_terms(terms: dict, names) -> dict:
    """Return a copy of ``terms`` without the ``badness`` arrays (``luminance`` by name)."""
    skip = ("badness", "visible_share", "target_share", "luminance")
    out = {k: v for k, v in terms.items() if k not in skip and not k.startswith("_")}
    out["visible_share"] = dict(terms["visible_share"])
    out["target_share"] = dict(terms["target_share"])
    out["luminance"] = {n: float(v) for n, v in zip(names, terms["luminance"], strict=True)}
    return out
